"""Host-side topology (`dmd_jax.topology`) against dense loop references.

Every function is checked for the same values, dtypes and order as a direct reading of
its definition, on meshes with open boundaries, a non-manifold edge, an isolated vertex
and several components. The order matters where the JAX kernels sum with
`indices_are_sorted=True` and where `presmooth` pairs consecutive faces of an edge.
"""

from __future__ import annotations

import itertools
from collections import defaultdict

import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import presmooth, topology


def _grid(k: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    idx = (i * (k + 1) + j).ravel()
    lower = np.stack([idx, idx + 1, idx + k + 1], -1)
    upper = np.stack([idx + 1, idx + k + 2, idx + k + 1], -1)
    f = np.concatenate([lower, upper])
    gi, gj = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
    z = np.random.default_rng(k).normal(size=gi.size) * 0.3
    return np.stack([gi.ravel(), gj.ravel(), z], -1).astype(float), f


def _nonmanifold() -> tuple[np.ndarray, np.ndarray]:
    """Three faces on edge (0, 2), a boundary fan, a second component and vertex 7 unused."""
    v = np.random.default_rng(0).normal(size=(8, 3))
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4], [1, 2, 5], [5, 6, 1]])
    return v, f


MESHES = {
    "tetrahedron": tetrahedron(),
    "icosphere": icosphere(1),
    "grid": _grid(4),
    "nonmanifold": _nonmanifold(),
    "two components": (
        np.concatenate([tetrahedron()[0], _grid(2)[0]]),
        np.concatenate([tetrahedron()[1], _grid(2)[1] + 4]),
    ),
}


@pytest.fixture(params=sorted(MESHES))
def mesh(request):
    v, f = MESHES[request.param]
    return np.asarray(v, np.float64), np.asarray(f)


def _edge_faces(f) -> dict[tuple[int, int], list[int]]:
    out = defaultdict(list)
    for i, tri in enumerate(f.tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            out[(min(a, b), max(a, b))].append(i)
    return dict(sorted(out.items()))


def test_edges_and_their_face_counts(mesh):
    v, f = mesh
    ref = _edge_faces(f)
    a, b, count = topology.edge_face_counts(f, len(v))
    assert [(x, y) for x, y in zip(a.tolist(), b.tolist(), strict=True)] == list(ref)
    assert count.tolist() == [len(x) for x in ref.values()]
    assert a.dtype == b.dtype == count.dtype == np.int64
    ea, eb = topology.vertex_edges(f, len(v))
    np.testing.assert_array_equal(ea, a)
    np.testing.assert_array_equal(eb, b)
    # The previous definition (`np.unique` of the keys): same arrays.
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1).astype(np.int64)
    key, n = np.unique(e[:, 0] * len(v) + e[:, 1], return_counts=True)
    np.testing.assert_array_equal(np.stack(np.divmod(key, len(v))), np.stack([a, b]))
    np.testing.assert_array_equal(n, count)


def test_edge_keys_list_each_slot_of_every_face_in_turn():
    v, f = _nonmanifold()
    key = topology.edge_keys(f, len(v))
    for k, kk in enumerate(key.tolist()):
        tri = f[k % len(f)]
        a, b = tri[k // len(f)], tri[(k // len(f) + 1) % 3]
        assert kk == min(a, b) * len(v) + max(a, b)


def test_face_adjacency_pairs_every_two_faces_of_an_edge(mesh):
    v, f = mesh
    ref = sorted({p for faces in _edge_faces(f).values() for p in itertools.combinations(faces, 2)})
    a, b = topology.face_adjacency(f, len(v))
    assert list(zip(a.tolist(), b.tolist(), strict=True)) == ref
    da, db = topology.dual_edges(f, len(v))
    assert da.dtype == db.dtype == np.int32
    np.testing.assert_array_equal(da, a)
    np.testing.assert_array_equal(db, b)
    dense = np.zeros((len(f), len(f)), np.int8)
    for i, j in ref:
        dense[i, j] = dense[j, i] = 1
    m = topology.face_adjacency_matrix(f, len(v))
    assert m.dtype == np.int8 and m.shape == dense.shape
    np.testing.assert_array_equal(m.toarray(), dense)


def test_boundary_vertices_are_those_of_one_face_edges(mesh):
    v, f = mesh
    ref = np.zeros(len(v), bool)
    for (a, b), faces in _edge_faces(f).items():
        if len(faces) == 1:
            ref[[a, b]] = True
    np.testing.assert_array_equal(topology.boundary_vertex_mask(f, len(v)), ref)


def test_umbrella_weights_follow_meshlab_boundary_rule(mesh):
    v, f = mesh
    n = len(v)
    edges = _edge_faces(f)
    boundary = np.zeros(n, bool)
    for (a, b), faces in edges.items():
        if len(faces) == 1:
            boundary[[a, b]] = True
    dense = np.zeros((n, n))
    for (a, b), faces in edges.items():
        for r, s in ((a, b), (b, a)):
            dense[r, s] = (len(faces) == 1) if boundary[r] else len(faces)
    s, r, w, self_w = topology.umbrella_weights(f, n)
    assert s.dtype == r.dtype == np.int32 and w.dtype == self_w.dtype == np.float64
    assert np.all(np.diff(r) >= 0) and np.all(w > 0)
    got = np.zeros((n, n))
    np.add.at(got, (r, s), w)
    np.testing.assert_array_equal(got, dense)
    np.testing.assert_array_equal(self_w, boundary.astype(float))


def test_face_rings_are_faces_sharing_a_vertex_in_lexicographic_order(mesh):
    v, f = mesh
    share = [(i, j) for i in range(len(f)) for j in range(len(f)) if set(f[i]) & set(f[j])]
    r, s = topology.face_ring_pairs(f, len(v))
    assert r.dtype == s.dtype == np.int32
    assert list(zip(r.tolist(), s.tolist(), strict=True)) == share
    r, s = topology.face_ring_pairs(f, len(v), include_self=False)
    assert list(zip(r.tolist(), s.tolist(), strict=True)) == [p for p in share if p[0] != p[1]]
    inc = topology.vertex_face_incidence(f, len(v)).toarray()
    np.testing.assert_array_equal(inc, [[float(k in tri) for k in range(len(v))] for tri in f])


def test_corner_arrays_list_every_corner_row_major(mesh):
    v, f = mesh
    cv, cf = topology.vertex_corner_arrays(f)
    assert cv.dtype == cf.dtype == np.int32
    np.testing.assert_array_equal(cv, f.ravel())
    np.testing.assert_array_equal(cf, np.repeat(np.arange(len(f)), 3))


def test_one_ring_mean_averages_each_neighbour_once(mesh):
    v, f = mesh
    n = len(v)
    ring = [set() for _ in range(n)]
    for a, b in _edge_faces(f):
        ring[a].add(b)
        ring[b].add(a)
    dense = np.zeros((n, n))
    for i, nbr in enumerate(ring):
        for j in nbr:
            dense[i, j] = 1.0 / len(nbr)
    np.testing.assert_allclose(topology.one_ring_mean(f, n).toarray(), dense, rtol=0, atol=1e-15)


def test_empty_mesh_has_no_edges():
    f = np.zeros((0, 3), np.int64)
    a, b, count = topology.edge_face_counts(f, 3)
    assert a.size == b.size == count.size == 0
    assert topology.face_adjacency(f, 3)[0].size == 0
    assert not topology.boundary_vertex_mask(f, 3).any()


def _old_edge_pairs(faces, n_vertex):
    """`presmooth._edge_pairs` before it read `topology.edge_keys` (min/max per slot)."""
    m = faces.shape[0]
    stride = 1 if m <= presmooth.EXACT_MAX_FACES else -(-3 * m // presmooth.SAMPLED_HALF_EDGES)
    keys, owners = [], []
    for lo in range(0, m, presmooth._CHUNK_FACES):
        f = faces[lo : lo + presmooth._CHUNK_FACES].astype(np.int64)
        ids = np.arange(lo, lo + f.shape[0], dtype=np.int64)
        for a, b in ((0, 1), (1, 2), (2, 0)):
            key = np.minimum(f[:, a], f[:, b]) * n_vertex + np.maximum(f[:, a], f[:, b])
            face = ids
            if stride > 1:
                with np.errstate(over="ignore"):
                    mixed = (key.astype(np.uint64) * presmooth._HASH) >> np.uint64(32)
                keep = mixed % np.uint64(stride) == 0
                key, face = key[keep], ids[keep]
            keys.append(key)
            owners.append(face)
    key, owner = np.concatenate(keys), np.concatenate(owners)
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    return owner[same], owner[same + 1]


@pytest.mark.parametrize("exact_max, chunk", [(10**9, 10**9), (100, 10**9), (100, 70)])
def test_roughness_edge_pairs_unchanged(monkeypatch, exact_max, chunk):
    """Whole, sampled and chunked: the pairs the roughness reads are the same as before."""
    monkeypatch.setattr(presmooth, "EXACT_MAX_FACES", exact_max)
    monkeypatch.setattr(presmooth, "SAMPLED_HALF_EDGES", 120)
    monkeypatch.setattr(presmooth, "_CHUNK_FACES", chunk)
    for v, f in (_grid(12), _nonmanifold()):
        got = presmooth._edge_pairs(f, len(v))
        ref = _old_edge_pairs(f, len(v))
        for g, r in zip(got, ref, strict=True):
            assert g.dtype == r.dtype
            np.testing.assert_array_equal(g, r)


def test_edge_groups_list_each_edge_with_its_faces():
    v, f = _nonmanifold()
    g = topology.edge_groups(f, len(v))
    ref = _edge_faces(f)
    assert np.all(np.diff(g.key) >= 0)
    np.testing.assert_array_equal(np.stack(np.divmod(g.key[g.start], len(v))).T, list(ref))
    for start, size, faces in zip(g.start, g.size, ref.values(), strict=True):
        assert sorted(g.face[start : start + size].tolist()) == faces
