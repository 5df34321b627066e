"""DMD-Net modules against dense NumPy formulas; every variant's forward and gradients;
permutation equivariance; per-mesh independence inside a padded batch; parameter counts.

Parameters are drawn at random (not the initialisers' values) so heads, biases and the
STN are far from their special initial values and the checks have something to detect.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax.config import VARIANT_NAMES, VARIANTS, ModelConfig, preset, variant_config
from dmd_jax.graph import (
    PaddedSizes,
    batch_mesh_graphs,
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
)
from dmd_jax.model import (
    Aggregator,
    DMDNet,
    TwoStream,
    apply_transform,
    init_params,
    param_count,
    param_counts_by_module,
    param_shapes,
    symmetric_aggregate,
)
from dmd_jax.ops import gcn_aggregate

# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def jgraph(graph):
    return jax.tree.map(jnp.asarray, graph)


def random_params(shapes, seed: int, scale: float = 1.0):
    """Random parameters with the given shapes: kernels ~ N(0, 1/fan_in), rest N(0, .3²)."""
    leaves, treedef = jax.tree.flatten(shapes)
    rng = np.random.default_rng(seed)
    out = []
    for leaf in leaves:
        if len(leaf.shape) == 2:
            std = scale / np.sqrt(leaf.shape[0])
        else:
            std = 0.3 * scale
        out.append(jnp.asarray(rng.normal(0.0, std, leaf.shape), leaf.dtype))
    return jax.tree.unflatten(treedef, out)


def bumpy_sphere(subdivisions: int = 1, seed: int = 0):
    v, f = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    return v * (1.0 + 0.1 * rng.standard_normal((len(v), 1))) / 2.2, f


def open_mesh():
    """An icosphere with a cap removed: boundary edges and vertices of varied degree."""
    v, f = icosphere(1)
    keep = v[f].mean(axis=1)[:, 2] < 0.6
    f = f[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(used.size)
    return v[used] / 2.0, remap[f].astype(np.int32)


def padded(v, f, sizes: PaddedSizes | None = None, fill: float = 0.0):
    graph = build_mesh_graph(f, len(v))
    sizes = padded_sizes_for(graph) if sizes is None else sizes
    return pad_vertex_array(v, sizes.n_vertex, fill), pad_mesh_graph(graph, sizes)


def config(**kwargs) -> ModelConfig:
    base = dict(width=8, stn_width=8, dtype="float64")
    base.update(kwargs)
    return ModelConfig(**base)


# Unit tests are compile-bound: the lowest XLA backend optimisation level halves compile
# time and changes no result beyond float rounding.
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def fast_jit(fn):
    return jax.jit(fn, compiler_options=FAST_COMPILE)


def make_loss(model):
    """Simple scalar of every output, masked to real rows; returns outputs as aux."""

    def loss(params, vertices, graph, rng):
        kwargs = {} if rng is None else {"rngs": {"dropout": rng}}
        out = model.apply({"params": params}, vertices, graph, deterministic=rng is None, **kwargs)
        denoised, features, aux = out
        m = graph.vertex_mask[:, None]
        total = jnp.sum(jnp.where(m, jnp.sin(3.0 * denoised), 0.0))
        if features is not None:
            total = total + jnp.sum(jnp.where(m, features**2, 0.0))
        return total, out

    return fast_jit(jax.value_and_grad(loss, has_aux=True))


def dense_gcn(faces, n):
    a = np.eye(n)
    for tri in faces:
        for i in range(3):
            for j in range(3):
                a[tri[i], tri[j]] = 1.0
    d = a.sum(axis=1)
    # MeshGraph stores the weights in float32; round the same way for a tight comparison.
    return (a / np.sqrt(np.outer(d, d))).astype(np.float32).astype(np.float64), a


def dense_dual(faces):
    nf = len(faces)
    a = np.eye(nf)
    edges = {}
    for k, tri in enumerate(faces):
        for i in range(3):
            e = tuple(sorted((tri[i], tri[(i + 1) % 3])))
            edges.setdefault(e, []).append(k)
    for fs in edges.values():
        for p in fs:
            for q in fs:
                a[p, q] = 1.0
    d = a.sum(axis=1)
    return (a / np.sqrt(np.outer(d, d))).astype(np.float32).astype(np.float64)


# --------------------------------------------------------------------------------------
# Layers against dense formulas
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("d_in,d_out", [(8, 8), (3, 8), (12, 5)])
def test_aggregator_matches_dense_gcn(d_in, d_out):
    v, f = bumpy_sphere()
    g = jgraph(build_mesh_graph(f, len(v)))
    x = np.random.default_rng(1).standard_normal((len(v), d_in))
    agg = Aggregator(d_out, param_dtype=jnp.float64)
    edges = (g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)
    shapes = jax.eval_shape(lambda: agg.init(jax.random.PRNGKey(0), x, *edges)["params"])
    p = random_params(shapes, 3)
    out = np.asarray(agg.apply({"params": p}, jnp.asarray(x), *edges))
    a_norm, _ = dense_gcn(f, len(v))
    ref = np.maximum(a_norm @ x @ np.asarray(p["kernel"]["kernel"]) + np.asarray(p["bias"]), 0)
    if d_in == d_out:
        ref = ref + x
    np.testing.assert_allclose(out, ref, atol=1e-12)


def test_aggregator_attention_matches_dense_gat():
    v, f = bumpy_sphere()
    n = len(v)
    g = jgraph(build_mesh_graph(f, n))
    x = np.random.default_rng(2).standard_normal((n, 6))
    agg = Aggregator(6, attention=True, param_dtype=jnp.float64)
    edges = (g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)
    shapes = jax.eval_shape(lambda: agg.init(jax.random.PRNGKey(0), x, *edges)["params"])
    p = random_params(shapes, 4)
    out = np.asarray(agg.apply({"params": p}, jnp.asarray(x), *edges))
    xw = x @ np.asarray(p["kernel"]["kernel"])
    a_s, a_r = np.asarray(p["attn_sender"]), np.asarray(p["attn_receiver"])
    _, adj = dense_gcn(f, n)
    logits = (xw @ a_r)[:, None] + (xw @ a_s)[None, :]  # [receiver, sender]
    logits = np.where(logits > 0, logits, 0.2 * logits)
    logits = np.where(adj > 0, logits, -np.inf)
    alpha = np.exp(logits - logits.max(axis=1, keepdims=True))
    alpha /= alpha.sum(axis=1, keepdims=True)
    ref = np.maximum(alpha @ xw + np.asarray(p["bias"]), 0) + x
    np.testing.assert_allclose(out, ref, atol=1e-12)


def test_two_stream_matches_dense_formula():
    v, f = open_mesh()
    n, nf = len(v), len(f)
    g = jgraph(build_mesh_graph(f, n))
    x = np.random.default_rng(5).standard_normal((n, 4))
    ts = TwoStream(6, param_dtype=jnp.float64)
    shapes = jax.eval_shape(lambda: ts.init(jax.random.PRNGKey(0), x, g)["params"])
    p = jax.tree.map(np.asarray, random_params(shapes, 6))
    out = np.asarray(ts.apply({"params": p}, jnp.asarray(x), g))

    def agg(h, a_norm, q):
        return np.maximum(a_norm @ h @ q["kernel"]["kernel"] + q["bias"], 0) + h

    a_v, _ = dense_gcn(f, n)
    a_f = dense_dual(f)
    a_fv = np.zeros((nf, n))
    a_fv[np.arange(nf)[:, None], f] = 1.0
    prim = x @ p["primal_in"]["kernel"] + p["primal_in"]["bias"]
    dual = (a_fv @ x / 3.0) @ p["dual_in"]["kernel"] + p["dual_in"]["bias"]
    for i in range(3):
        prim = agg(prim, a_v, p[f"primal_agg{i}"])
        dual = agg(dual, a_f, p[f"dual_agg{i}"])
    dap = np.stack([np.abs(prim[f[:, c]] - dual) for c in range(3)]).mean(axis=0)
    d2p = (a_fv.T / a_fv.sum(axis=0)[:, None]) @ dap
    np.testing.assert_allclose(out, d2p + prim, atol=1e-12)

    no_skip = TwoStream(6, pdf_residual=False, param_dtype=jnp.float64)
    out0 = np.asarray(no_skip.apply({"params": p}, jnp.asarray(x), g))
    np.testing.assert_allclose(out0, d2p, atol=1e-12)

    single = TwoStream(6, two_stream=False, param_dtype=jnp.float64)
    sp = {k: p[k] for k in ("primal_in", "primal_agg0", "primal_agg1", "primal_agg2")}
    out1 = np.asarray(single.apply({"params": sp}, jnp.asarray(x), g))
    np.testing.assert_allclose(out1, prim, atol=1e-12)


def test_symmetric_aggregate_gradient_equals_autodiff():
    graphs = [build_mesh_graph(f, len(v)) for v, f in (tetrahedron(), open_mesh())]
    g = jgraph(
        pad_mesh_graph(batch_mesh_graphs(graphs), padded_sizes_for(batch_mesh_graphs(graphs)))
    )
    x = jnp.asarray(np.random.default_rng(7).standard_normal((g.vertex_graph.shape[0], 5)))
    edges = (g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight)
    np.testing.assert_array_equal(symmetric_aggregate(x, *edges), gcn_aggregate(x, *edges))
    ct = jnp.asarray(np.random.default_rng(8).standard_normal(x.shape))
    mine = jax.grad(lambda x: jnp.sum(ct * symmetric_aggregate(x, *edges)))(x)
    auto = jax.grad(lambda x: jnp.sum(ct * gcn_aggregate(x, *edges)))(x)
    np.testing.assert_allclose(mine, auto, atol=1e-13)
    fedges = (g.face_senders, g.face_receivers, g.face_edge_weight)
    y = jnp.asarray(np.random.default_rng(9).standard_normal((g.faces.shape[0], 3)))
    mine = jax.grad(lambda y: jnp.sum(jnp.sin(symmetric_aggregate(y, *fedges))))(y)
    auto = jax.grad(lambda y: jnp.sum(jnp.sin(gcn_aggregate(y, *fedges))))(y)
    np.testing.assert_allclose(mine, auto, atol=1e-13)


def test_apply_transform_matches_einsum():
    rng = np.random.default_rng(10)
    x = rng.standard_normal((7, 8))
    w = rng.standard_normal((3, 8, 5))
    gid = np.array([0, 0, 1, 2, 2, 2, 1])
    ref = np.einsum("na,nab->nb", x, w[gid])
    np.testing.assert_allclose(apply_transform(x, w, gid), ref, atol=1e-12)
    with pytest.raises(ValueError, match="cannot apply"):
        apply_transform(x[:, :3], w, gid)


# --------------------------------------------------------------------------------------
# Whole model: every variant, forward + gradient + permutation equivariance
# --------------------------------------------------------------------------------------


def permuted(v, f, seed):
    """Relabels vertices and faces and rotates each face's corners."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(v))  # new vertex i is old vertex perm[i]
    inverse = np.argsort(perm)
    fperm = rng.permutation(len(f))
    new_f = inverse[f][fperm]
    shift = rng.integers(0, 3, len(new_f))
    new_f = np.stack([np.roll(row, s) for row, s in zip(new_f, shift, strict=True)])
    return v[perm], new_f.astype(np.int32), perm


def check_forward(cfg: ModelConfig, out, n_real: int, n_vertex: int):
    denoised, features, aux = out
    assert denoised.shape == (n_vertex, 3)
    assert denoised.dtype == jnp.dtype(cfg.dtype)
    assert np.all(np.isfinite(denoised))
    if cfg.uses_feature_extractor:
        assert features.shape == (n_vertex, 5)
        assert np.all(np.isfinite(features))
        if cfg.normalize_fe_normals:
            np.testing.assert_allclose(np.linalg.norm(features[:n_real, :3], axis=1), 1.0)
    else:
        assert features is None
    if cfg.uses_transformer:
        shapes = [w.shape[1:] for w in aux["w_tf"]]
        rows = cfg.transform_in_dim
        assert shapes[-1] == (rows, cfg.width)
        assert len(shapes) == cfg.n_transforms
        assert all(s == (rows, rows) for s in shapes[:-1])
    else:
        assert "w_tf" not in aux
    assert ("stn" in aux) == cfg.stn


def check_grads(cfg: ModelConfig, grads):
    leaves = jax.tree.leaves(grads)
    assert all(np.all(np.isfinite(x)) for x in leaves)
    expected = {"denoiser"}
    if cfg.uses_feature_extractor:
        expected.add("feature_extractor")
    if cfg.uses_transformer:
        expected.add("transformer")
    if cfg.stn:
        expected.add("stn")
    assert set(grads) == expected
    for name, sub in grads.items():
        total = sum(float(jnp.sum(jnp.abs(x))) for x in jax.tree.leaves(sub))
        assert total > 0, f"no gradient reaches {name}"


CASES = [pytest.param(config(variant=name), id=name) for name in VARIANT_NAMES] + [
    pytest.param(config(depth=1), id="fgt8-depth1"),
    pytest.param(config(depth=3, variant="fgt3"), id="fgt3-depth3"),
    pytest.param(config(depth=4), id="fgt8-depth4"),
    pytest.param(config(attention=True), id="fgt8-attention"),
    pytest.param(config(dropout=0.35), id="fgt8-dropout"),
    pytest.param(config(stn=True), id="fgt8-stn"),
]


@pytest.mark.parametrize("cfg", CASES)
def test_variant_forward_grad_and_permutation_equivariance(cfg):
    v, f = bumpy_sphere(1, seed=11)
    vp, fp, perm = permuted(v, f, seed=12)
    sizes = padded_sizes_for(build_mesh_graph(f, len(v)))
    x, g = padded(v, f, sizes)
    xp, gp = padded(vp, fp, sizes)
    n = len(v)
    model = DMDNet(cfg)
    params = random_params(param_shapes(cfg), seed=13)
    step = make_loss(model)
    rng = jax.random.PRNGKey(3) if cfg.dropout > 0 else None

    (value, out), grads = step(params, jnp.asarray(x), jgraph(g), rng)
    assert np.isfinite(value)
    check_forward(cfg, out, n, sizes.n_vertex)
    check_grads(cfg, grads)
    assert sum(k.startswith("two_stream") for k in params["denoiser"]["stack"]) == cfg.depth

    if cfg.dropout > 0:
        # Dropout is on: another key gives another output.
        (_, out2), _ = step(params, jnp.asarray(x), jgraph(g), jax.random.PRNGKey(4))
        assert not np.allclose(out[0][:n], out2[0][:n])
        return

    # The output is far from the input, so equivariance is not trivially true.
    assert np.abs(out[0][:n] - v).max() > 1e-2
    (_, out_p), _ = step(params, jnp.asarray(xp), jgraph(gp), None)
    np.testing.assert_allclose(out_p[0][:n], out[0][:n][perm], atol=1e-10, rtol=0)
    if out[1] is not None:
        np.testing.assert_allclose(out_p[1][:n], out[1][:n][perm], atol=1e-10, rtol=0)
    for a, b in zip(out[2].get("w_tf", []), out_p[2].get("w_tf", []), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-10, rtol=0)


# --------------------------------------------------------------------------------------
# Batches: each mesh is independent of the others and of padding
# --------------------------------------------------------------------------------------


@pytest.mark.slow  # measured 12-20 s on 2 idle cores; `make test-slow` runs it
def test_batch_equals_each_mesh_alone():
    # MT has the most per-mesh state: two W_tf per mesh, plus the STN matrix and the
    # attention softmax (per receiver).
    cfg = config(variant="mt", stn=True, attention=True)
    meshes = [tetrahedron(), bumpy_sphere(1, seed=20), open_mesh()]
    meshes[0] = (meshes[0][0] / 2.0, meshes[0][1])
    graphs = [build_mesh_graph(f, len(v)) for v, f in meshes]
    batch = batch_mesh_graphs(graphs)
    sizes = padded_sizes_for(batch)
    g = pad_mesh_graph(batch, sizes)
    x = pad_vertex_array(np.concatenate([v for v, _ in meshes]), sizes.n_vertex)
    model = DMDNet(cfg)
    params = random_params(param_shapes(cfg), seed=21)
    fwd = fast_jit(lambda p, x, g: model.apply({"params": p}, x, g))
    den, feat, aux = fwd(params, jnp.asarray(x), jgraph(g))

    # Garbage in the padding rows changes nothing in the real rows.
    x_garbage = x.copy()
    x_garbage[batch.n_vertex :] = np.random.default_rng(22).normal(
        0, 5, (sizes.n_vertex - batch.n_vertex, 3)
    )
    den_g, feat_g, _ = fwd(params, jnp.asarray(x_garbage), jgraph(g))
    np.testing.assert_array_equal(den_g[: batch.n_vertex], den[: batch.n_vertex])

    start = 0
    for k, ((v, f), graph) in enumerate(zip(meshes, graphs, strict=True)):
        n = len(v)
        # Alone and padded to the batch's sizes (the same compiled program), and, for the
        # smallest mesh, alone without any padding.
        xa, ga = padded(v, f, sizes)
        runs = [fwd(params, jnp.asarray(xa), jgraph(ga))]
        if k == 0:
            runs.append(model.apply({"params": params}, jnp.asarray(v), jgraph(graph)))
        for other in runs:
            np.testing.assert_allclose(den[start : start + n], other[0][:n], atol=1e-11, rtol=0)
            np.testing.assert_allclose(feat[start : start + n], other[1][:n], atol=1e-11, rtol=0)
            for w_batch, w_alone in zip(aux["w_tf"], other[2]["w_tf"], strict=True):
                np.testing.assert_allclose(w_batch[k], w_alone[0], atol=1e-11, rtol=0)
            if cfg.stn:
                np.testing.assert_allclose(aux["stn"][k], other[2]["stn"][0], atol=1e-11)
        start += n


# --------------------------------------------------------------------------------------
# Initialisation, dtypes, errors, parameter counts
# --------------------------------------------------------------------------------------


def test_init_float32_stn_identity_and_zero_head():
    # The cheapest variant with every special initialiser: STN and the denoiser head.
    v, f = bumpy_sphere(1, seed=30)
    g = jgraph(build_mesh_graph(f, len(v)))
    cfg = ModelConfig(width=8, stn=True, stn_width=8, variant="do_1s", depth=1)
    params = init_params(cfg, jax.random.PRNGKey(0), v, g)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(params))
    assert np.all(params["denoiser"]["stack"]["head"]["kernel"] == 0)
    den, feat, aux = DMDNet(cfg).apply({"params": params}, jnp.asarray(v), g)
    assert den.dtype == jnp.float32 and feat is None
    np.testing.assert_array_equal(aux["stn"][0], np.eye(3))
    # The untrained offset model is the identity map.
    np.testing.assert_array_equal(den, v.astype(np.float32))
    shapes64 = param_shapes(ModelConfig(width=8, dtype="float64"))
    assert all(x.dtype == jnp.float64 for x in jax.tree.leaves(shapes64))


def test_absolute_output_is_offset_output_minus_input():
    v, f = bumpy_sphere(1, seed=31)
    g = jgraph(build_mesh_graph(f, len(v)))
    cfg_a = config(variant="do_1s", depth=1, predict_offset=True)
    cfg_b = config(variant="do_1s", depth=1, predict_offset=False)
    params = random_params(param_shapes(cfg_a), seed=33)
    den_a = DMDNet(cfg_a).apply({"params": params}, jnp.asarray(v), g)[0]
    den_b = DMDNet(cfg_b).apply({"params": params}, jnp.asarray(v), g)[0]
    assert np.abs(den_b).max() > 1e-2
    np.testing.assert_allclose(den_a - den_b, v, atol=1e-12)


def test_rejects_vertices_that_do_not_match_the_graph():
    v, f = tetrahedron()
    g = jgraph(build_mesh_graph(f, 4))
    cfg = config()
    params = random_params(param_shapes(cfg), seed=0)
    with pytest.raises(ValueError, match="vertices must have shape"):
        DMDNet(cfg).apply({"params": params}, jnp.zeros((5, 3)), g)
    with pytest.raises(ValueError, match="vertices must have shape"):
        DMDNet(cfg).apply({"params": params}, jnp.zeros((4, 2)), g)


def expected_param_count(cfg: ModelConfig) -> int:
    """Closed-form count of our reading of the architecture (independent of Flax)."""
    from dmd_jax import encoding

    w, t = cfg.width, cfg.hidden_transformer_width
    local = cfg.encoding == "local"
    # Candidates: the noisy normal, 3 filters x 3 snapshots, and one per Taubin snapshot.
    n_taubin = len(encoding.taubin_snapshots(cfg.taubin_iterations)) if local else 0
    k = 1 + 9 + n_taubin
    # Vertex: Laplacian coordinates, normal, each smoothed field's vertex average and each
    # Taubin displacement (3 columns each); face: every candidate (3 each).
    v_in = 6 + 3 * (k - 1) + 3 * n_taubin if local else 3
    f_in = 3 * k if local else 0  # face features on every dual input

    def dense(i, o, bias=True):
        return i * o + (o if bias else 0)

    def agg(i, o):
        return dense(i, o) + (2 * o if cfg.attention else 0)

    def two_stream(d_in, two):
        prim = dense(d_in, w) + cfg.n_agg * agg(w, w)
        dual = dense(d_in + f_in, w) + cfg.n_agg * agg(w, w)
        return prim + (dual if two else 0)

    def trunk(d_in, n, two):
        return two_stream(d_in, two) + (n - 1) * two_stream(w, two)

    total = 0
    in_dim = cfg.transform_in_dim
    if cfg.uses_feature_extractor:
        total += trunk(v_in, cfg.fe_two_streams, cfg.fe_two_stream) + dense(w, 5)
    if cfg.uses_transformer:
        total += dense(5, t)
        total += sum(agg(t * (i + 1), t) for i in range(cfg.dense_layers))
        total += agg(t * (cfg.dense_layers + 1), t)
        total += (cfg.n_transforms - 1) * dense(t, in_dim * in_dim) + dense(t, in_dim * w)
        total += agg(w, w)
        den_in = w + v_in
    elif cfg.uses_feature_extractor:
        den_in = v_in + 5
    else:
        den_in = v_in
    total += trunk(den_in, cfg.depth, cfg.denoiser_two_stream)
    if cfg.head == "offset":
        total += dense(w, 3)
    else:
        if cfg.denoiser_two_stream:  # head on [d ‖ DAP(p, d)]
            total += dense(2 * w, k + 3)
        else:  # face features from Dense([P2D(p) ‖ face_x])
            total += dense(w + f_in, w) + dense(w, k + 3)
    if cfg.stn:
        s = cfg.stn_width
        total += dense(3, s) + dense(s, 2 * s) + dense(2 * s, s) + dense(s, 9)
    return total


PAPER_PARAM_COUNT = 12_881_416


def test_paper_preset_parameter_count(capsys):
    cfg = preset("paper").model
    count = param_count(cfg)
    print(f"paper preset: {count:,d} parameters")
    assert count == PAPER_PARAM_COUNT
    assert count == expected_param_count(cfg)
    by_module = param_counts_by_module(cfg)
    assert sum(by_module.values()) == count
    from dmd_jax.cli import main

    assert main(["info", "--preset", "paper"]) == 0
    assert f"{PAPER_PARAM_COUNT:,d}" in capsys.readouterr().out


@pytest.mark.parametrize("name", list(VARIANTS))
def test_variant_parameter_counts_match_closed_form(name):
    other = {"attention": True, "stn": True, "dense_layers": 1, "n_agg": 2, "depth": 3}
    local_offset = {"encoding": "local", "head": "offset"}
    for base in (
        preset("small").model,  # local encoding, normal-first head
        preset("small").model.with_edits(local_offset),
        preset("test").model.with_edits(other),
        preset("test").model.with_edits({**other, "encoding": "local", "head": "normal"}),
    ):
        cfg = variant_config(base, name)
        assert param_count(cfg) == expected_param_count(cfg)
