"""The training engine's settings: every one changes what a step or a run does."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import config, pipeline, train

# A one-stream denoiser without the feature term: the cheapest model to compile.
TINY = {
    "model": {"variant": "do_1s", "depth": 1, "n_agg": 1},
    "loss": {"feature": 0.0},
    "train": {"batch_size": 2, "steps": 4, "eval_every": 0, "ckpt_every": 0},
}


def _update(cfg, grads, params):
    tx = train.make_optimizer(cfg)
    updates, _ = tx.update(grads, tx.init(params), params)
    return updates


def test_adam_eps_reaches_the_optimizer():
    params = {"w": jnp.zeros(3)}
    grads = {"w": jnp.array([1e-9, 1e-6, 1.0])}
    # A constant rate: the preset's cosine schedule starts its warm-up at 0.
    base = config.preset("test").with_edits({"train": {"schedule": "constant"}})
    default = _update(base, grads, params)["w"]
    large = _update(base.with_edits({"train": {"eps": 1.0}}), grads, params)["w"]
    # Adam's first step is -lr * g / (|g| + eps): eps = 1 shrinks the small gradients.
    assert np.all(np.abs(large) < np.abs(default))
    np.testing.assert_allclose(default[2], -base.train.lr, rtol=1e-6)


def test_phase_loss_switches_terms_off():
    cfg = config.preset("test").with_edits({"train": {"scheme": "alter"}})
    fe = train.phase_loss(cfg, "fe")
    assert (fe.vertex, fe.normal, fe.curvature, fe.chamfer, fe.feature) == (0, 0, 0, 0, 1)
    assert train.phase_loss(cfg, "rest") == cfg.loss.with_edits({"feature": 0.0})
    assert train.phase_loss(cfg, "all") == cfg.loss
    u_fe = cfg.with_edits({"train": {"scheme": "u_fe"}})
    assert train.phase_loss(u_fe, "all").feature == 0.0


@pytest.mark.parametrize(("log_every", "rows"), [(1, [1, 2, 3, 4]), (3, [3, 4]), (0, [4])])
def test_log_every_sets_the_logged_steps(tmp_path, log_every, rows):
    cfg = config.preset("test").with_edits(TINY).with_edits({"train": {"log_every": log_every}})
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    out = train.train(cfg, examples, tmp_path, progress=False)
    assert out["step"] == 4
    logged = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logged if r["kind"] == "train"] == rows


def test_one_device_is_a_one_device_mesh():
    cfg = config.preset("test").with_edits(TINY)
    trainer = train.Trainer(cfg)
    assert trainer.mesh.size == 1 and trainer.mesh.devices.flat[0] == jax.devices()[0]
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    kw = dict(batch_size=2, seed=0, noise=cfg.noise)
    state = trainer.init(pipeline.training_batch(examples, 0, **kw))
    state, out = trainer.train_step(state, pipeline.training_batch(examples, 0, **kw))
    assert int(state.step) == 1 and trainer.compiles == 1
    # The terms of the preset's recipe (curvature and chamfer weigh 0 there, so they
    # are not computed) and the normal-first head's own face-normal term.
    assert set(out) == {"loss", "grad_norm", "vertex", "normal", "face_normal"}
