"""Host-side mesh topology: edges, face adjacency, boundary and neighbourhood index arrays.

Everything here is NumPy/SciPy on the host, built once per mesh from the faces alone (no
positions, no Python loop over elements), and imports no other `dmd_jax` module, so the
graph builder (`graph.build_mesh_graph`), the classic baselines, pre-smoothing,
tangential relaxation and the real-data patches all read one definition of what an edge,
a boundary or a neighbour is.

An undirected edge `a < b` has the key `a * n_vertex + b`; sorting the keys of every
face's three edges (the "edge groups") gives the unique edges, the faces on each, and
the pairs of faces sharing one in one pass. A *boundary* edge belongs to exactly one face;
a *non-manifold* edge to three or more, and all of their faces count as adjacent.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp


def _i32(x) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.int32)


# --------------------------------------------------------------------------------------
# Edges
# --------------------------------------------------------------------------------------


def sorted_unique(keys: np.ndarray) -> np.ndarray:
    """`np.unique(keys)` for a 1-D integer array, by a sort and a mask of first entries.

    NumPy 2.4's `np.unique` hashes: 3 s for 1M int64 keys here against 0.07 s for
    `np.sort`, which made `build_mesh_graph` take a minute at 1M vertices.

    Args:
      keys: `[n]` integers.

    Returns:
      `[k]` the distinct values, ascending.
    """
    k = np.sort(keys)
    if k.size == 0:
        return k
    return k[np.concatenate([[True], k[1:] != k[:-1]])]


def edge_keys(faces: np.ndarray, n_vertex: int) -> np.ndarray:
    """The key `min * n_vertex + max` of every face's three edges.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      `[3 n_face]` int64: edge (0, 1) of every face, then edge (1, 2), then edge (2, 0),
      so entry `k` belongs to face `k % n_face`.
    """
    f = np.asarray(faces)
    m = f.shape[0]
    key = np.empty(3 * m, np.int64)
    # Slot by slot with min/max instead of sorting a `[3 n_face, 2]` copy: a third of the
    # temporary memory (`presmooth.roughness` reads this on 1M-face chunks).
    for slot, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        lo = np.minimum(f[:, a], f[:, b]).astype(np.int64)
        hi = np.maximum(f[:, a], f[:, b]).astype(np.int64)
        np.multiply(lo, n_vertex, out=key[slot * m : (slot + 1) * m])
        key[slot * m : (slot + 1) * m] += hi
    return key


def vertex_edges(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected primal edges of a triangle mesh.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      `(a [n_edge], b [n_edge])` int64 with `a < b`, sorted by `(a, b)`.
    """
    return np.divmod(sorted_unique(edge_keys(faces, n_vertex)), n_vertex)


class EdgeGroups(NamedTuple):
    """Every face's edges sorted by key and grouped by edge (see `edge_groups`)."""

    key: np.ndarray  # [3 n_face] int64, ascending
    face: np.ndarray  # [3 n_face] int64, the face of each entry
    start: np.ndarray  # [n_edge] int64, where each edge's group starts
    size: np.ndarray  # [n_edge] int64, how many faces the edge has

    def edges(self, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
        """`(a [n_edge], b [n_edge])`, the unique undirected edges (`vertex_edges`)."""
        return np.divmod(self.key[self.start], n_vertex)


def edge_groups(faces: np.ndarray, n_vertex: int) -> EdgeGroups:
    """Every face's three edges grouped by edge, from one stable sort of `edge_keys`.

    Within a group the entries keep `edge_keys`' order (by slot, then face), so the faces
    of an edge are not sorted. `key[start]` are the unique edges' keys (as
    `vertex_edges`), `size` the number of faces on each.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.
    """
    key = edge_keys(faces, n_vertex)
    face = np.tile(np.arange(np.asarray(faces).shape[0], dtype=np.int64), 3)
    order = np.argsort(key, kind="stable")
    key, face = key[order], face[order]
    # Groups of equal keys in the sorted array: where each starts and how long it is.
    start = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if key.size else key
    size = np.diff(np.append(start, key.size))
    return EdgeGroups(key, face, start, size)


def edge_face_counts(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, ...]:
    """Unique undirected edges and the number of faces on each.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      `(a [n_edge], b [n_edge], count [n_edge])` int64, `a < b`, sorted by `(a, b)`.
    """
    g = edge_groups(faces, n_vertex)
    return (*g.edges(n_vertex), g.size)


# --------------------------------------------------------------------------------------
# Faces sharing an edge or a vertex
# --------------------------------------------------------------------------------------


def adjacent_faces(groups: EdgeGroups, n_face: int) -> tuple[np.ndarray, np.ndarray]:
    """`face_adjacency` from already computed `edge_groups` (no second sort of the edges).

    Args:
      groups: `edge_groups(faces, n_vertex)`.
      n_face: number of faces.

    Returns:
      `(a [n_pair], b [n_pair])` int64, `a < b`, sorted by `(a, b)`.
    """
    key, face_of, start, size = groups
    if not size.size or size.max() <= 2:
        # A manifold mesh (an edge has one or two faces): the pair of each two-face edge.
        two = start[size == 2]
        a, b = face_of[two], face_of[two + 1]
        a, b = np.minimum(a, b), np.maximum(a, b)
        keep = a < b
        return np.divmod(sorted_unique(a[keep] * n_face + b[keep]), n_face)
    # Each face-edge entry pairs with every entry of its edge group (vectorised).
    group = np.repeat(np.arange(start.size), size)
    reps = size[group]
    first = np.repeat(np.arange(key.size), reps)
    offset = np.arange(first.size) - np.repeat(np.cumsum(reps) - reps, reps)
    second = start[group[first]] + offset
    a, b = face_of[first], face_of[second]
    keep = a < b
    pair = sorted_unique(a[keep] * n_face + b[keep])
    return np.divmod(pair, n_face)


def face_adjacency(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces that share an edge, each unordered pair once (`a < b`).

    On a non-manifold edge with k faces all k(k-1)/2 pairs are adjacent.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      `(a [n_pair], b [n_pair])` int64, sorted by `(a, b)`.
    """
    return adjacent_faces(edge_groups(faces, n_vertex), np.asarray(faces).shape[0])


def dual_edges(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """`face_adjacency` as int32 arrays, the index type of the JAX kernels."""
    fa, fb = face_adjacency(faces, n_vertex)
    return _i32(fa), _i32(fb)


def face_adjacency_matrix(faces: np.ndarray, n_vertex: int) -> sp.csr_matrix:
    """Sparse symmetric `[n_face, n_face]` int8 adjacency of faces sharing an edge."""
    a, b = face_adjacency(np.asarray(faces), n_vertex)
    n = np.asarray(faces).shape[0]
    data = np.ones(2 * len(a), np.int8)
    return sp.csr_matrix((data, (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n))


def vertex_face_incidence(faces: np.ndarray, n_vertex: int) -> sp.csr_matrix:
    """Sparse `[n_face, n_vertex]` float64 0/1 incidence matrix."""
    f = np.asarray(faces, dtype=np.int64)
    n_face = f.shape[0]
    rows = np.repeat(np.arange(n_face), 3)
    return sp.csr_matrix((np.ones(3 * n_face), (rows, f.ravel())), shape=(n_face, n_vertex))


def face_ring_pairs(
    faces: np.ndarray, n_vertex: int, *, include_self: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs `(i, j)` of faces sharing at least one vertex, sorted by `(i, j)`.

    This is the vertex-based 1-ring face neighbourhood that Sun et al. (2007), Zheng et
    al. (2011) and Zhang et al. (2015) filter over.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.
      include_self: whether every face is its own neighbour.

    Returns:
      `(receivers [m], senders [m])` int32: face `i = receivers[k]` gathers from
      `senders[k]`.
    """
    inc = vertex_face_incidence(faces, n_vertex)
    ring = (inc @ inc.T).tocoo()
    i, j = ring.row.astype(np.int64), ring.col.astype(np.int64)
    if not include_self:
        keep = i != j
        i, j = i[keep], j[keep]
    order = np.lexsort((j, i))
    return _i32(i[order]), _i32(j[order])


def vertex_corner_arrays(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(vertex [3 n_face], face [3 n_face])` int32 of every corner, row-major, for
    vertex-from-face segment sums."""
    f = np.asarray(faces)
    return _i32(f.ravel()), _i32(np.repeat(np.arange(f.shape[0]), 3))


# --------------------------------------------------------------------------------------
# Boundary and vertex neighbourhoods
# --------------------------------------------------------------------------------------


def boundary_vertex_mask(faces: np.ndarray, n_vertex: int) -> np.ndarray:
    """`[n_vertex]` bool, `True` on vertices of edges that belong to one face only."""
    a, b, count = edge_face_counts(faces, n_vertex)
    mask = np.zeros(n_vertex, bool)
    mask[a[count == 1]] = True
    mask[b[count == 1]] = True
    return mask


def umbrella_weights(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, ...]:
    """Weights of the uniform umbrella operator with VCG/MeshLab's boundary rule.

    An interior vertex averages its 1-ring neighbours (each edge weighted by its number
    of faces, i.e. uniformly on a manifold). A vertex on a boundary edge averages
    itself and its neighbours along boundary edges only, so open boundaries are
    smoothed as curves instead of shrinking into the surface. This is
    `vcg::tri::Smooth::AccumulateLaplacianInfo`, which pymeshlab's Taubin and
    Laplacian filters use.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      `(senders [m] int32, receivers [m] int32, weight [m] float64, self_weight
      [n_vertex] float64)`, sorted by receiver: the average at `v` is
      `(self_weight[v] x_v + Σ weight x_s) / (self_weight[v] + Σ weight)`.
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


def one_ring_mean(faces: np.ndarray, n_vertex: int) -> sp.csr_matrix:
    """The row-normalised 0/1 vertex adjacency: `M @ x` is each vertex's 1-ring mean.

    Unlike `umbrella_weights` every neighbour counts once, whatever its number of
    faces, and boundary vertices average their whole (one-sided) ring.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.

    Returns:
      Sparse `[n_vertex, n_vertex]` float64; rows of vertices without a face are 0.
    """
    f = np.asarray(faces)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertex, n_vertex))
    adj.data[:] = 1.0  # edges shared by two faces were summed twice
    degree = np.asarray(adj.sum(axis=1)).ravel()
    inv = np.where(degree > 0, 1.0 / np.maximum(degree, 1.0), 0.0)
    return sp.diags(inv) @ adj
