"""The paper's graph layers as pure gather + `jax.ops.segment_sum` functions.

Sizes come from static shapes, so every function jits once per shape bucket. No dense
adjacency matrix is ever built; tests compare each op with the paper's dense formula.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

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
