"""`gcn_aggregate_ell` and `ell_layout` against `gcn_aggregate` and dense references.

The forward pass must equal the segment-sum op on the same graph (primal, dual, padded
batches); the custom backward pass (a gather through `reverse_slot`, no scatter) must
equal plain autodiff of a dense `[n, n]` operator built from the edge list, for
features and for non-symmetric edge weights.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, shared_mesh_path, tetrahedron

from dmd_jax import ops
from dmd_jax.graph import (
    batch_mesh_graphs,
    build_mesh_graph,
    ell_layout,
    pad_mesh_graph,
    padded_sizes_for,
)
from dmd_jax.io import load_mesh


def dense_operator(senders, receivers, weight, n_node):
    """`M[r, s] = sum of the weights of the edges s -> r`, as a JAX expression of
    `weight` (so autodiff through it is the independent reference)."""
    m = jnp.zeros((n_node, n_node), weight.dtype)
    return m.at[jnp.asarray(receivers), jnp.asarray(senders)].add(weight)


def graphs():
    v, f = icosphere(2)
    ico = build_mesh_graph(f, v.shape[0])
    _, ft = tetrahedron()
    tet = build_mesh_graph(ft, 4)
    return {"icosphere": ico, "tetrahedron": tet}


@pytest.fixture(scope="module", params=["icosphere", "tetrahedron"])
def graph(request):
    return graphs()[request.param]


@pytest.mark.parametrize("stream", ["vertex", "face"])
@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_forward_matches_gcn_aggregate(graph, stream, use_jit):
    s = getattr(graph, f"{stream}_senders")
    r = getattr(graph, f"{stream}_receivers")
    w = getattr(graph, f"{stream}_edge_weight")
    n = graph.n_vertex if stream == "vertex" else graph.n_face
    layout = ell_layout(s, r, w, n)
    x = jnp.asarray(np.random.default_rng(0).normal(size=(n, 6)))
    agg = jax.jit(ops.gcn_aggregate_ell) if use_jit else ops.gcn_aggregate_ell
    expected = ops.gcn_aggregate(x, s, r, w)
    np.testing.assert_allclose(agg(x, *layout), expected, rtol=1e-12, atol=1e-12)


def test_layout_of_tetrahedron_by_hand():
    # Every vertex of a tetrahedron sees all four (self loop included), weight 1/4 each.
    _, f = tetrahedron()
    g = build_mesh_graph(f, 4)
    layout = ell_layout(g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight, 4)
    assert layout.neighbours.shape == (4, 4)
    np.testing.assert_array_equal(np.sort(layout.neighbours, axis=1), np.tile(np.arange(4), (4, 1)))
    np.testing.assert_allclose(layout.weights, 0.25)
    # The reverse of row i, slot k (the entry j -> i) is the slot of i in row j.
    for i in range(4):
        for k in range(4):
            j = layout.neighbours[i, k]
            assert layout.neighbours[j, layout.reverse_slot[i, k]] == i


def test_padded_batch_matches_gcn_aggregate():
    v1, f1 = icosphere(1)
    v2, f2 = tetrahedron()
    batch = batch_mesh_graphs([build_mesh_graph(f1, len(v1)), build_mesh_graph(f2, len(v2))])
    g = pad_mesh_graph(batch, padded_sizes_for(batch))
    # pad_mesh_graph repeats the zero-weight padding self loop: the layout merges them.
    assert len(np.unique(g.vertex_senders[-5:])) == 1
    layout = ell_layout(g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight, g.n_vertex)
    assert layout.neighbours.shape[1] == np.bincount(batch.vertex_receivers).max()
    x = jnp.asarray(np.random.default_rng(1).normal(size=(g.n_vertex, 3)))
    expected = ops.gcn_aggregate(x, g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)
    np.testing.assert_allclose(ops.gcn_aggregate_ell(x, *layout), expected, atol=1e-12)


def test_real_mesh_float32_matches_gcn_aggregate():
    v, f = load_mesh(shared_mesh_path("fandisk.off"))
    g = build_mesh_graph(f, len(v))
    layout = ell_layout(g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight, len(v))
    x = jnp.asarray(np.random.default_rng(2).normal(size=(len(v), 16)), jnp.float32)
    out = jax.jit(ops.gcn_aggregate_ell)(x, *layout)
    assert out.dtype == jnp.float32
    expected = ops.gcn_aggregate(x, g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)


def test_gradients_match_dense_autodiff_with_asymmetric_weights(graph):
    s, r = graph.vertex_senders, graph.vertex_receivers
    n = graph.n_vertex
    rng = np.random.default_rng(3)
    # Weights differ between s -> r and r -> s, so a backward pass that reused the
    # forward table (a symmetric transpose) would be wrong.
    w = rng.uniform(0.1, 1.0, size=s.shape)
    layout = ell_layout(s, r, w, n)
    slot_of_edge = {
        (int(layout.neighbours[i, k]), i): (i, k)
        for i in range(n)
        for k in range(layout.neighbours.shape[1])
        if layout.weights[i, k] != 0
    }
    rows, cols = np.array([slot_of_edge[(int(a), int(b))] for a, b in zip(s, r, strict=True)]).T
    x = jnp.asarray(rng.normal(size=(n, 4)))
    target = jnp.asarray(rng.normal(size=(n, 4)))

    def loss_ell(x, weights):
        return jnp.sum(
            (ops.gcn_aggregate_ell(x, layout.neighbours, weights, layout.reverse_slot) - target)
            ** 2
        )

    def loss_dense(x, w_edges):
        return jnp.sum((dense_operator(s, r, w_edges, n) @ x - target) ** 2)

    gx, gw = jax.jit(jax.grad(loss_ell, argnums=(0, 1)))(x, jnp.asarray(layout.weights))
    ex, ew = jax.grad(loss_dense, argnums=(0, 1))(x, jnp.asarray(w))
    np.testing.assert_allclose(gx, ex, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(gw)[rows, cols], ew, rtol=1e-10, atol=1e-10)


def test_feature_gradient_matches_gcn_aggregate_through_layers():
    # Three residual GCN layers, the shape the model uses: the gradient must not depend
    # on which aggregation runs.
    v, f = icosphere(2)
    g = build_mesh_graph(f, len(v))
    layout = ell_layout(g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight, len(v))
    rng = np.random.default_rng(4)
    w = jnp.asarray(rng.normal(size=(5, 5)) / 2)
    x = jnp.asarray(rng.normal(size=(len(v), 5)))

    def loss(x, aggregate):
        for _ in range(3):
            x = jax.nn.relu(aggregate(x @ w)) + x
        return jnp.sum(x**2)

    def seg(x):
        return ops.gcn_aggregate(x, g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)

    def ell(x):
        return ops.gcn_aggregate_ell(x, *layout)

    expected = jax.grad(loss)(x, seg)
    np.testing.assert_allclose(
        jax.jit(jax.grad(loss), static_argnums=1)(x, ell), expected, rtol=1e-10
    )


def test_layout_rejects_bad_input():
    with pytest.raises(ValueError, match="no reverse"):
        ell_layout(np.array([0, 1]), np.array([1, 1]), np.ones(2), 2)
    with pytest.raises(ValueError, match="1-D of one length"):
        ell_layout(np.array([0, 1]), np.array([1]), np.ones(2), 2)
    with pytest.raises(ValueError, match=r"lie in \[0, 2\)"):
        ell_layout(np.array([0, 2]), np.array([2, 0]), np.ones(2), 2)
    with pytest.raises(ValueError, match="n_node must be positive"):
        ell_layout(np.array([], int), np.array([], int), np.ones(0), 0)


def test_aggregate_rejects_bad_shapes():
    layout = ell_layout(np.array([0, 1]), np.array([1, 0]), np.ones(2), 2)
    with pytest.raises(ValueError, match="features must be"):
        ops.gcn_aggregate_ell(jnp.zeros(2), *layout)
    with pytest.raises(ValueError, match="neighbours must be"):
        ops.gcn_aggregate_ell(jnp.zeros((3, 2)), *layout)
    with pytest.raises(ValueError, match="must have the shape of neighbours"):
        ops.gcn_aggregate_ell(
            jnp.zeros((2, 2)), layout.neighbours, layout.weights[:, :0], layout.reverse_slot
        )
