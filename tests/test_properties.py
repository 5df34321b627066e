"""Property tests (hypothesis) over random valid meshes.

Meshes are perturbed icospheres (closed) and grids with random diagonals (open), with
their vertices and faces randomly permuted, at random scales and offsets. All have at
most 49 vertices, so `denoise` pads every one of them to the same bucket and the network
compiles once.

Each property runs twice: a few examples in the default suite, and 1000 in the slow
suite (`make test-slow`), as a separate `*_many` test marked `slow`.
"""

from __future__ import annotations

from collections import defaultdict
from functools import lru_cache

import numpy as np
import pytest
from conftest import icosphere
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from test_reliability import CONFIG, random_params

from dmd_jax import checkpoints, inference, losses
from dmd_jax.graph import build_mesh_graph
from dmd_jax.mesh import canonical_frame, validate_mesh
from dmd_jax.metrics import mesh_metrics

FEW = settings(
    max_examples=10, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
MANY = settings(
    max_examples=1000, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)


@pytest.fixture(scope="module")
def bundle():
    return checkpoints.ModelBundle(random_params(CONFIG), CONFIG, {})


# The permutation tests run the paper's encoding and offset head: with random params the
# `local` encoding's 60 bilateral passes amplify the segment sums' float32 reordering
# (0.04 of the extent on one hypothesis mesh, 2026-11-30), beyond a 1e-6 tolerance.
XYZ_CONFIG = CONFIG.with_edits({"model": {"encoding": "xyz", "head": "offset"}})


@pytest.fixture(scope="module")
def xyz_bundle():
    return checkpoints.ModelBundle(random_params(XYZ_CONFIG), XYZ_CONFIG, {})


# --------------------------------------------------------------------------------------
# Random meshes
# --------------------------------------------------------------------------------------


@lru_cache(maxsize=4)
def _sphere(subdivisions: int):
    return icosphere(subdivisions)


def _grid(nx: int, ny: int, diagonals: list[bool]):
    """An `nx × ny` vertex grid in the plane z = 0, each cell split along a chosen diagonal."""
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(nx * ny)], axis=1)
    faces = []
    for c, (i, j) in enumerate((i, j) for i in range(nx - 1) for j in range(ny - 1)):
        a, b, c_, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
        faces += [[a, b, c_], [a, c_, d]] if diagonals[c] else [[a, b, d], [b, c_, d]]
    return v, np.array(faces)


@st.composite
def meshes(draw, *, allow_open: bool = True):
    """A valid triangle mesh `(vertices [n, 3] float64, faces [f, 3] int)`."""
    if allow_open and draw(st.booleans()):
        nx, ny = draw(st.integers(2, 7)), draw(st.integers(2, 7))
        v, f = _grid(nx, ny, draw(st.lists(st.booleans(), min_size=36, max_size=36)))
        closed = False
    else:
        v, f = _sphere(draw(st.integers(0, 1)))
        closed = True
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    # Jitter well below the edge length keeps every face non-degenerate.
    edge = 1.0 if not closed else (0.6 if len(v) == 12 else 0.3)
    v = v + draw(st.floats(0.0, 0.2)) * edge * rng.uniform(-1, 1, v.shape)
    perm = rng.permutation(len(v))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(v))
    v, f = v[perm], inverse[f][rng.permutation(len(f))]
    scale = 10.0 ** draw(st.floats(-3, 3))
    shift = np.array(draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3)))
    return v * scale + shift, f


# A scale and a shift; the shift is in units of the scaled mesh's extent: float64 keeps
# eps · |shift| / extent of relative precision in the canonical frame, so a far larger
# shift would test rounding, not equivariance.
transforms = st.tuples(
    st.floats(-4, 4).map(lambda e: 10.0**e),
    st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3).map(np.array),
)


def _apply(v, transform):
    scale, shift = transform
    return v * scale + shift * _extent(v) * scale


def _extent(v) -> float:
    return float(np.ptp(v, axis=0).max())


# --------------------------------------------------------------------------------------
# denoise: shape, finiteness, equivariance
# --------------------------------------------------------------------------------------


def check_denoise_finite_and_shaped(bundle, mesh):
    v, f = mesh
    for x in (v, v.astype(np.float32)):
        out = inference.denoise(x, f, bundle)
        assert out.shape == v.shape and out.dtype == x.dtype
        assert np.all(np.isfinite(out))


def _is_flat(v) -> bool:
    """Whether every vertex lies on one plane (to float64 rounding of the extent)."""
    centred = v - v.mean(axis=0)
    return np.linalg.svd(centred, compute_uv=False)[-1] <= 1e-9 * _extent(v) * len(v) ** 0.5


def check_translation_and_scale_equivariance(bundle, mesh, transform):
    v, f = mesh
    scale = transform[0]
    base = inference.denoise(v, f, bundle)
    if np.abs(base - v).max() <= 1e-9 * _extent(v):
        # A mesh drawn without jitter is a clean flat: its vertices are held (to float64
        # rounding of the frame, `dmd_jax.consistency`), at any scale and offset too;
        # or it has nothing to denoise (a clean icosahedron: all creases), returned as
        # given (`consistency.still_faces`).
        from dmd_jax.consistency import still_faces

        assert _is_flat(v) or still_faces(v, f).all()
    else:
        # Not vacuous: these weights move vertices by 1.7-8 % of the extent (measured).
        assert np.abs(base - v).max() > 1e-3 * _extent(v)
    moved = inference.denoise(_apply(v, transform), f, bundle)
    # The network runs in float32 on canonical coordinates (longest side 1): the two
    # calls see inputs equal up to float32 rounding, so results agree to float32
    # precision amplified by the network (measured: at most 2.0e-6 of the extent over
    # 2,500 examples).
    tolerance = 2e-5 * _extent(v) * scale
    expected = base * scale + (_apply(v, transform) - v * scale)
    np.testing.assert_allclose(moved, expected, rtol=0, atol=tolerance)


def check_permutation_equivariance(bundle, mesh, seed):
    v, f = mesh
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(v))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(v))
    out = inference.denoise(v[perm], inverse[f][rng.permutation(len(f))], bundle)
    # Segment sums add in another order: equal up to float32 rounding (measured: at
    # most 6e-8 of the extent over 2,500 examples).
    base = inference.denoise(v, f, bundle)
    np.testing.assert_allclose(out, base[perm], rtol=0, atol=1e-6 * _extent(v))


@pytest.mark.slow  # measured 12-20 s on 2 idle cores; `make test-slow` runs it
@FEW
@given(mesh=meshes())
def test_denoise_finite_and_shaped(bundle, mesh):
    check_denoise_finite_and_shaped(bundle, mesh)


@FEW
@given(mesh=meshes(), transform=transforms)
def test_denoise_translation_and_scale_equivariant(bundle, mesh, transform):
    check_translation_and_scale_equivariance(bundle, mesh, transform)


@FEW
@given(mesh=meshes(), seed=st.integers(0, 2**32 - 1))
def test_model_permutation_equivariant(xyz_bundle, mesh, seed):
    check_permutation_equivariance(xyz_bundle, mesh, seed)


@pytest.mark.slow
@MANY
@given(mesh=meshes())
def test_denoise_finite_and_shaped_many(bundle, mesh):
    check_denoise_finite_and_shaped(bundle, mesh)


@pytest.mark.slow
@MANY
@given(mesh=meshes(), transform=transforms)
def test_denoise_translation_and_scale_equivariant_many(bundle, mesh, transform):
    check_translation_and_scale_equivariance(bundle, mesh, transform)


@pytest.mark.slow
@MANY
@given(mesh=meshes(), seed=st.integers(0, 2**32 - 1))
def test_model_permutation_equivariant_many(xyz_bundle, mesh, seed):
    check_permutation_equivariance(xyz_bundle, mesh, seed)


# --------------------------------------------------------------------------------------
# Metrics: symmetry, zero on identical meshes, frame invariance, scipy reference
# --------------------------------------------------------------------------------------


@st.composite
def mesh_pairs(draw, *, allow_open: bool = True):
    """A mesh and a perturbed copy of it (same faces)."""
    v, f = draw(meshes(allow_open=allow_open))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    level = draw(st.floats(1e-4, 0.05)) * _extent(v)
    return v, v + level * rng.standard_normal(v.shape), f


def check_metrics(pair, transform):
    world_a, world_b, f = pair
    # The loss functions work in the canonical frame, as training and `mesh_metrics` use them.
    frame = canonical_frame(world_a)
    a, b = frame.apply(world_a), frame.apply(world_b)
    chamfer_ab = float(losses.chamfer_distance(a, b))
    chamfer_ba = float(losses.chamfer_distance(b, a))
    assert chamfer_ab == chamfer_ba  # the same two one-sided sums, added in either order
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    np.testing.assert_allclose(chamfer_ab, np.mean(d_ab**2) + np.mean(d_ba**2), rtol=1e-9)
    vertex = float(losses.vertex_loss(a, b))
    assert vertex == float(losses.vertex_loss(b, a))
    # Nearest neighbours are never farther than the corresponding vertex.
    assert chamfer_ab <= 2 * vertex * (1 + 1e-12)
    # Both meshes are non-degenerate, so the angle between face normals is symmetric.
    normal_ab = float(losses.normal_loss(a, b, f))
    np.testing.assert_allclose(normal_ab, float(losses.normal_loss(b, a, f)), rtol=1e-12)

    m = mesh_metrics(world_b, world_a, f)
    same = mesh_metrics(world_a, world_a, f)
    assert same["vertex"] == same["normal_deg"] == 0.0
    assert same["chamfer"] <= 1e-15
    # The same similarity applied to both meshes changes nothing (canonical frame of GT).
    shift = _apply(world_a, transform) - world_a * transform[0]
    moved = mesh_metrics(world_b * transform[0] + shift, world_a * transform[0] + shift, f)
    for key in ("vertex", "normal_deg", "chamfer"):
        np.testing.assert_allclose(moved[key], m[key], rtol=1e-6, atol=1e-12, err_msg=key)


# The losses compile once per mesh size: the default run keeps to the two icospheres.
@FEW
@given(pair=mesh_pairs(allow_open=False), transform=transforms)
def test_metrics_symmetric_zero_and_frame_invariant(pair, transform):
    check_metrics(pair, transform)


@pytest.mark.slow
@MANY
@given(pair=mesh_pairs(), transform=transforms)
def test_metrics_symmetric_zero_and_frame_invariant_many(pair, transform):
    check_metrics(pair, transform)


# --------------------------------------------------------------------------------------
# validate_mesh: raises exactly on invalid input
# --------------------------------------------------------------------------------------


@st.composite
def raw_arrays(draw):
    """Arrays that are often, but not always, a valid mesh."""
    n = draw(st.integers(0, 6))
    width = draw(st.sampled_from([3, 3, 3, 2, 4]))
    special = st.sampled_from([0.0, -1.0, 1e300, -1e-300, np.nan, np.inf, -np.inf])
    coords = st.one_of(st.floats(-10, 10), special) if draw(st.booleans()) else st.floats(-10, 10)
    v = np.array(draw(st.lists(coords, min_size=n * width, max_size=n * width))).reshape(n, width)
    with np.errstate(over="ignore"):  # 1e300 becomes inf in float16 / float32
        v = v.astype(draw(st.sampled_from([np.float64, np.float32, np.float16])))
    m = draw(st.integers(0, 5))
    k = draw(st.sampled_from([3, 3, 3, 4, 2]))
    idx = draw(st.lists(st.integers(-2, n + 1), min_size=m * k, max_size=m * k))
    f = np.array(idx, dtype=draw(st.sampled_from([np.int64, np.int32, np.float64]))).reshape(m, k)
    return v, f


def _is_valid(v, f) -> bool:
    """An independent statement of what `validate_mesh` accepts."""
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(v.astype(np.float64)).all()
    return bool(
        v.shape[0] > 0
        and v.shape[1] == 3
        and finite
        and f.shape[0] > 0
        and f.shape[1] == 3
        and f.min() >= 0
        and f.max() < v.shape[0]
        and all(len(set(row)) == 3 for row in f.tolist())
    )


def check_validation(arrays):
    v, f = arrays
    try:
        out_v, out_f = validate_mesh(v, f)
    except ValueError as exc:
        assert not _is_valid(v, f), f"rejected a valid mesh: {exc}"
        assert str(exc).startswith("mesh: ")
        return
    assert _is_valid(v, f)
    assert out_v.dtype == np.float64 and out_f.dtype == np.int32
    np.testing.assert_array_equal(out_v, v.astype(np.float64))
    np.testing.assert_array_equal(out_f, f)


@FEW
@given(arrays=raw_arrays())
def test_validate_mesh_rejects_exactly_the_invalid(arrays):
    check_validation(arrays)


@pytest.mark.slow
@MANY
@given(arrays=raw_arrays())
def test_validate_mesh_rejects_exactly_the_invalid_many(arrays):
    check_validation(arrays)


# --------------------------------------------------------------------------------------
# MeshGraph invariants and the canonical frame
# --------------------------------------------------------------------------------------


@st.composite
def face_subsets(draw):
    """A random mesh with a random subset of its faces (boundaries, unused vertices,
    several components)."""
    v, f = draw(meshes())
    keep = draw(st.lists(st.booleans(), min_size=len(f), max_size=len(f)))
    if not any(keep):
        keep[0] = True
    return v, f[np.array(keep)]


def check_graph(mesh):
    v, f = mesh
    n, n_face = len(v), len(f)
    graph = build_mesh_graph(f, n)
    # Reference adjacency from plain Python sets and dicts.
    edges = {
        frozenset((int(a), int(b))) for tri in f for a, b in zip(tri, np.roll(tri, 1), strict=True)
    }
    faces_of_edge = defaultdict(set)
    for i, tri in enumerate(f):
        for a, b in zip(tri, np.roll(tri, 1), strict=True):
            faces_of_edge[frozenset((int(a), int(b)))].add(i)
    dual = {frozenset((p, q)) for fs in faces_of_edge.values() for p in fs for q in fs if p < q}
    for senders, receivers, weight, undirected, size in (
        (graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight, edges, n),
        (graph.face_senders, graph.face_receivers, graph.face_edge_weight, dual, n_face),
    ):
        assert np.all(np.diff(receivers) >= 0)
        pairs = set(zip(senders.tolist(), receivers.tolist(), strict=True))
        assert len(pairs) == len(senders)  # no duplicates
        expected = {(i, i) for i in range(size)}
        expected |= {(a, b) for e in undirected for a in e for b in e if a != b}
        assert pairs == expected
        degree = np.bincount(receivers, minlength=size).astype(np.float64)
        np.testing.assert_allclose(
            weight, 1.0 / np.sqrt(degree[senders] * degree[receivers]), rtol=1e-6
        )
    np.testing.assert_array_equal(graph.vertex_face_degree, np.bincount(f.ravel(), minlength=n))
    if all(len(fs) == 2 for fs in faces_of_edge.values()):
        # Closed: only a whole (perturbed) icosphere is, a sphere of Euler characteristic 2.
        assert len(np.unique(f)) - len(edges) + n_face == 2

    frame = canonical_frame(v)
    c = frame.apply(v)
    # v - centre loses the bits of |v| that the extent does not need: a far-off small
    # mesh is exact only to eps · |v| / extent in the canonical frame.
    tol = 8 * np.finfo(np.float64).eps * (1 + np.abs(v).max() / frame.scale)
    np.testing.assert_allclose(np.ptp(c, axis=0).max(), 1.0, rtol=0, atol=tol)
    np.testing.assert_allclose((c.min(axis=0) + c.max(axis=0)) / 2, 0.0, rtol=0, atol=tol)
    np.testing.assert_allclose(frame.invert(c), v, rtol=0, atol=tol * frame.scale)


@FEW
@given(mesh=face_subsets())
def test_mesh_graph_invariants(mesh):
    check_graph(mesh)


@pytest.mark.slow
@MANY
@given(mesh=face_subsets())
def test_mesh_graph_invariants_many(mesh):
    check_graph(mesh)
