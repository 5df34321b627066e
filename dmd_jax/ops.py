"""The paper's graph layers as pure gather + `jax.ops.segment_sum` functions.

Sizes come from static shapes, so every function jits once per shape bucket. No dense
adjacency matrix is ever built; tests compare each op with the paper's dense formula.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.mesh import MeshGraph


def gcn_aggregate(features, senders, receivers, edge_weight):
    """Symmetric-normalised neighbourhood sum, `D̂^-1/2 Â D̂^-1/2 X` without the weight.

    Args:
      features: `[n_node, d]` node features.
      senders: `[n_edge]` int32, edges of `A + I` in both directions.
      receivers: `[n_edge]` int32, sorted ascending (as `build_mesh_graph` makes them).
      edge_weight: `[n_edge]` the normalised weights `1/sqrt(d_s d_r)`.

    Returns:
      `[n_node, d]` aggregated features.
    """
    messages = features[senders] * edge_weight[:, None].astype(features.dtype)
    return jax.ops.segment_sum(
        messages, receivers, num_segments=features.shape[0], indices_are_sorted=True
    )


def primal_aggregate(graph: MeshGraph, features):
    """`gcn_aggregate` over the primal (vertex) graph of `graph`: `[n_vertex, d]`."""
    return gcn_aggregate(
        features, graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight
    )


def dual_aggregate(graph: MeshGraph, features):
    """`gcn_aggregate` over the dual (face) graph of `graph`: `[n_face, d]`."""
    return gcn_aggregate(features, graph.face_senders, graph.face_receivers, graph.face_edge_weight)


def primal_to_dual(vertex_features, faces):
    """P2D: each face's feature is the mean of its three vertices, `(1/3) A_FV X_V`.

    Args:
      vertex_features: `[n_vertex, d]`.
      faces: `[n_face, 3]` int32.

    Returns:
      `[n_face, d]`.
    """
    return vertex_features[faces].mean(axis=1)


def dual_to_primal(face_features, faces, vertex_face_degree):
    """D2P: each vertex's feature is the mean over its incident faces, `D_VF^-1 A_VF X_F`.

    Vertices with `vertex_face_degree == 0` (isolated, or padding, even though padding
    faces reference the first padding vertex) get zeros.

    Args:
      face_features: `[n_face, d]`.
      faces: `[n_face, 3]` int32.
      vertex_face_degree: `[n_vertex]` number of faces incident to each vertex.

    Returns:
      `[n_vertex, d]`.
    """
    n_face, d = face_features.shape
    n_vertex = vertex_face_degree.shape[0]
    summed = jax.ops.segment_sum(
        jnp.broadcast_to(face_features[:, None, :], (n_face, 3, d)).reshape(3 * n_face, d),
        faces.reshape(-1),
        num_segments=n_vertex,
    )
    # Padding faces sit on a padding vertex whose degree is 0: zero it like an isolated
    # vertex, or its feature would be the sum over all padding faces and grow per layer.
    degree = vertex_face_degree.astype(face_features.dtype)
    inverse = jnp.where(degree > 0, 1.0 / jnp.maximum(degree, 1.0), 0.0)
    return summed * inverse[:, None]


def dual_average_pool(vertex_features, face_features, faces):
    """DAP: per face, the mean over its three vertices of `|p_i - d|` (element-wise).

    Args:
      vertex_features: `[n_vertex, k]` primal-stream features `p`.
      face_features: `[n_face, k]` dual-stream features `d`.
      faces: `[n_face, 3]` int32.

    Returns:
      `[n_face, k]` fused dual features.
    """
    return jnp.abs(vertex_features[faces] - face_features[:, None, :]).mean(axis=1)


def feature_average_pool(vertex_features, vertex_graph, n_graph: int, vertex_mask=None):
    """FAP: mean of the vertex features of each mesh in a batch.

    Args:
      vertex_features: `[n_vertex, d]`.
      vertex_graph: `[n_vertex]` int32 graph id of each vertex.
      n_graph: number of graphs (static).
      vertex_mask: optional `[n_vertex]` bool; masked-out (padding) vertices are ignored.

    Returns:
      `[n_graph, d]`; a graph with no (unmasked) vertex gets zeros.
    """
    if vertex_mask is None:
        weight = jnp.ones(vertex_features.shape[0], vertex_features.dtype)
    else:
        weight = vertex_mask.astype(vertex_features.dtype)
    summed = jax.ops.segment_sum(
        vertex_features * weight[:, None], vertex_graph, num_segments=n_graph
    )
    count = jax.ops.segment_sum(weight, vertex_graph, num_segments=n_graph)
    return summed / jnp.maximum(count, 1.0)[:, None]


def broadcast_to_vertices(graph_features, vertex_graph):
    """Gives every vertex the feature of its graph: `[n_graph, ...]` → `[n_vertex, ...]`."""
    return graph_features[vertex_graph]


# --------------------------------------------------------------------------------------
# Padded-neighbour (ELL) layout: the same operator as `gcn_aggregate`, faster on CPU
# --------------------------------------------------------------------------------------


class EllLayout(NamedTuple):
    """A graph operator as a padded neighbour table (ELL format); see `ell_layout`.

    Attributes:
      neighbours: `[n_node, max_degree]` int32; row `i` lists the senders into node `i`;
        unused slots point at `i` itself.
      weights: `[n_node, max_degree]`, the weight of each slot; 0 on unused slots.
      reverse_slot: `[n_node, max_degree]` int32; for the entry `j -> i` in slot `k` of
        row `i`, the slot of the entry `i -> j` in row `j` (unused slots: their own slot).
    """

    neighbours: np.ndarray
    weights: np.ndarray
    reverse_slot: np.ndarray


def ell_layout(
    senders, receivers, edge_weight, n_node: int, *, max_fill: float | None = None
) -> EllLayout | None:
    """Builds the ELL layout of the operator `out[r] += w * x[s]` on the host (NumPy).

    Duplicate `(sender, receiver)` pairs are merged by summing their weights (the padding
    self loops of `pad_mesh_graph` become one zero-weight slot), so the layout is the same
    operator as `gcn_aggregate(x, senders, receivers, edge_weight)`. The edge set must be
    structurally symmetric (every `s -> r` has an `r -> s`, as in `MeshGraph`); the
    weights need not be. The table has `max_degree` columns, so the work is
    `n_node * max_degree` rather than `n_edge`: fine for meshes (valence ≤ ~15), wasteful
    for graphs with a few very high-degree nodes.

    Args:
      senders: `[n_edge]` integer sender of each edge.
      receivers: `[n_edge]` integer receiver of each edge.
      edge_weight: `[n_edge]` weight of each edge.
      n_node: number of nodes.
      max_fill: return None, before allocating the table, when it would hold more than
        this many slots (`n_node × max_degree`) per distinct edge (None: no limit).

    Returns:
      An `EllLayout`; pass it as `gcn_aggregate_ell(features, *layout)`. None if
      `max_fill` is exceeded.

    Raises:
      ValueError: on mismatched shapes, indices outside `[0, n_node)`, or an edge whose
        reverse is missing.
    """
    s = np.asarray(senders).astype(np.int64)
    r = np.asarray(receivers).astype(np.int64)
    w = np.asarray(edge_weight)
    if s.ndim != 1 or s.shape != r.shape or s.shape != w.shape:
        raise ValueError(
            "senders, receivers and edge_weight must be 1-D of one length, got shapes "
            f"{s.shape}, {r.shape}, {w.shape}"
        )
    if n_node < 1:
        raise ValueError(f"n_node must be positive, got {n_node}")
    if s.size and (min(s.min(), r.min()) < 0 or max(s.max(), r.max()) >= n_node):
        raise ValueError(f"edge indices must lie in [0, {n_node})")
    if not np.issubdtype(w.dtype, np.floating):
        w = w.astype(np.float32)
    # np.sort plus a mask rather than np.unique: the same result, several times faster.
    key = r * n_node + s
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.ones(key.size, bool)
    first[1:] = key[1:] != key[:-1]
    group = np.cumsum(first) - 1
    key = key[first]
    weight = np.bincount(group, weights=w[order].astype(np.float64), minlength=key.size)
    r, s = np.divmod(key, n_node)
    degree = np.bincount(r, minlength=n_node)
    width = max(int(degree.max()), 1)
    if max_fill is not None and n_node * width > max_fill * max(key.size, 1):
        return None
    slot = np.arange(key.size) - (np.cumsum(degree) - degree)[r]
    rows = np.arange(n_node)
    neighbours = np.repeat(rows[:, None], width, axis=1).astype(np.int32)
    weights = np.zeros((n_node, width), w.dtype)
    reverse_slot = np.repeat(np.arange(width)[None, :], n_node, axis=0).astype(np.int32)
    reverse = np.searchsorted(key, s * n_node + r)
    found = reverse < key.size
    found[found] = key[reverse[found]] == (s * n_node + r)[found]
    if not found.all():
        i = int(np.flatnonzero(~found)[0])
        raise ValueError(
            f"edge {s[i]} -> {r[i]} has no reverse {r[i]} -> {s[i]}; the ELL layout needs "
            "a structurally symmetric edge set"
        )
    neighbours[r, slot] = s
    weights[r, slot] = weight
    reverse_slot[r, slot] = slot[reverse]
    return EllLayout(neighbours, weights, reverse_slot)


def _ell_sum(features, neighbours, weights):
    """`out[i] = sum_k weights[i, k] * features[neighbours[i, k]]`: `[n_node, d]`."""
    w = weights.astype(features.dtype)
    # One gather per slot, summed in one loop fusion: no `[n_node, max_degree, d]` buffer.
    out = features[neighbours[:, 0]] * w[:, 0, None]
    for k in range(1, neighbours.shape[1]):
        out = out + features[neighbours[:, k]] * w[:, k, None]
    return out


def _ell_sum_unfused(features, neighbours, weights):
    """`_ell_sum`, kept out of the producers' fusion on CPU.

    XLA's CPU fusion pulls the producer of `features` (a previous aggregation, the
    cotangent of the loss) into the gather and recomputes it once per slot. Without the
    boundary, `grad(sum(out²))` was 1.5-1.8× slower and the gradient of three residual
    GCN layers 3.5-4.3× slower (100k-node grid, width 64, two runs); the forward alone
    was within noise. A conditional is a fusion boundary XLA keeps; its predicate is
    always true for a valid layout (indices are non-negative).
    """

    def cpu(features, neighbours, weights):
        return jax.lax.cond(
            neighbours[0, 0] >= 0,
            _ell_sum,
            lambda x, n, w: jnp.zeros_like(x),
            features,
            neighbours,
            weights,
        )

    return jax.lax.platform_dependent(features, neighbours, weights, cpu=cpu, default=_ell_sum)


@jax.custom_vjp
def gcn_aggregate_ell(features, neighbours, weights, reverse_slot):
    """`gcn_aggregate` on an `EllLayout`: a masked gather-sum, no scatter, no dense matrix.

    Same result as `gcn_aggregate(features, senders, receivers, edge_weight)` for the
    layout `ell_layout(senders, receivers, edge_weight, n_node)` (up to summation order).
    The backward pass gathers too: the transpose of the operator is the same table with
    the weights read through `reverse_slot`, so no scatter-add is needed. Gradients flow
    to `features` and `weights`.

    Args:
      features: `[n_node, d]` node features.
      neighbours: `[n_node, max_degree]` int32 from `ell_layout`.
      weights: `[n_node, max_degree]` slot weights (0 on unused slots).
      reverse_slot: `[n_node, max_degree]` int32 from `ell_layout`.

    Returns:
      `[n_node, d]` aggregated features.
    """
    _check_ell(features, neighbours, weights, reverse_slot)
    return _ell_sum_unfused(features, neighbours, weights)


def _check_ell(features, neighbours, weights, reverse_slot):
    if features.ndim != 2:
        raise ValueError(f"features must be [n_node, d], got shape {features.shape}")
    if neighbours.ndim != 2 or neighbours.shape[0] != features.shape[0]:
        raise ValueError(
            f"neighbours must be [n_node={features.shape[0]}, max_degree], "
            f"got shape {neighbours.shape}"
        )
    if weights.shape != neighbours.shape or reverse_slot.shape != neighbours.shape:
        raise ValueError(
            f"weights {weights.shape} and reverse_slot {reverse_slot.shape} must have the "
            f"shape of neighbours {neighbours.shape}"
        )


def _gcn_aggregate_ell_fwd(features, neighbours, weights, reverse_slot):
    out = gcn_aggregate_ell(features, neighbours, weights, reverse_slot)
    return out, (features, neighbours, weights, reverse_slot)


def _gcn_aggregate_ell_bwd(residuals, cotangent):
    features, neighbours, weights, reverse_slot = residuals
    # Row j of the transpose holds, in slot k, the weight of the entry j -> i in row i.
    transposed = weights[neighbours, reverse_slot]
    d_features = _ell_sum_unfused(cotangent, neighbours, transposed)
    d_weights = jnp.sum(cotangent[:, None, :] * features[neighbours], axis=-1)
    return d_features, None, d_weights.astype(weights.dtype), None


gcn_aggregate_ell.defvjp(_gcn_aggregate_ell_fwd, _gcn_aggregate_ell_bwd)
