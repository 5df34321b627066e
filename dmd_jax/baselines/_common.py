"""Shared pieces of the classic denoisers: host-side neighbourhoods and JAX kernels.

Neighbourhoods are index arrays built once per mesh in NumPy/SciPy (sparse products,
no Python loops over elements); the filters themselves are gathers plus
`jax.ops.segment_*` reductions inside `jax.jit`. Every public filter runs in the
mesh's canonical frame (centre and longest bounding-box side 1) and maps the result
back, so it is translation and scale equivariant and keeps float32 accurate when
64-bit JAX is off.
"""

from __future__ import annotations

import collections
import inspect
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from dmd_jax.geometry import (  # noqa: F401  (re-exported for the baselines)
    face_centroids,
    fit_vertices_to_normals,
    safe_norm,
)
from dmd_jax.graph import face_adjacency
from dmd_jax.mesh import canonical_frame, validate_mesh

# How many times each jitted core has been traced; tests read it to check that a
# second call on a mesh of the same size reuses the compiled program.
TRACE_COUNTS: collections.Counter = collections.Counter()


def count_trace(name: str) -> None:
    """Records one trace of the jitted core `name` (runs at trace time only)."""
    TRACE_COUNTS[name] += 1


# --------------------------------------------------------------------------------------
# Calling convention
# --------------------------------------------------------------------------------------


def run_in_canonical_frame(vertices, faces, core: Callable, *, name: str) -> np.ndarray:
    """Validates a mesh, runs `core(v, f)` in its canonical frame and maps back.

    Args:
      vertices: `[n_vertex, 3]` array-like.
      faces: `[n_face, 3]` array-like of vertex indices.
      core: `core(vertices [n, 3] float64 canonical, faces [f, 3] int32) -> [n, 3]`.
      name: the method's name, for error messages.

    Returns:
      `[n_vertex, 3]` float64 NumPy array in the input's frame.
    """
    v, f = validate_mesh(vertices, faces, name=name)
    frame = canonical_frame(v)
    out = np.asarray(core(frame.apply(v), f), dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise FloatingPointError(f"{name}: the filter produced non-finite vertices")
    return frame.invert(out)


def default_params(fn: Callable) -> dict:
    """The keyword-only parameters of a filter and their defaults."""
    return {
        p.name: p.default
        for p in inspect.signature(fn).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }


def check_positive(name: str, **values) -> None:
    """Raises `ValueError` unless every value is a finite number > 0."""
    for key, val in values.items():
        if not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name}: {key} must be a finite number > 0, got {val!r}")


def check_count(name: str, **values) -> None:
    """Raises `ValueError` unless every value is an integer >= 0."""
    for key, val in values.items():
        if isinstance(val, bool) or int(val) != val or val < 0:
            raise ValueError(f"{name}: {key} must be an integer >= 0, got {val!r}")


def float_dtype():
    """float64 when 64-bit JAX is enabled, else float32."""
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


# --------------------------------------------------------------------------------------
# Host-side neighbourhoods
# --------------------------------------------------------------------------------------


def _i32(x) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.int32)


def edge_face_counts(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, ...]:
    """Unique undirected edges `(a, b)` with `a < b` and the number of faces on each."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key, count = np.unique(e[:, 0] * n_vertex + e[:, 1], return_counts=True)
    a, b = np.divmod(key, n_vertex)
    return a, b, count


def umbrella_weights(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, ...]:
    """Weights of the uniform umbrella operator with VCG/MeshLab's boundary rule.

    An interior vertex averages its 1-ring neighbours (each edge weighted by its number
    of faces, i.e. uniformly on a manifold). A vertex on a boundary edge averages
    itself and its neighbours along boundary edges only, so open boundaries are
    smoothed as curves instead of shrinking into the surface. This is
    `vcg::tri::Smooth::AccumulateLaplacianInfo`, which pymeshlab's Taubin and
    Laplacian filters use.

    Returns:
      `(senders [m], receivers [m], weight [m], self_weight [n_vertex])`: the average
      at `v` is `(self_weight[v] x_v + Σ weight x_s) / (self_weight[v] + Σ weight)`.
    """
    a, b, count = edge_face_counts(faces, n_vertex)
    boundary_edge = count == 1
    on_boundary = np.zeros(n_vertex, bool)
    on_boundary[a[boundary_edge]] = True
    on_boundary[b[boundary_edge]] = True
    senders = np.concatenate([a, b])
    receivers = np.concatenate([b, a])
    c = np.concatenate([count, count]).astype(np.float64)
    be = np.concatenate([boundary_edge, boundary_edge])
    weight = np.where(on_boundary[receivers], be.astype(np.float64), c)
    keep = weight > 0
    order = np.argsort(receivers[keep], kind="stable")
    return (
        _i32(senders[keep][order]),
        _i32(receivers[keep][order]),
        weight[keep][order],
        on_boundary.astype(np.float64),
    )


def vertex_face_incidence(faces: np.ndarray, n_vertex: int) -> sp.csr_matrix:
    """Sparse `[n_face, n_vertex]` 0/1 incidence matrix."""
    f = np.asarray(faces, dtype=np.int64)
    n_face = f.shape[0]
    rows = np.repeat(np.arange(n_face), 3)
    return sp.csr_matrix((np.ones(3 * n_face), (rows, f.ravel())), shape=(n_face, n_vertex))


def face_ring_pairs(
    faces: np.ndarray, n_vertex: int, *, include_self: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs `(i, j)` of faces sharing at least one vertex, sorted by `i`.

    This is the vertex-based 1-ring face neighbourhood that Sun et al. (2007), Zheng et
    al. (2011) and Zhang et al. (2015) filter over.

    Returns:
      `(receivers, senders)` int32: face `i = receivers[k]` gathers from `senders[k]`.
    """
    inc = vertex_face_incidence(faces, n_vertex)
    ring = (inc @ inc.T).tocoo()
    i, j = ring.row.astype(np.int64), ring.col.astype(np.int64)
    if not include_self:
        keep = i != j
        i, j = i[keep], j[keep]
    order = np.lexsort((j, i))
    return _i32(i[order]), _i32(j[order])


def dual_edges(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces sharing an edge, each unordered pair once."""
    fa, fb = face_adjacency(faces, n_vertex)
    return _i32(fa), _i32(fb)


def vertex_corner_arrays(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(vertex [3 f], face [3 f])` of every corner, for vertex-from-face segment sums."""
    f = np.asarray(faces)
    return _i32(f.ravel()), _i32(np.repeat(np.arange(f.shape[0]), 3))


def boundary_vertex_mask(faces: np.ndarray, n_vertex: int) -> np.ndarray:
    """`[n_vertex]` bool, `True` on vertices of edges that belong to one face only."""
    a, b, count = edge_face_counts(faces, n_vertex)
    mask = np.zeros(n_vertex, bool)
    mask[a[count == 1]] = True
    mask[b[count == 1]] = True
    return mask


# --------------------------------------------------------------------------------------
# JAX kernels shared by the normal-filtering methods
# --------------------------------------------------------------------------------------


def gaussian(dist_sq, sigma):
    """`exp(-d² / (2σ²))` from squared distances."""
    return jnp.exp(-0.5 * dist_sq / (sigma * sigma))


def mean_adjacent_centroid_distance(vertices, faces, dual_a, dual_b):
    """Mean distance between the centroids of faces sharing an edge (a scalar).

    A mesh without two edge-adjacent faces gets 1 (any positive value: its filters
    then only see each face itself).
    """
    if dual_a.shape[0] == 0:
        return jnp.asarray(1.0, vertices.dtype)
    c = face_centroids(vertices, faces)
    return jnp.mean(safe_norm(c[dual_a] - c[dual_b]))


def weighted_normal_average(weights, normals, receivers, senders, n_face):
    """`normalize(Σ_j w_ij n_j)` per receiving face; zero-sum faces keep their normal.

    Only an exactly zero sum counts as zero: products of small areas and range weights
    are legitimately tiny (`safe_normalize`'s 1e-10 floor would freeze such faces).
    """
    acc = jax.ops.segment_sum(
        weights[:, None] * normals[senders],
        receivers,
        num_segments=n_face,
        indices_are_sorted=True,
    )
    norm = jnp.sqrt(jnp.sum(acc * acc, axis=-1, keepdims=True))
    ok = norm > 0
    return jnp.where(ok, acc / jnp.where(ok, norm, 1.0), normals)
