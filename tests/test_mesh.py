"""`dmd_jax.mesh`: validation, MeshGraph construction, batching, canonical frame and I/O.

MeshGraph index arrays are checked against matrices built independently from the faces
with scipy.sparse: with the incidence `B = A_FV`, vertices are adjacent iff `B^T B > 0`
off the diagonal, faces iff `B B^T >= 2` (they share two vertices, hence an edge).
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from conftest import NEEDS_SHARED, SHARED_MESHES, icosphere, shared_mesh_path, tetrahedron

from dmd_jax import ops
from dmd_jax.graph import (
    MeshGraph,
    PaddedSizes,
    batch_mesh_graphs,
    bucket_size,
    build_mesh_graph,
    face_adjacency,
    fine_padded_sizes_for,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    undirected_vertex_edges,
    vertex_edges,
)
from dmd_jax.io import atomic_write, load_mesh, save_mesh
from dmd_jax.mesh import CanonicalFrame, canonical_frame, mean_edge_length, validate_mesh

# --------------------------------------------------------------------------------------
# Independent references
# --------------------------------------------------------------------------------------


def incidence(faces, n_vertex):
    f = np.asarray(faces)
    rows = np.repeat(np.arange(f.shape[0]), 3)
    return sp.csr_matrix((np.ones(f.size), (rows, f.ravel())), shape=(f.shape[0], n_vertex))


def reference_adjacency(faces, n_vertex):
    """`(A_V, A_F)` without self loops, as boolean scipy CSR matrices."""
    b = incidence(faces, n_vertex)
    a_v = (b.T @ b).tocsr() > 0
    a_f = (b @ b.T).tocsr() >= 2
    a_v.setdiag(False)
    a_f.setdiag(False)
    a_v.eliminate_zeros()
    a_f.eliminate_zeros()
    return a_v, a_f


def gcn_weights(adjacency):
    a_hat = (adjacency + sp.identity(adjacency.shape[0], format="csr")).astype(np.float64)
    d = np.asarray(a_hat.sum(axis=1)).ravel()
    inv = sp.diags(1.0 / np.sqrt(d))
    return (inv @ a_hat @ inv).tocsr()


def edge_matrix(senders, receivers, weight, n):
    """Weighted edge list as a CSR matrix indexed `[receiver, sender]`, duplicates summed."""
    return sp.csr_matrix((np.asarray(weight, np.float64), (receivers, senders)), shape=(n, n))


def check_graph(graph: MeshGraph, faces, n_vertex):
    """Every structural promise of `build_mesh_graph`, against the references."""
    n_face = len(faces)
    a_v, a_f = reference_adjacency(faces, n_vertex)
    for senders, receivers, weight, adjacency, n in (
        (graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight, a_v, n_vertex),
        (graph.face_senders, graph.face_receivers, graph.face_edge_weight, a_f, n_face),
    ):
        assert senders.dtype == receivers.dtype == np.int32
        assert np.all(np.diff(receivers) >= 0), "receivers must be sorted"
        pairs = receivers.astype(np.int64) * n + senders
        assert np.unique(pairs).size == pairs.size, "duplicate edges"
        m = edge_matrix(senders, receivers, weight, n)
        assert abs(m - m.T).max() == 0.0, "weights must be symmetric"
        expected = gcn_weights(adjacency)
        assert m.nnz == expected.nnz == adjacency.nnz + n
        assert ((m != 0) != (expected != 0)).nnz == 0, "wrong sparsity pattern"
        # Weights are float32 and at most 1.
        assert abs(m - expected).max() < 1e-7
    np.testing.assert_array_equal(
        graph.vertex_face_degree, np.bincount(np.ravel(faces), minlength=n_vertex)
    )
    np.testing.assert_array_equal(graph.faces, faces)
    assert graph.n_vertex == n_vertex and graph.n_face == n_face and graph.n_graph == 1
    assert graph.vertex_mask.all() and graph.face_mask.all()


# --------------------------------------------------------------------------------------
# validate_mesh
# --------------------------------------------------------------------------------------

_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
_F = np.array([[0, 1, 2], [0, 3, 1]])


@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        (np.zeros((0, 3)), _F, "no vertices"),
        (_V, np.zeros((0, 3), np.int64), "no faces"),
        (np.where(np.arange(12).reshape(4, 3) == 4, np.nan, _V), _F, "NaN or infinite"),
        (np.where(np.arange(12).reshape(4, 3) == 7, -np.inf, _V), _F, "NaN or infinite"),
        (_V, np.array([[0, 1, 4]]), "out of range"),
        (_V, np.array([[0, -1, 2]]), "negative"),
        (_V[:, :2], _F, r"vertices must have shape \[n_vertex, 3\]"),
        (_V.ravel(), _F, r"vertices must have shape \[n_vertex, 3\]"),
        (_V, _F.ravel(), r"faces must have shape \[n_face, 3\]"),
        (_V, np.array([[0, 1, 2, 3]]), "polygons with 4 corners"),
        (_V, np.array([[0.0, 1.5, 2.0]]), "non-integral"),
        (_V, np.array([[0.0, np.nan, 2.0]]), "non-integral"),
        (_V, np.array([[0, 1, 1]]), "repeat a vertex index"),
        (_V, np.array([[2, 1, 2]]), "repeat a vertex index"),
        (_V.astype(complex), _F, "real numbers"),
        (_V, np.array([["a", "b", "c"]]), "integers"),
        (np.array([[0, 0], [1, 1, 1]], dtype=object), _F, "ragged"),
    ],
)
def test_validate_mesh_names_the_problem(vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        validate_mesh(vertices, faces, name="bad.obj")
    with pytest.raises(ValueError, match="bad.obj"):
        validate_mesh(vertices, faces, name="bad.obj")


def test_validate_mesh_accepts_and_converts():
    v, f = validate_mesh(_V.astype(np.int16), _F.astype(np.float32))
    assert v.dtype == np.float64 and f.dtype == np.int32
    np.testing.assert_array_equal(v, _V)
    np.testing.assert_array_equal(f, _F)
    # Copies: the caller's arrays are never aliased.
    src = _V.copy()
    v, _ = validate_mesh(src, _F)
    v[0, 0] = 9.0
    assert src[0, 0] == 0.0


# --------------------------------------------------------------------------------------
# MeshGraph on awkward meshes
# --------------------------------------------------------------------------------------


def test_graph_of_tetrahedron_and_icosphere():
    for v, f in (tetrahedron(), icosphere(2)):
        check_graph(build_mesh_graph(f, len(v)), f, len(v))
    graph = build_mesh_graph(tetrahedron()[1], 4)
    # Complete graph K4 plus loops: every weight is 1/sqrt(4 * 4).
    np.testing.assert_allclose(graph.vertex_edge_weight, 0.25)
    np.testing.assert_allclose(graph.face_edge_weight, 0.25)


def test_non_manifold_edge_connects_all_its_faces():
    # Three faces on edge (0, 1), plus a fourth face hanging off face 0's edge (1, 2).
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 5, 2]])
    graph = build_mesh_graph(faces, 6)
    check_graph(graph, faces, 6)
    dual = set(zip(graph.face_senders.tolist(), graph.face_receivers.tolist(), strict=True))
    fan = {(a, b) for a in range(3) for b in range(3)}
    assert fan <= dual  # 0, 1, 2 mutually adjacent (and self loops)
    assert {(0, 3), (3, 0), (3, 3)} <= dual
    assert not {(1, 3), (2, 3)} & dual
    a, b = face_adjacency(faces, 6)
    assert set(zip(a.tolist(), b.tolist(), strict=True)) == {(0, 1), (0, 2), (1, 2), (0, 3)}
    # Face 0 has degree 4 in Â (three neighbours + itself), faces 1 and 2 have 3.
    m = edge_matrix(graph.face_senders, graph.face_receivers, graph.face_edge_weight, 4)
    np.testing.assert_allclose(m[0, 1], 1 / np.sqrt(4 * 3), rtol=1e-7)
    np.testing.assert_allclose(m[1, 2], 1 / 3, rtol=1e-7)


def test_isolated_vertices_get_a_self_loop_only():
    v, f = tetrahedron()
    n_vertex = 7  # vertices 4, 5, 6 are in no face
    graph = build_mesh_graph(f, n_vertex)
    check_graph(graph, f, n_vertex)
    for i in (4, 5, 6):
        rows = graph.vertex_receivers == i
        np.testing.assert_array_equal(graph.vertex_senders[rows], [i])
        np.testing.assert_array_equal(graph.vertex_edge_weight[rows], [1.0])
        assert graph.vertex_face_degree[i] == 0
    d2p = ops.dual_to_primal(np.ones((4, 2)), graph.faces, graph.vertex_face_degree)
    np.testing.assert_array_equal(d2p[4:], 0.0)
    np.testing.assert_array_equal(d2p[:4], 1.0)
    # An isolated vertex keeps its own feature under aggregation (weight 1, self only).
    x = np.arange(14.0).reshape(7, 2)
    np.testing.assert_allclose(ops.primal_aggregate(graph, x)[4:], x[4:])


def test_several_components_stay_disconnected():
    v1, f1 = tetrahedron()
    v2, f2 = icosphere(1)
    faces = np.concatenate([f1, f2 + 4])
    n = 4 + len(v2)
    graph = build_mesh_graph(faces, n)
    check_graph(graph, faces, n)
    assert ((graph.vertex_senders < 4) == (graph.vertex_receivers < 4)).all()
    assert ((graph.face_senders < 4) == (graph.face_receivers < 4)).all()


def _grid(nx, ny):
    """An open `nx × ny` planar grid of quads split into triangles."""
    x, y = np.meshgrid(np.arange(nx + 1.0), np.arange(ny + 1.0), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(v.shape[0]).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    return v, f


def test_open_boundary():
    v, f = _grid(4, 3)
    graph = build_mesh_graph(f, len(v))
    check_graph(graph, f, len(v))
    # Interior faces of a grid have 3 neighbours, faces on the boundary fewer.
    dual_degree = np.bincount(graph.face_receivers, minlength=len(f)) - 1
    assert dual_degree.max() == 3 and dual_degree.min() == 1
    mesh = trimesh.Trimesh(v, f, process=False)
    boundary_edges = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1).size
    assert boundary_edges == 2 * (4 + 3)
    assert dual_degree.sum() == 3 * len(f) - boundary_edges


def test_vertex_edges_and_face_adjacency_match_trimesh():
    v, f = icosphere(2)
    mesh = trimesh.Trimesh(v, f, process=False)
    a, b = vertex_edges(f, len(v))
    np.testing.assert_array_equal(
        np.stack([a, b], 1), np.unique(np.sort(mesh.edges_unique, axis=1), axis=0)
    )
    a, b = face_adjacency(f, len(v))
    np.testing.assert_array_equal(
        np.stack([a, b], 1), np.unique(np.sort(mesh.face_adjacency, axis=1), axis=0)
    )
    np.testing.assert_allclose(mean_edge_length(v, f), mesh.edges_unique_length.mean())


def test_build_mesh_graph_rejects_bad_faces():
    with pytest.raises(ValueError, match="must be triangles"):
        build_mesh_graph(np.zeros((2, 4), int), 5)
    with pytest.raises(ValueError, match="out of range"):
        build_mesh_graph(np.array([[0, 1, 5]]), 5)
    with pytest.raises(ValueError, match="ragged"):
        build_mesh_graph([[None, 1, 2]], 5)
    with pytest.raises(TypeError, match="n_vertex"):
        build_mesh_graph(np.array([[0, 1, 2]]), 5.0)


# --------------------------------------------------------------------------------------
# Every shared mesh
# --------------------------------------------------------------------------------------


def _readme_counts():
    """`{file: (vertices, faces)}` from the table in ../shared/meshes/README.md."""
    readme = SHARED_MESHES / "README.md"
    if not readme.is_file():
        return {}
    counts = {}
    for line in readme.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and re.fullmatch(r"\d+", cells[1]):
            faces = re.match(r"(\d+)", cells[2]).group(1)
            counts[cells[0]] = (int(cells[1]), int(faces), "quad" in cells[2])
    return counts


SHARED_COUNTS = _readme_counts()


def test_readme_lists_every_shared_mesh(shared_meshes):
    files = {p.name for p in shared_meshes.iterdir() if p.suffix in (".obj", ".off", ".ply")}
    assert files == set(SHARED_COUNTS)


# Without the meshes' README there is nothing to parametrise over: one test says so.
_NO_README = pytest.mark.skip(reason=f"{NEEDS_SHARED}: {SHARED_MESHES}/README.md is absent")


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS) or [pytest.param("", marks=_NO_README)])
def test_shared_mesh_loads_and_builds(name):
    path = shared_mesh_path(name)
    n_vertex, n_face, quads = SHARED_COUNTS[name]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        v, f = load_mesh(path)
    messages = [str(w.message) for w in caught]
    if quads:
        # Each quad is fanned into two triangles, with a warning that says how many.
        assert len(f) == 2 * n_face
        assert any(f"triangulated {n_face} polygon faces" in m for m in messages)
        with pytest.raises(ValueError, match=f"{n_face} faces are polygons"):
            load_mesh(path, polygons="reject")
    else:
        assert len(f) == n_face
        assert not messages
    assert v.shape == (n_vertex, 3) and v.dtype == np.float64 and f.dtype == np.int32
    check_graph(build_mesh_graph(f, len(v)), f, len(v))


# --------------------------------------------------------------------------------------
# Batching and padding
# --------------------------------------------------------------------------------------


def test_batch_offsets_indices_and_graph_ids():
    meshes = [tetrahedron(), icosphere(1), _grid(2, 2)]
    graphs = [build_mesh_graph(f, len(v)) for v, f in meshes]
    batch = batch_mesh_graphs(graphs)
    faces = np.concatenate([f + off for (_, f), off in zip(meshes, [0, 4, 4 + 42], strict=True)])
    n = 4 + 42 + 9
    # The disjoint union is the graph of the concatenated faces.
    whole = build_mesh_graph(faces, n)
    for field in ("faces", "vertex_senders", "vertex_receivers", "face_senders", "face_receivers"):
        np.testing.assert_array_equal(getattr(batch, field), getattr(whole, field), err_msg=field)
    np.testing.assert_array_equal(batch.vertex_edge_weight, whole.vertex_edge_weight)
    np.testing.assert_array_equal(batch.face_edge_weight, whole.face_edge_weight)
    np.testing.assert_array_equal(batch.vertex_graph, np.repeat([0, 1, 2], [4, 42, 9]))
    np.testing.assert_array_equal(batch.face_graph, np.repeat([0, 1, 2], [4, 80, 8]))
    np.testing.assert_array_equal(batch.n_vertex_per_graph, [4, 42, 9])
    np.testing.assert_array_equal(batch.n_face_per_graph, [4, 80, 8])
    # Batching batches renumbers graph ids again.
    twice = batch_mesh_graphs([batch, graphs[0]])
    np.testing.assert_array_equal(np.unique(twice.vertex_graph), [0, 1, 2, 3])
    with pytest.raises(ValueError, match="at least one"):
        batch_mesh_graphs([])


def test_bucket_sizes():
    sizes = [bucket_size(n) for n in range(1, 5000)]
    assert min(sizes) == 64
    assert all(s >= n for n, s in zip(range(1, 5000), sizes, strict=True))
    assert all(s <= 1.25 * n for n, s in zip(range(1, 5000), sizes, strict=True) if n > 64)
    assert len(set(sizes)) <= 4 * 7 + 1  # four buckets per octave from 64 to 8192


def test_fine_bucket_sizes_waste_at_most_one_step():
    ns = range(1, 20000, 7)
    sizes = [bucket_size(n, steps=16) for n in ns]
    assert all(n <= s <= max(64, n * (1 + 1 / 16)) for n, s in zip(ns, sizes, strict=True))
    # The default steps are the four buckets of before.
    assert [bucket_size(n, steps=4) for n in ns] == [bucket_size(n) for n in ns]


def test_fine_padded_sizes_fit_each_count_tightly():
    v, f = icosphere(4)  # 2,562 vertices, 5,120 faces
    graph = build_mesh_graph(f, len(v))
    sizes = fine_padded_sizes_for(graph)
    padded = pad_mesh_graph(graph, sizes)  # room for the padding vertex and graph
    counts = [graph.n_vertex, graph.n_face, graph.vertex_senders.size, graph.face_senders.size]
    for count, size in zip(counts, sizes[:4], strict=True):
        assert count < size <= (count + 1) * (1 + 1 / 16)
    assert padded.n_face == sizes.n_face and padded.n_graph == 2
    coarse = padded_sizes_for(graph)
    assert sizes.n_face < coarse.n_face


def test_undirected_vertex_edges_match_vertex_edges_and_survive_padding():
    v, f = icosphere(2)
    graph = build_mesh_graph(f, len(v))
    a, b = vertex_edges(f, len(v))
    for g in (graph, pad_mesh_graph(graph, padded_sizes_for(graph))):
        s, r = undirected_vertex_edges(g)
        order = np.lexsort((r, s))
        np.testing.assert_array_equal(np.stack([s[order], r[order]]), np.stack([a, b]))
    np.testing.assert_allclose(
        mean_edge_length(v, f, edges=undirected_vertex_edges(graph)),
        mean_edge_length(v, f),
        rtol=1e-12,
    )


def test_pad_mesh_graph_sizes_and_errors():
    v, f = icosphere(1)
    graph = build_mesh_graph(f, len(v))
    sizes = padded_sizes_for(graph)
    padded = pad_mesh_graph(graph, sizes)
    assert padded.n_vertex == sizes.n_vertex > graph.n_vertex
    assert padded.n_face == sizes.n_face
    assert padded.vertex_senders.shape[0] == sizes.n_vertex_edge
    assert padded.face_senders.shape[0] == sizes.n_face_edge
    assert padded.n_graph == 2
    arrays = [k for k in MeshGraph._fields if not k.endswith("_ell")]  # ELL: None here
    assert all(getattr(padded, k).dtype == getattr(graph, k).dtype for k in arrays)
    with pytest.raises(ValueError, match="cannot pad"):
        pad_mesh_graph(graph, sizes._replace(n_vertex=graph.n_vertex))
    with pytest.raises(ValueError, match="cannot pad"):
        pad_mesh_graph(graph, sizes._replace(n_graph=1))
    # With no room for a padding face, face padding edges go to face 0 with weight 0.
    exact = PaddedSizes(
        n_vertex=graph.n_vertex + 1,
        n_face=graph.n_face,
        n_vertex_edge=graph.vertex_senders.shape[0],
        n_face_edge=graph.face_senders.shape[0] + 3,
        n_graph=2,
    )
    tight = pad_mesh_graph(graph, exact)
    np.testing.assert_array_equal(tight.face_edge_weight[-3:], 0.0)
    x = np.random.default_rng(0).normal(size=(graph.n_face, 2))
    np.testing.assert_allclose(ops.dual_aggregate(tight, x), ops.dual_aggregate(graph, x))


def test_pad_vertex_array():
    x = np.ones((3, 2))
    out = pad_vertex_array(x, 5, value=-1.0)
    np.testing.assert_array_equal(out, [[1, 1]] * 3 + [[-1, -1]] * 2)
    with pytest.raises(ValueError, match="cannot pad"):
        pad_vertex_array(x, 2)


# --------------------------------------------------------------------------------------
# Canonical frame
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["screwdriver.off", "decimated-knight.off", "offset-random"])
def test_canonical_frame(name):
    if name == "offset-random":
        rng = np.random.default_rng(1)
        v = rng.normal(size=(200, 3)) * [3e-4, 1e-4, 2e-4] + [1e3, -5e2, 7.0]
    else:
        v, _ = load_mesh(shared_mesh_path(name))
    frame = canonical_frame(v)
    c = frame.apply(v)
    lo, hi = c.min(axis=0), c.max(axis=0)
    np.testing.assert_allclose((hi - lo).max(), 1.0, rtol=1e-12)
    # The centre is exact up to rounding of the world coordinates, magnified by 1/scale.
    eps = np.finfo(np.float64).eps
    np.testing.assert_allclose((hi + lo) / 2, 0.0, atol=4 * eps * np.abs(v).max() / frame.scale)
    back = frame.invert(c)
    np.testing.assert_allclose(back, v, rtol=0, atol=1e-12 * np.abs(v).max())
    assert isinstance(frame, CanonicalFrame)


def test_canonical_frame_of_flat_mesh_and_zero_extent():
    v, _ = _grid(3, 2)  # flat: zero extent along z is fine
    c = canonical_frame(v).apply(v)
    np.testing.assert_allclose(c.max(axis=0) - c.min(axis=0), [1.0, 2 / 3, 0.0])
    with pytest.raises(ValueError, match="zero extent"):
        canonical_frame(np.tile([[1.0, 2.0, 3.0]], (5, 1)))
    with pytest.raises(ValueError, match="zero extent"):
        canonical_frame(np.array([[0.0, 0.0, 0.0]]))


# --------------------------------------------------------------------------------------
# I/O
# --------------------------------------------------------------------------------------


def _test_mesh():
    """A perturbed icosphere with an unused vertex and a shuffled vertex order."""
    v, f = icosphere(1)
    rng = np.random.default_rng(2)
    v = (v + 1e-3 * rng.normal(size=v.shape)) * 1e-3 + 0.1  # small scale, off-centre
    perm = rng.permutation(len(v))
    inverse = np.argsort(perm)
    v, f = v[perm], inverse[f].astype(np.int32)
    return np.concatenate([v, [[0.5, 0.5, 0.5]]]), f


@pytest.mark.parametrize("ext", ["obj", "off", "ply"])
def test_save_load_round_trip_keeps_order(tmp_path, ext):
    v, f = _test_mesh()
    path = save_mesh(tmp_path / f"m.{ext}", v, f)
    v2, f2 = load_mesh(path)
    np.testing.assert_array_equal(f2, f)
    assert v2.shape == v.shape  # the unused vertex survives
    # Every writer but STL's keeps float64 exactly (shortest repr, or binary doubles).
    np.testing.assert_array_equal(v2, v)


def test_stl_round_trip_merges_soup_in_first_appearance_order(tmp_path):
    v, f = _test_mesh()
    path = save_mesh(tmp_path / "m.stl", v, f)
    raw = trimesh.load(path, process=False)
    assert len(raw.vertices) == 3 * len(f)  # STL itself is a triangle soup
    v2, f2 = load_mesh(path)
    # Vertices come back numbered in order of first appearance in the faces, as float32,
    # and the unused vertex is gone.
    first = np.unique(f.ravel(), return_index=True)[1]
    order = f.ravel()[np.sort(first)]
    np.testing.assert_array_equal(v2, v[order].astype(np.float32))
    np.testing.assert_array_equal(order[f2], f)
    check_graph(build_mesh_graph(f2, len(v2)), f2, len(v2))
    # A mesh already numbered that way comes back unchanged (up to float32).
    save_mesh(tmp_path / "again.stl", v2, f2)
    v3, f3 = load_mesh(tmp_path / "again.stl")
    np.testing.assert_array_equal(f3, f2)
    np.testing.assert_array_equal(v3, v2)


def test_save_refuses_to_overwrite(tmp_path):
    v, f = tetrahedron()
    path = tmp_path / "t.off"
    save_mesh(path, v, f)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        save_mesh(path, v + 1, f)
    assert path.read_bytes() == before
    save_mesh(path, v + 1, f, overwrite=True)
    np.testing.assert_allclose(load_mesh(path)[0], v + 1)
    with pytest.raises(ValueError, match="input file"):
        save_mesh(path, v, f, overwrite=True, protect=[path])
    assert [p.name for p in tmp_path.iterdir()] == ["t.off"]  # no temporary left over


def test_atomic_write_cleans_up_on_error(tmp_path):
    def boom(tmp):
        with open(tmp, "w") as fh:
            fh.write("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.obj", boom)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError, match="directory"):
        atomic_write(tmp_path / "missing" / "x.obj", boom)


def test_save_and_load_errors(tmp_path):
    v, f = tetrahedron()
    with pytest.raises(ValueError, match="unknown mesh format"):
        save_mesh(tmp_path / "m.xyz", v, f)
    with pytest.raises(ValueError, match="repeat a vertex"):
        save_mesh(tmp_path / "m.obj", v, [[0, 0, 1]])
    with pytest.raises(ValueError, match="unknown mesh format"):
        load_mesh(tmp_path / "m.xyz")
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "absent.obj")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(ValueError, match="empty"):
        load_mesh(tmp_path / "empty.obj")
    for name, text in (
        ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        ("points.off", "OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n"),
    ):
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match="no faces"):
            load_mesh(tmp_path / name)
    (tmp_path / "quad.off").write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    with pytest.warns(UserWarning, match="triangulated 1 polygon"):
        v4, f4 = load_mesh(tmp_path / "quad.off")
    assert f4.shape == (2, 3) and v4.shape == (4, 3)
    with pytest.raises(ValueError, match="1 faces are polygons"):
        load_mesh(tmp_path / "quad.off", polygons="reject")
    with pytest.raises(ValueError, match="polygons must be"):
        load_mesh(tmp_path / "quad.off", polygons="keep")


PLAIN_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1.5 0\nv 0 0 -2e-3\nf 1 2 3\nf 1 3 4\nf 2 4 3\nf 1 4 2\n"


@pytest.mark.parametrize(
    "text, plain",
    [
        (PLAIN_OBJ, True),
        ("# header\n# two lines\n" + PLAIN_OBJ, True),
        (PLAIN_OBJ.replace("\n", "\r\n"), True),
        ("  " + PLAIN_OBJ.replace("\nf", "\n\tf"), True),
        (PLAIN_OBJ.rstrip("\n"), True),
        (PLAIN_OBJ + "# a comment after the header\n", False),
        (PLAIN_OBJ.replace("f 1 2 3", "f 1/1 2/2 3/3"), False),
        (PLAIN_OBJ.replace("f 1 2 3", "f -4 -3 -2"), False),
        (PLAIN_OBJ.replace("f 1 2 3", "f 1 2 3 4"), False),
        (PLAIN_OBJ.replace("v 1 0 0", "v 1 0 0 1"), False),
        (PLAIN_OBJ.replace("f 1 2 3\n", "f 1 2 3\nvn 0 0 1\n"), False),
        (PLAIN_OBJ.replace("\nf 1 2 3", "\n\nf 1 2 3"), False),
        (PLAIN_OBJ.replace("f 1 3 4", "f 1 3 5"), False),  # out of range: the line is named
        (PLAIN_OBJ.replace("v 1 0 0", "v 1 0 x"), False),
        (PLAIN_OBJ.replace("v 1 0 0", "v 1_0 0 0"), False),  # not C strtod: refused
    ],
)
def test_plain_obj_is_read_in_bulk_as_line_by_line(text, plain):
    from dmd_jax.io.obj import _read_obj, _read_obj_lines, _read_plain_obj

    bulk = _read_plain_obj(text)
    assert (bulk is not None) == plain
    try:
        lines = _read_obj_lines(text, "m.obj")
    except ValueError as err:
        assert not plain
        with pytest.raises(ValueError, match=re.escape(str(err))):
            _read_obj(text.encode(), "m.obj")
        return
    got = _read_obj(text.encode(), "m.obj")
    for a, b in zip(got, lines, strict=True):
        np.testing.assert_array_equal(a, b)
        assert np.asarray(a).dtype == np.asarray(b).dtype


def test_plain_obj_of_the_writer_round_trips(tmp_path):
    from dmd_jax.io.obj import _read_obj_lines, _read_plain_obj

    v, f = icosphere(3)
    v = v * np.pi + 1e-17  # every digit of repr kept
    save_mesh(tmp_path / "m.obj", v, f)
    text = (tmp_path / "m.obj").read_text()
    bulk, lines = _read_plain_obj(text), _read_obj_lines(text, "m.obj")
    np.testing.assert_array_equal(bulk.vertices, v)
    np.testing.assert_array_equal(bulk.vertices, lines.vertices)
    np.testing.assert_array_equal(bulk.faces, lines.faces)
