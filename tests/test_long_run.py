"""The long run that outlives sessions (`dmd_jax.long_run`): a state committed as one file
resumes on another machine bit-identically, and a stale, conflicting or foreign state is
refused rather than silently thrown away."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import config, long_run, pipeline, train

TINY = {
    "model": {"variant": "do_1s", "depth": 1, "n_agg": 1},
    "loss": {"feature": 0.0},
    "train": {"batch_size": 2, "steps": 4, "eval_every": 0, "ckpt_every": 0, "log_every": 1},
}


@pytest.fixture(scope="module")
def setup():
    cfg = config.preset("test").with_edits(TINY)
    return cfg, pipeline.make_examples([icosphere(1), tetrahedron()])


def _run(cfg, examples, workdir, state_file, *hooks, **kw):
    hook = long_run.LongRun(workdir, state_file, cfg.to_dict(), say=lambda _: None, **kw)
    return train.train(cfg, examples, workdir, progress=False, hooks=[hook, *hooks])


def _leaves(result):
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(result["state"]))]


def _losses(workdir):
    rows = [json.loads(x) for x in (workdir / "log.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in rows if r["kind"] == "train"}


def test_a_committed_state_resumes_bit_identically_on_a_fresh_workdir(tmp_path, setup):
    cfg, examples = setup
    whole = train.train(cfg, examples, tmp_path / "whole", progress=False)
    state, curve = tmp_path / "repo/state.msgpack", tmp_path / "repo/curve.csv"

    # Session 1: two steps, stopped by the stop file, saved.
    first = tmp_path / "s1"
    out = _run(cfg, examples, first, state, train.StopAfter(2))
    assert out["step"] == 2 and (first / long_run.LOCAL_STATE).is_file()
    assert long_run.save(first, state, curve) == 2
    meta = long_run.read_meta(state)
    assert meta["step"] == 2 and meta["parent"] == "" and meta["config"] == cfg.to_dict()
    assert state.stat().st_size < 5e6

    # Session 2 on a fresh machine: only the committed file is there.
    second = tmp_path / "s2"
    out = _run(cfg, examples, second, state)
    assert out["step"] == 4
    for a, b in zip(_leaves(out), _leaves(whole), strict=True):
        np.testing.assert_array_equal(a, b)
    assert _losses(second) == {k: v for k, v in _losses(tmp_path / "whole").items() if k > 2}
    assert long_run.save(second, state, curve) == 4
    assert (
        long_run.read_meta(state)["parent"]
        == long_run.read_meta(second / long_run.LOCAL_STATE)["parent"]
    )
    steps = [int(r.split(",")[0]) for r in curve.read_text().splitlines()[1:]]
    assert sorted(set(steps)) == [1, 2, 3, 4]  # each step once, across both sessions
    line = long_run.status_line(second, state)
    assert line.startswith("step 4;") and "not running" in line and "committed step 4" in line


@pytest.mark.slow  # 30 s on 2 busy cores (four compiled runs); the next test is its cheap twin
def test_stale_foreign_and_conflicting_states_are_refused(tmp_path, setup):
    cfg, examples = setup
    state, curve = tmp_path / "state.msgpack", tmp_path / "curve.csv"
    a = tmp_path / "a"
    _run(cfg, examples, a, state, train.StopAfter(1))
    long_run.save(a, state, curve)

    # Another recipe cannot resume this state.
    other = cfg.with_edits({"train": {"lr": cfg.train.lr * 2}})
    with pytest.raises(long_run.StateConflictError, match="another recipe.*train.lr"):
        _run(other, examples, tmp_path / "other", state)

    # Two sessions grow from the same committed step; the first to save wins, the
    # second is refused (its save would replace training it does not hold).
    b = tmp_path / "b"
    _run(cfg, examples, b, state, train.StopAfter(1))
    c = tmp_path / "c"
    _run(cfg, examples, c, state, train.StopAfter(2))
    assert long_run.save(b, state, curve) == 2
    with pytest.raises(long_run.StateConflictError, match="changed since this run resumed"):
        long_run.save(c, state, curve)
    # ... and resuming the loser's workdir, ahead of the committed state on another
    # lineage, is refused too.
    with pytest.raises(long_run.StateConflictError, match="did not grow from the committed"):
        _run(cfg, examples, c, state)

    # A workdir behind the committed state (stale) takes the committed one.
    out = _run(cfg, examples, a, state, train.StopAfter(1))
    assert out["step"] == 3


def test_starting_state_takes_keeps_or_refuses_without_training(tmp_path, setup):
    """The same rules as above on states written directly (no step compiled)."""
    cfg, examples = setup
    trainer = train.Trainer(cfg, train.parallel.batch_mesh(jax.devices()[:1]))
    batch = pipeline.training_batch(
        examples, 0, batch_size=2, seed=0, noise=cfg.noise, encoding=cfg.model.encoding
    )
    fresh = trainer.init(batch)
    at = {n: fresh._replace(step=np.int32(n)) for n in (0, 3, 5)}
    committed = tmp_path / "state.msgpack"
    committed.write_bytes(long_run.state_bytes(at[3], cfg.to_dict(), parent="", seconds=7.0))

    def start(workdir, state, conf=cfg):
        hook = long_run.LongRun(workdir, committed, conf.to_dict(), say=lambda _: None)
        return int(hook.starting_state(state).step)

    assert start(tmp_path / "new", at[0]) == 3  # a fresh workdir takes the committed state
    assert start(tmp_path / "new", at[5]) == 5  # ... and, having grown from it, keeps its own
    assert start(tmp_path / "stale", at[0]) == 3
    other = cfg.with_edits({"loss": {"normal": 9.0}})
    with pytest.raises(long_run.StateConflictError, match="another recipe.*loss.normal"):
        start(tmp_path / "x", at[0], other)
    with pytest.raises(long_run.StateConflictError, match="did not grow from the committed"):
        start(tmp_path / "foreign", at[5])  # ahead, but of unknown lineage
    # A setting added to the code since the state was written counts as its default:
    # switching it on is another recipe, leaving it alone resumes.
    older = cfg.to_dict()
    del older["train"]["candidate_pool"]
    assert long_run.recipe_difference(older, cfg.to_dict()) == ""
    pooled = cfg.with_edits({"train": {"candidate_pool": 1}}).to_dict()
    assert "train.candidate_pool is 0 there, 1 here" in long_run.recipe_difference(older, pooled)
    (tmp_path / "new" / long_run.LOCAL_STATE).write_bytes(
        long_run.state_bytes(at[5], cfg.to_dict(), parent="", seconds=9.0)
    )
    committed.write_bytes(long_run.state_bytes(at[5], cfg.to_dict(), parent="x", seconds=8.0))
    with pytest.raises(long_run.StateConflictError, match="changed since this run resumed"):
        long_run.save(tmp_path / "new", committed, tmp_path / "curve.csv")


def test_the_stop_file_stops_after_the_running_step(tmp_path, setup):
    cfg, examples = setup
    hook = long_run.LongRun(tmp_path, tmp_path / "none.msgpack", cfg.to_dict(), say=print)

    class Stopper(train.TrainHook):
        def after_step(self, step, metrics):
            (tmp_path / long_run.STOP_FILE).touch()

    out = train.train(cfg, examples, tmp_path, progress=False, hooks=[Stopper(), hook])
    assert out["step"] == 1 and (tmp_path / long_run.LOCAL_STATE).is_file()


def test_a_timed_checkpoint_exports_the_state(tmp_path, setup):
    cfg, examples = setup
    hook = long_run.LongRun(
        tmp_path, tmp_path / "none.msgpack", cfg.to_dict(), checkpoint_seconds=0.0, say=print
    )
    exported = []
    hook_export = hook.on_checkpoint

    def spy(state):
        hook_export(state)
        exported.append(long_run.read_meta(tmp_path / long_run.LOCAL_STATE)["step"])

    hook.on_checkpoint = spy
    train.train(cfg, examples, tmp_path, progress=False, hooks=[hook])
    assert exported == [1, 2, 3, 4]  # every step was due (ckpt_every is 0 here)


def test_bad_state_files_and_the_command_line(tmp_path, capsys):
    bad = tmp_path / "bad.msgpack"
    bad.write_bytes(b"not msgpack at all")
    with pytest.raises(ValueError, match="not a long-run state file"):
        long_run.read_meta(bad)
    with pytest.raises(FileNotFoundError, match="no state file"):
        long_run.read_meta(tmp_path / "missing.msgpack")
    args = ["--workdir", str(tmp_path / "w"), "--state", str(bad)]
    assert long_run.main(["status", *args]) == 2
    assert "not a long-run state file" in capsys.readouterr().err
    assert long_run.main(["save", *args, "--curve", str(tmp_path / "c.csv")]) == 2
    assert "exported no state" in capsys.readouterr().err
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / long_run.PID_FILE).write_text(f"{os.getpid()}\n")
    with pytest.raises(long_run.StateConflictError, match="still running"):
        long_run.save(tmp_path / "w", bad, tmp_path / "c.csv")


@pytest.mark.slow  # 25 s on 2 busy cores (a compiled run); the next test is its cheap twin
def test_milestones_are_kept_when_the_run_crosses_them(tmp_path, setup):
    cfg, examples = setup
    cfg = cfg.with_edits({"train": {"ckpt_every": 3}})  # checkpoints at steps 3 and 4
    state = tmp_path / "none.msgpack"
    _run(cfg, examples, tmp_path / "w", state, milestone_every=2)
    kept = long_run.milestones(tmp_path / "w")
    # Milestone 2 has no checkpoint of its own: the first one past it (3) is kept, and
    # says so; milestone 4 is the run's step-4 checkpoint.
    assert [(m["milestone"], m["step"]) for m in kept] == [(2, 3), (4, 4)]
    for m in kept:
        folder = long_run.milestone_dir(tmp_path / "w", m["milestone"])
        assert folder == tmp_path / "w" / "milestones" / f"step_{m['milestone']:06d}"
        assert long_run.read_meta(folder / long_run.LOCAL_STATE)["step"] == m["step"]
        assert (folder / "checkpoint" / str(m["step"])).is_dir()
    from dmd_jax.checkpoints import load_params

    params, stored = load_params(long_run.milestone_dir(tmp_path / "w", 2) / "checkpoint")
    assert stored.to_dict() == cfg.to_dict() and params
    assert not list((tmp_path / "w" / "milestones").glob("*.tmp"))


def test_a_milestone_is_kept_once_and_not_on_resume(tmp_path, setup):
    """No step is compiled: the hook's checkpoint callback on states written directly."""
    cfg, examples = setup
    trainer = train.Trainer(cfg, train.parallel.batch_mesh(jax.devices()[:1]))
    batch = pipeline.training_batch(
        examples, 0, batch_size=2, seed=0, noise=cfg.noise, encoding=cfg.model.encoding
    )
    fresh = trainer.init(batch)
    at = {n: fresh._replace(step=np.int32(n)) for n in (0, 9, 10, 12, 25)}

    def hook():
        return long_run.LongRun(
            tmp_path,
            tmp_path / "none.msgpack",
            cfg.to_dict(),
            milestone_every=10,
            say=lambda _: None,
        )

    orbax = tmp_path / "checkpoints" / "latest" / "10"  # the checkpoint train() wrote
    orbax.mkdir(parents=True)
    (orbax / "commit_success.txt").write_text("ok")
    h = hook()
    h.starting_state(at[0])
    h.on_checkpoint(at[9])
    assert long_run.milestones(tmp_path) == []
    h.on_checkpoint(at[10])
    h.on_checkpoint(at[12])  # past 10 again: the milestone stays the step-10 one
    assert [(m["milestone"], m["step"]) for m in long_run.milestones(tmp_path)] == [(10, 10)]
    kept = long_run.milestone_dir(tmp_path, 10)
    assert (kept / "checkpoint" / "10" / "commit_success.txt").read_text() == "ok"
    assert long_run.read_meta(kept / long_run.LOCAL_STATE)["step"] == 10
    # A run resumed past 20 did not cross it in this process: no milestone 20 at step 25.
    h = hook()
    h.starting_state(at[25])
    h.on_checkpoint(at[25])
    assert [m["milestone"] for m in long_run.milestones(tmp_path)] == [10]
    assert long_run.LongRun(tmp_path, tmp_path / "x", {}).milestone_every == 10_000


def test_the_kept_candidate_is_a_milestone_with_its_controller_switched_on():
    """`training/candidate.msgpack` (docs/training.md, "The candidate"), while there is
    one: a milestone of the long run, the bundled rules, a controller switched on, and a
    network the bundled weights' shapes fit (what `make bundle` will copy in place)."""
    from pathlib import Path

    import jax

    from dmd_jax import load_pretrained, load_weights

    path = Path(__file__).resolve().parents[1] / "training" / "candidate.msgpack"
    if not path.is_file():
        pytest.skip("no candidate kept (the bundled weights are the last one)")
    candidate, bundled = load_weights(path), load_pretrained()
    assert candidate.meta["long_run_milestone"] % 10_000 == 0
    assert candidate.controller is not None and candidate.policy.controller
    shapes = lambda p: jax.tree.map(np.shape, p)  # noqa: E731
    assert shapes(candidate.params) == shapes(bundled.params)


def test_the_bundled_weights_are_a_milestone_of_the_long_run_with_its_controller():
    """Issue 62: the bundled weights are a milestone of the long run (bundled 2026-12-08,
    milestone 50,000), exported with the controller trained for its network, switched
    on, and the network configured as the run trained it (the converged solve)."""
    from dmd_jax import load_pretrained

    bundled = load_pretrained()
    assert bundled.meta["long_run_milestone"] % 10_000 == 0
    assert bundled.meta["long_run_step"] == bundled.meta["long_run_milestone"]
    assert bundled.controller is not None and bundled.policy.controller
    assert bundled.config.model.vertex_update == "solve"
