"""The paper's graph layers as pure gather + `jax.ops.segment_sum` functions.

Sizes come from static shapes, so every function jits once per shape bucket. No dense
adjacency matrix is ever built; tests compare each op with the paper's dense formula.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dmd_jax import geometry
from dmd_jax.graph import MeshGraph


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
    return geometry.corner_sum(vertex_features, faces) / 3.0


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
    # Written out over the three corners: one fusion on CPU, no `[n_face, 3, k]` block.
    vertex_features = jnp.asarray(vertex_features)  # NumPy cannot take traced indices
    corner = [jnp.abs(vertex_features[faces[:, k]] - face_features) for k in range(3)]
    return (corner[0] + corner[1] + corner[2]) / 3.0


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
# Padded-neighbour (ELL) tables: the same operator as `gcn_aggregate`, faster on CPU
# --------------------------------------------------------------------------------------


def _ell_sum(features, neighbours, weights):
    """`out[i] = sum_k weights[i, k] * features[neighbours[i, k]]`: `[n_node, d]`.

    Slot 0 is the row itself (`graph.ell_layout`): read without a gather.
    """
    w = weights.astype(features.dtype)
    # One gather per slot, summed in one loop fusion: no `[n_node, max_degree, d]` buffer.
    out = features * w[:, 0, None]
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
