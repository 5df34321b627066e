"""The model and `denoise` on ELL layouts (`with_ell_layout`) against the segment sum.

`MeshGraph.vertex_ell` / `face_ell` hold the same GCN operators as the edge lists, so
DMD-Net's outputs and parameter gradients must agree with the segment-sum path up to
float summation order, padding rows included, and `denoise` must give the same vertices
with either `aggregation`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, shared_mesh_path, tetrahedron
from test_inference import TINY_CONFIG, tiny_params
from test_model import FAST_COMPILE, random_params

from dmd_jax import checkpoints, ops
from dmd_jax import graph as graph_module
from dmd_jax.config import preset, variant_config
from dmd_jax.graph import (
    batch_mesh_graphs,
    build_mesh_graph,
    ell_layout,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    with_ell_layout,
)
from dmd_jax.inference import denoise
from dmd_jax.io import load_mesh
from dmd_jax.model import Aggregator, DMDNet, param_shapes


def padded_pair():
    """A bumpy icosphere and a tetrahedron as one padded batch: `(vertices, graph)`."""
    v1, f1 = icosphere(1)
    v1 = v1 * (1.0 + 0.1 * np.random.default_rng(0).standard_normal((len(v1), 1))) / 2.2
    v2, f2 = tetrahedron()
    batch = batch_mesh_graphs([build_mesh_graph(f1, len(v1)), build_mesh_graph(f2, len(v2))])
    graph = pad_mesh_graph(batch, padded_sizes_for(batch))
    return pad_vertex_array(np.concatenate([v1, v2 / 2.0]), graph.n_vertex), graph


# --------------------------------------------------------------------------------------
# with_ell_layout
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("slot_multiple", [1, 4, 5])
def test_with_ell_layout_is_ell_layout_plus_rounding_slots(slot_multiple):
    _, graph = padded_pair()
    out = with_ell_layout(graph, slot_multiple=slot_multiple)
    for stream, n_node in (("vertex", graph.n_vertex), ("face", graph.n_face)):
        ref = ell_layout(
            getattr(graph, f"{stream}_senders"),
            getattr(graph, f"{stream}_receivers"),
            getattr(graph, f"{stream}_edge_weight"),
            n_node,
        )
        got = getattr(out, f"{stream}_ell")
        width = ref.neighbours.shape[1]
        assert got.neighbours.shape[0] == n_node
        assert got.neighbours.shape[1] % slot_multiple == 0
        assert width <= got.neighbours.shape[1] < width + slot_multiple
        for name in ("neighbours", "weights", "reverse_slot"):
            a, b = getattr(got, name), getattr(ref, name)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a[:, :width], b)
        # Rounding slots: own row, weight 0, their own reverse slot.
        extra = got.neighbours.shape[1] - width
        rows = np.arange(n_node)[:, None]
        np.testing.assert_array_equal(
            got.neighbours[:, width:], np.broadcast_to(rows, (n_node, extra))
        )
        np.testing.assert_array_equal(got.weights[:, width:], 0.0)
        slots = np.arange(width, width + extra)[None, :]
        np.testing.assert_array_equal(
            got.reverse_slot[:, width:], np.broadcast_to(slots, (n_node, extra))
        )
    # Every other field is the input's.
    for name in graph._fields:
        if not name.endswith("_ell"):
            assert getattr(out, name) is getattr(graph, name)


def test_rounded_layout_is_the_same_operator_with_the_same_transpose():
    _, graph = padded_pair()
    ell = with_ell_layout(graph, slot_multiple=8).face_ell
    assert ell.neighbours.shape[1] == 8  # max face valence 3 + 1, rounded up
    x = jnp.asarray(np.random.default_rng(1).normal(size=(graph.n_face, 5)))
    ct = jnp.asarray(np.random.default_rng(2).normal(size=(graph.n_face, 5)))
    args = (graph.face_senders, graph.face_receivers, graph.face_edge_weight)
    ref, ref_vjp = jax.vjp(lambda y: ops.gcn_aggregate(y, *args), x)
    got, got_vjp = jax.vjp(lambda y: ops.gcn_aggregate_ell(y, *ell), x)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got_vjp(ct)[0], ref_vjp(ct)[0], rtol=1e-12, atol=1e-12)


def test_batching_and_padding_drop_the_layouts():
    v, f = icosphere(1)
    graph = with_ell_layout(build_mesh_graph(f, len(v)))
    assert graph.vertex_ell is not None and graph.face_ell is not None
    assert graph.vertex_ell.neighbours.shape == (graph.n_vertex, 8)  # valence 6 + 1 → 8
    batch = batch_mesh_graphs([graph, graph])
    assert batch.vertex_ell is None and batch.face_ell is None
    padded = pad_mesh_graph(graph, padded_sizes_for(graph))
    assert padded.vertex_ell is None and padded.face_ell is None
    # None is an empty subtree: a graph without layouts has just the 14 index arrays.
    assert len(jax.tree.leaves(padded)) == 14
    assert len(jax.tree.leaves(with_ell_layout(padded))) == 20


def test_with_ell_layout_rejects_bad_slot_multiple():
    _, graph = padded_pair()
    with pytest.raises(ValueError, match="slot_multiple"):
        with_ell_layout(graph, slot_multiple=0)


# --------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------


def test_attention_aggregator_ignores_ell():
    _, graph = padded_pair()
    ell = with_ell_layout(graph).vertex_ell
    x = jnp.asarray(np.random.default_rng(3).normal(size=(graph.n_vertex, 4)))
    edges = (graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight)
    agg = Aggregator(4, attention=True)
    params = agg.init(jax.random.PRNGKey(0), x, *edges)
    np.testing.assert_array_equal(
        agg.apply(params, x, *edges, ell=ell), agg.apply(params, x, *edges)
    )


@pytest.mark.parametrize(
    "variant",
    # fgt3 and fgt_1s take ~20 s each: `make test-slow`.
    [
        "fgt8",
        pytest.param("fgt3", marks=pytest.mark.slow),
        pytest.param("fgt_1s", marks=pytest.mark.slow),
    ],
)
def test_dmdnet_forward_and_gradient_match_segment_sum(variant):
    # fgt8 is the `test` preset (FE, transformer, two-stream denoiser); fgt3 feeds the
    # transformer 3 columns; fgt_1s runs single-stream networks (no face graph use).
    # float64, so the comparison sees the operators and the custom VJP, not float32
    # rounding: random params amplify that to ~1e-4 in some gradients (float32, the
    # production dtype, is compared end to end by the `denoise` test below).
    cfg = variant_config(preset("test").model, variant).with_edits({"dtype": "float64"})
    model = DMDNet(cfg)
    params = random_params(param_shapes(cfg), seed=0)
    vertices, graph = padded_pair()
    mask = graph.vertex_mask
    target = np.random.default_rng(4).normal(size=vertices.shape)

    def loss(params, vertices, graph):
        denoised, features, _ = model.apply({"params": params}, vertices, graph)
        # Real rows only: padding rows of the output must not matter, and do not here.
        total = jnp.sum(jnp.where(mask[:, None], jnp.sin(3.0 * denoised) * target, 0.0))
        return total, (denoised, features)

    run = jax.jit(jax.value_and_grad(loss, has_aux=True), compiler_options=FAST_COMPILE)
    plain = jax.tree.map(jnp.asarray, graph)
    ell = jax.tree.map(jnp.asarray, with_ell_layout(graph))
    (_, (ref, ref_feat)), ref_grad = run(params, vertices, plain)
    (_, (got, got_feat)), got_grad = run(params, vertices, ell)
    assert got.dtype == jnp.float64
    scale = float(jnp.abs(ref[mask]).max())
    np.testing.assert_allclose(got[mask], ref[mask], rtol=1e-9, atol=1e-9 * scale)
    if ref_feat is not None:
        np.testing.assert_allclose(got_feat[mask], ref_feat[mask], rtol=1e-9, atol=1e-9)
    for g, r in zip(jax.tree.leaves(got_grad), jax.tree.leaves(ref_grad), strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-9, atol=1e-9 * float(jnp.abs(r).max()))

    # Junk in the padding rows changes no real row (the layouts keep the meshes apart).
    junk = np.where(mask[:, None], vertices, 7.0)
    (_, (moved, _)), _ = run(params, junk, ell)
    np.testing.assert_allclose(moved[mask], got[mask], rtol=1e-12, atol=1e-12 * scale)


# --------------------------------------------------------------------------------------
# denoise
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_bundle():
    return checkpoints.ModelBundle(params=tiny_params(), config=TINY_CONFIG, meta={})


def test_denoise_ell_matches_segment_sum(small_bundle, monkeypatch):
    v, f = load_mesh(shared_mesh_path("fandisk.off"))
    scale = float((v.max(0) - v.min(0)).max())
    built = []

    def spy(graph, **kwargs):
        built.append(graph.n_vertex)
        return with_ell_layout(graph, **kwargs)

    monkeypatch.setattr(graph_module, "with_ell_layout", spy)
    ell = denoise(v, f, small_bundle)
    assert len(built) == 1  # the default builds the layouts...
    seg = denoise(v, f, small_bundle, aggregation="segment_sum")
    assert len(built) == 1  # ...segment_sum does not
    assert np.abs(seg - v).max() > 1e-4 * scale  # the network does move vertices
    np.testing.assert_allclose(ell, seg, rtol=1e-5, atol=1e-5 * scale)
    # fandisk's tables are far below the cap: "auto" keeps both, as "ell" does.
    explicit = denoise(v, f, small_bundle, aggregation="ell")
    np.testing.assert_array_equal(explicit, ell)


@pytest.mark.parametrize("bad", ["ELL", "dense", "", None])
def test_denoise_rejects_unknown_aggregation(small_bundle, bad):
    v, f = tetrahedron()
    with pytest.raises(ValueError, match="unknown aggregation"):
        denoise(v, f, small_bundle, aggregation=bad)


def bipyramid(k: int):
    """Two apexes of valence `k` over a `k`-gon ring: `([k + 2, 3] vertices, [2k, 3] faces)`."""
    t = 2 * np.pi * np.arange(k) / k
    ring = np.stack([np.cos(t), np.sin(t), np.zeros(k)], 1)
    v = np.concatenate([ring, [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
    i, j = np.arange(k), (np.arange(k) + 1) % k
    f = np.concatenate([np.stack([i, j, np.full(k, k)], 1), np.stack([j, i, np.full(k, k + 1)], 1)])
    return v, f


def test_max_fill_leaves_out_only_the_table_of_a_high_valence_graph():
    v, f = bipyramid(60)
    g = build_mesh_graph(f, len(v))
    graph = pad_mesh_graph(g, padded_sizes_for(g))
    # Vertex graph: 64 slots per row for a mean of about 6 distinct edges per row.
    capped = with_ell_layout(graph, max_fill=8.0)
    assert capped.vertex_ell is None
    assert capped.face_ell is not None  # every face has 3 neighbours: width 4
    full = with_ell_layout(graph)
    np.testing.assert_array_equal(capped.face_ell.neighbours, full.face_ell.neighbours)
    assert full.vertex_ell.neighbours.shape[1] == 64
    # A regular mesh keeps both tables under the same cap.
    v2, f2 = icosphere(2)
    g2 = build_mesh_graph(f2, len(v2))
    kept = with_ell_layout(pad_mesh_graph(g2, padded_sizes_for(g2)), max_fill=8.0)
    assert kept.vertex_ell is not None and kept.face_ell is not None
    with pytest.raises(ValueError, match="max_fill"):
        with_ell_layout(graph, max_fill=0.5)


def test_denoise_auto_falls_back_to_the_edge_lists_where_a_table_is_mostly_padding(
    small_bundle, monkeypatch
):
    v, f = bipyramid(60)
    v = v + 0.01 * np.random.default_rng(1).standard_normal(v.shape)
    built = []

    def spy(graph, **kwargs):
        out = with_ell_layout(graph, **kwargs)
        built.append(out)
        return out

    monkeypatch.setattr(graph_module, "with_ell_layout", spy)
    auto = denoise(v, f, small_bundle)
    assert built[-1].vertex_ell is None and built[-1].face_ell is not None
    forced = denoise(v, f, small_bundle, aggregation="ell")
    assert built[-1].vertex_ell is not None
    seg = denoise(v, f, small_bundle, aggregation="segment_sum")
    for got in (auto, forced):
        np.testing.assert_allclose(got, seg, rtol=1e-5, atol=1e-5)
