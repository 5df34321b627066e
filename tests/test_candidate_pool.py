"""The candidate pool (`TrainConfig.candidate_pool`, `pipeline.CandidatePool`): the
encoding's inputs computed once per cached noisy draw give the model's outputs and
gradients, its batches are a function of `(seed, step)`, and its step compiles once."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import config, encoding, losses, pipeline, train
from dmd_jax.model import DMDNet

# test_train's one-stream denoiser without the feature term: the cheapest to compile.
TINY = {
    "model": {"variant": "do_1s", "depth": 1, "n_agg": 1},
    "loss": {"feature": 0.0},
    "train": {"batch_size": 2, "steps": 4, "eval_every": 0, "ckpt_every": 0},
}
POOL = {"train": {"candidate_pool": 1, "candidate_uses": 2}}


def _meshes():
    v, f = icosphere(2)
    bumpy = v * (1.0 + 0.1 * np.sin(5 * v[:, :1]))
    return pipeline.make_examples([icosphere(1), (bumpy, f), tetrahedron()])


def _pool(cfg, examples, **kw):
    return pipeline.CandidatePool.from_config(examples, cfg, **kw)


@pytest.mark.slow
def test_cached_inputs_give_the_models_outputs_and_gradients():
    # Rotated after encoding (each use of a draw is rotated afresh), one mesh at a time:
    # the model's own inputs of the batch, its outputs and its gradients.
    cfg = config.preset("test").with_edits(TINY).with_edits(POOL)
    examples = _meshes()
    batch = _pool(cfg, examples, sizes=pipeline.largest_sizes(examples, 2)).batch(3)
    group = jax.tree.map(lambda x: jnp.asarray(x[0]), batch)
    model = DMDNet(cfg.model)
    params = train.merge_params(train.Trainer(cfg).init(batch).params)
    loss = train.phase_loss(cfg, "all")

    @jax.jit
    def run(p, local):
        def loss_of(p):
            terms = train.loss_terms(
                model, cfg, p, group.noisy, group.clean, group.graph, loss=loss, local=local
            )
            return losses.reduce_terms(terms, loss)[0]

        out = model.apply({"params": p}, group.noisy, group.graph, local=local)[0]
        return out, jax.value_and_grad(loss_of)(p)

    own = jax.jit(lambda x, g: encoding.local_inputs(x, g, cfg.model))(group.noisy, group.graph)
    n = int(np.sum(batch.graph.vertex_mask[0]))
    np.testing.assert_allclose(group.local.vertex[:n], own.vertex[:n], atol=2e-4)
    np.testing.assert_allclose(group.local.candidates, own.candidates, atol=2e-4)
    (out_c, (l_c, g_c)), (out_o, (l_o, g_o)) = run(params, group.local), run(params, None)
    np.testing.assert_allclose(out_c[:n], out_o[:n], atol=2e-4)
    np.testing.assert_allclose(l_c, l_o, rtol=1e-4)
    for a, b in zip(jax.tree.leaves(g_c), jax.tree.leaves(g_o), strict=True):
        np.testing.assert_allclose(a, b, rtol=2e-3, atol=1e-4 * float(np.abs(b).max()))


def test_given_inputs_are_the_models_exactly():
    # The same inputs the model would compute: the same outputs, bit for bit.
    cfg = config.preset("test").with_edits(TINY)
    v, f = icosphere(1)
    (ex,) = pipeline.make_examples([(v, f)])
    graph = jax.tree.map(jnp.asarray, ex.graph)
    x = jnp.asarray(v * 4.0, jnp.float32)
    model = DMDNet(cfg.model)
    params = jax.jit(model.init)(jax.random.PRNGKey(0), x, graph)["params"]
    run = jax.jit(lambda x, g, local: model.apply({"params": params}, x, g, local=local)[0])
    local = jax.jit(lambda x, g: encoding.local_inputs(x, g, cfg.model))(x, graph)
    np.testing.assert_array_equal(run(x, graph, local), run(x, graph, None))


def test_rotated_inputs_are_the_inputs_of_the_rotated_mesh():
    cfg = config.preset("test").with_edits({"model": {"filter_iterations": 120}})
    v, f = icosphere(2)
    noisy = v * 8.0 + 0.3 * np.random.default_rng(0).normal(size=v.shape)
    (ex,) = pipeline.make_examples([(noisy, f)])
    graph = jax.tree.map(jnp.asarray, ex.graph)
    r = pipeline.random_rotation(jax.random.PRNGKey(3))
    fn = jax.jit(lambda x, g: encoding.local_inputs(x, g, cfg.model))
    base = jax.device_get(fn(jnp.asarray(noisy, jnp.float32), graph))
    rotated = fn(jnp.asarray(noisy @ r.T, jnp.float32), graph)
    moved = encoding.rotate_local_inputs(base, r.astype(np.float32))
    np.testing.assert_allclose(moved.vertex, rotated.vertex, atol=1e-4)
    np.testing.assert_allclose(moved.candidates, rotated.candidates, atol=1e-4)


def test_pool_batches_are_a_function_of_seed_and_step():
    cfg = config.preset("test").with_edits({"train": {"batch_size": 2, **POOL["train"]}})
    cfg = cfg.with_edits({"model": {"filter_iterations": 8}})
    examples = _meshes()
    sizes = pipeline.largest_sizes(examples, 2)
    run = _pool(cfg, examples, sizes=sizes)
    walked = [run.batch(s) for s in range(7)]
    # 7 steps of 2 meshes over 3 meshes: epochs 0-4, generations 0-2 (2 uses each).
    assert run.encoded < 14 and run.encoded >= 7
    for step in (6, 3, 0):
        fresh = _pool(cfg, examples, sizes=sizes).batch(step)
        for a, b in zip(jax.tree.leaves(walked[step]), jax.tree.leaves(fresh), strict=True):
            np.testing.assert_array_equal(a, b)
    # A draw serves `uses` visits, each rotated afresh; then it is redrawn.
    assert run.slot_of(0)[0][2] == 0 and run.slot_of(6)[0][2] == 2
    other = _pool(cfg.with_edits({"train": {"seed": 1}}), examples, sizes=sizes).batch(6)
    assert not np.array_equal(other.noisy, walked[6].noisy)


def test_pool_run_compiles_once(tmp_path):
    cfg = config.preset("test").with_edits(TINY).with_edits(POOL)
    out = train.train(cfg, _meshes(), tmp_path, progress=False, pad_to="largest")
    assert out["step"] == cfg.train.steps and out["compiles"] == 1


@pytest.mark.slow
def test_pool_run_compiles_every_program_before_its_first_step(tmp_path):
    # `pad_to="classes"` (the pool's default): a few programs, all compiled up front.
    cfg = config.preset("test").with_edits(TINY).with_edits(POOL)
    cfg = cfg.with_edits({"train": {"steps": 6}})
    examples = _meshes()
    classes = pipeline.size_classes(examples, 2, train.PAD_CLASSES)
    assert 1 < len(classes) <= train.PAD_CLASSES
    seen = []

    class Count(train.TrainHook):
        def before_step(self, step, batch):
            seen.append(batch.noisy.shape[-2])
            return batch

    out = train.train(cfg, examples, tmp_path, progress=False, pad_to="classes", hooks=[Count()])
    assert out["step"] == 6 and out["compiles"] == len(classes)
    assert set(seen) <= {c.n_vertex for c in classes} and len(set(seen)) > 1


@pytest.mark.slow
def test_pool_run_resumes_bit_identically(tmp_path):
    cfg = config.preset("test").with_edits(TINY).with_edits(POOL)
    cfg = cfg.with_edits({"train": {"steps": 5, "ckpt_every": 1}})
    examples = _meshes()
    whole = train.train(cfg, examples, tmp_path / "whole", progress=False, pad_to="largest")
    train.train(
        cfg,
        examples,
        tmp_path / "cut",
        progress=False,
        pad_to="largest",
        hooks=[train.StopAfter(3)],
    )
    resumed = train.train(cfg, examples, tmp_path / "cut", progress=False, pad_to="largest")
    assert resumed["step"] == 5
    for a, b in zip(
        jax.tree.leaves(whole["state"].params),
        jax.tree.leaves(resumed["state"].params),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)


def test_pool_refuses_an_encoding_without_candidates():
    cfg = config.preset("test").with_edits({"model": {"encoding": "xyz", "head": "offset"}})
    with pytest.raises(ValueError, match="local"):
        _pool(cfg.with_edits(POOL), _meshes())
