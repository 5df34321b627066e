"""Seeds trained side by side (`experiments.multiseed`) and the sweep's per-row jobs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dmd_jax.train import StopAfter, train
from experiments import multiseed, runner
from experiments import studies as st


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The smoke preset's dataset and a 4-step config (one padding bucket)."""
    data = tmp_path_factory.mktemp("data")
    p = st.get_preset("test")
    runner.ensure_dataset(p, data, progress=False)
    train_ex, evals = runner.load_examples(str(data), 1)
    cfg = st.base_config(p).with_edits(
        {"train": {"steps": 4, "ckpt_every": 2, "log_every": 1, "ckpt_keep": 2}}
    )
    return train_ex, evals, cfg


def _cfgs(cfg, seeds):
    return [cfg.with_edits({"train": {"seed": s}}) for s in seeds]


@pytest.mark.slow
def test_one_vmapped_step_is_each_seeds_own_step(tiny):
    """One step of two seeds as one program equals
    `Trainer.train_step` of each seed (same batch, same dropout key)."""
    import jax

    from dmd_jax.train import Trainer

    train_ex, _, cfg = tiny
    cfgs = _cfgs(cfg, (0, 5))
    batch = multiseed.seeds_batch(train_ex, cfgs, 0)
    trainers = [Trainer(c) for c in cfgs]
    states = [tr.init(jax.tree.map(lambda x, i=i: x[i], batch)) for i, tr in enumerate(trainers)]
    step = multiseed.seeds_step(cfg, "all")
    stacked, m = step(
        multiseed.stack_trees(states),
        batch.noisy,
        batch.clean,
        batch.graph,
        multiseed.step_rngs(cfgs, 0),
    )
    for i, (tr, st_) in enumerate(zip(trainers, states, strict=True)):
        alone, m1 = tr.train_step(st_, jax.tree.map(lambda x, i=i: x[i], batch))
        np.testing.assert_allclose(m["loss"][i], m1["loss"], rtol=1e-5)
        got = multiseed.unstack_tree(stacked.params, 2)[i]
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(alone.params), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_the_one_seed_program_is_the_vmap_of_one_seed(tiny):
    """`seeds_step(..., n_seeds=1)` (no vmap, traced faster) steps like the vmap."""
    import jax

    from dmd_jax.train import Trainer

    train_ex, _, cfg = tiny
    cfgs = _cfgs(cfg, (2,))
    batch = multiseed.seeds_batch(train_ex, cfgs, 0)
    state = multiseed.stack_trees([Trainer(cfg).init(jax.tree.map(lambda x: x[0], batch))])
    args = (batch.noisy, batch.clean, batch.graph, multiseed.step_rngs(cfgs, 0))
    one, m1 = multiseed.seeds_step(cfg, "all", n_seeds=1)(state, *args)
    vm, mv = multiseed.seeds_step(cfg, "all")(state, *args)
    assert m1["loss"].shape == mv["loss"].shape == (1,)
    np.testing.assert_allclose(m1["loss"], mv["loss"], rtol=1e-6)
    for a, b in zip(jax.tree.leaves(one.params), jax.tree.leaves(vm.params), strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_vmapped_seeds_follow_the_steps_of_separate_runs(tiny, tmp_path):
    train_ex, evals, cfg = tiny
    cfgs = _cfgs(cfg, (0, 3))
    res = multiseed.train_seeds(
        cfgs, train_ex, [tmp_path / "a0", tmp_path / "a3"], eval_sets=evals, progress=False
    )
    for c, r, d in zip(cfgs, res, ("b0", "b3"), strict=True):
        alone = train(c, train_ex, tmp_path / d, eval_sets=evals, progress=False)
        assert r["status"] == "ok" and r["step"] == 4
        for k, v in r["metrics"].items():
            np.testing.assert_allclose(v, alone[k], rtol=1e-4, err_msg=k)
        assert len(r["per_mesh"]["test_intra/normal_deg"]) == len(evals["test_intra"])
    # Different seeds, different models.
    assert res[0]["metrics"]["test_intra/vertex"] != res[1]["metrics"]["test_intra/vertex"]


@pytest.mark.slow
def test_a_killed_group_resumes_to_the_same_models(tiny, tmp_path):
    train_ex, evals, cfg = tiny
    cfgs = _cfgs(cfg, (0, 1))
    full = multiseed.train_seeds(
        cfgs, train_ex, [tmp_path / "f0", tmp_path / "f1"], eval_sets=evals, progress=False
    )
    dirs = [tmp_path / "k0", tmp_path / "k1"]
    stop = [StopAfter(2)]
    multiseed.train_seeds(cfgs, train_ex, dirs, eval_sets=evals, progress=False, hooks=stop)
    assert [multiseed.resume_step(d) for d in dirs] == [2, 2]
    resumed = multiseed.train_seeds(cfgs, train_ex, dirs, eval_sets=evals, progress=False)
    for a, b in zip(full, resumed, strict=True):
        assert b["resumed_from"] == 2
        for k, v in a["metrics"].items():
            np.testing.assert_allclose(b["metrics"][k], v, rtol=1e-6, err_msg=k)
    logged = [json.loads(x)["step"] for x in (dirs[0] / "log.jsonl").read_text().splitlines()]
    assert logged == [1, 2, 3, 4]


def test_seeds_of_different_configs_are_refused(tmp_path):
    cfg = st.base_config(st.get_preset("test"))
    other = cfg.with_edits({"train": {"lr": 1e-2, "seed": 1}})
    with pytest.raises(ValueError, match="share every setting"):
        multiseed.train_seeds([cfg, other], [], [tmp_path / "x", tmp_path / "y"])
    with pytest.raises(ValueError, match="repeated seeds"):
        multiseed.same_but_seed([cfg, cfg])


def test_stacking_round_trips():
    trees = [{"a": np.full(3, i), "b": (np.eye(2) * i,)} for i in range(3)]
    back = multiseed.unstack_tree(multiseed.stack_trees(trees), 3)
    for t, b in zip(trees, back, strict=True):
        np.testing.assert_array_equal(t["a"], b["a"])
        np.testing.assert_array_equal(t["b"][0], b["b"][0])


@pytest.mark.slow
def test_sweep_trains_a_rows_seeds_together_and_resumes_one_seed(tmp_path):
    """Three seeds per row: one job per row; a rerun has nothing to do; a seed whose
    results are lost is retrained alone from its checkpoint, the others are kept."""
    p = st.get_preset("test").with_changes(seeds=(0, 1, 2), workers=1)
    out, data = tmp_path / "out", tmp_path / "data"
    kw = {"studies": ["stn"], "progress": False, "echo": False}
    s1 = runner.run_sweep(p, out, data, **kw)
    assert s1["jobs"] == 2 and not s1["failures"]
    summary = json.loads((out / "summary.json").read_text())
    assert {iv["n_seeds"] for iv in summary["studies"]["stn"]["intervals"]} == {3}
    assert runner.run_sweep(p, out, data, **kw)["jobs"] == 0
    plan = json.loads((out / "plan.json").read_text())
    victim = next(r for r in plan["runs"] if r["row"] == "With STN" and r["seed"] == 1)
    d = out / "stn" / victim["run_id"]
    before = json.loads((d / "metrics.json").read_text())
    (d / "metrics.json").unlink()
    (d / "train_metrics.json").unlink()
    assert runner.run_sweep(p, out, data, **kw)["jobs"] == 1
    after = json.loads((d / "metrics.json").read_text())
    assert after["train"]["resumed_from"] == 2 and after["train"]["group_seeds"] == 1
    for k, v in before["metrics"].items():
        np.testing.assert_allclose(after["metrics"][k], v, rtol=1e-5, err_msg=k)


def test_eval_trainer_is_shared_per_model_and_pass_count():
    """Rows of one model share an evaluation predictor only when they train the same
    number of passes: evaluation runs a row's `train.passes`."""
    from dmd_jax.config import preset
    from experiments.multiseed import eval_trainer

    cfg = preset("test")
    assert eval_trainer(cfg) is eval_trainer(cfg.with_edits({"model": {"dropout": 0.1}}))
    two = eval_trainer(cfg.with_edits({"train": {"passes": 2}}))
    assert two is not eval_trainer(cfg) and two.cfg.train.passes == 2
