"""Training under faults: crash and resume, NaN batches, compile counts, a real SIGKILL.

Every interrupted run is compared with an uninterrupted reference run leaf by leaf
(`np.array_equal`, no tolerance): batches are pure functions of `(seed, step)`, so a
resumed run must reproduce the reference bit for bit. All meshes of the default test
have one size (a perturbed icosphere, 42 vertices), so every run compiles one program.

A module-scoped JAX persistent compilation cache lets the later runs load the train step
the first run compiled (identical HLO) instead of compiling it again; it is reset when
the module ends, so no other test sees it.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import REPO, icosphere

from dmd_jax.checkpoints import load_params
from dmd_jax.config import preset
from dmd_jax.pipeline import make_examples, training_batch
from dmd_jax.train import InjectNaN, NonFiniteLossError, StopAfter, phase_of, train

STEPS = 6
CKPT_EVERY = 2
NAN_STEP = 3  # after the checkpoint of step 2, before the one of step 4


def _meshes(n: int, subdivisions: int = 1, seed: int = 0):
    """`n` perturbed icospheres of one size (one bucket, one compiled program)."""
    v, f = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    return [(v + 0.03 * rng.standard_normal(v.shape), f) for _ in range(n)]


def _config(**train):
    edits = {
        "steps": STEPS,
        "ckpt_every": CKPT_EVERY,
        "ckpt_keep": 100,
        "batch_size": 1,
        "eval_every": 0,
        **train,
    }
    return preset("test").with_edits({"train": edits})


def _restore(ckpt_dir: Path, step: int) -> dict:
    """The whole saved train state (`step`, `params`, `opt_state`) of one checkpoint."""
    import orbax.checkpoint as ocp

    manager = ocp.CheckpointManager(Path(ckpt_dir).absolute())
    return manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))["state"]


def _saved_steps(ckpt_dir: Path) -> list[int]:
    """Finalised checkpoint steps (Orbax renames a finished temporary folder to the step)."""
    if not ckpt_dir.is_dir():
        return []
    return sorted(int(p.name) for p in ckpt_dir.iterdir() if p.name.isdigit())


def _assert_trees_identical(a, b, what: str) -> None:
    leaves_a, tree_a = jax.tree_util.tree_flatten_with_path(jax.device_get(a))
    leaves_b, tree_b = jax.tree_util.tree_flatten_with_path(jax.device_get(b))
    assert [p for p, _ in leaves_a] == [p for p, _ in leaves_b], f"{what}: structures differ"
    for (path, x), (_, y) in zip(leaves_a, leaves_b, strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y)), (
            f"{what}: leaf {jax.tree_util.keystr(path)} differs (max |diff| "
            f"{np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))})"
        )


@pytest.fixture(scope="module", autouse=True)
def _compilation_cache(tmp_path_factory):
    from jax.experimental.compilation_cache import compilation_cache as cc

    previous = jax.config.jax_compilation_cache_dir
    cc.reset_cache()
    cc.set_cache_dir(str(tmp_path_factory.mktemp("jax_cache")))
    yield
    jax.config.update("jax_compilation_cache_dir", previous)
    cc.reset_cache()


def _batch_signatures(cfg, examples) -> set:
    """`(padded shapes, phase)` of every step: what one compiled train step serves."""
    t = cfg.train
    noise = cfg.noise
    signatures = set()
    for step in range(t.steps):
        batch = training_batch(
            examples, step, batch_size=t.batch_size, seed=t.seed, noise=noise, rotate=t.rotate
        )
        shapes = tuple(np.shape(x) for x in jax.tree.leaves(batch))
        signatures.add((shapes, phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)))
    return signatures


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_nan_crash_then_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path):
    # One test, not several sharing fixtures: pytest-xdist deals consecutive tests to
    # different workers, and each would then pay for the reference run again.
    examples = make_examples(_meshes(3))
    cfg = _config()

    # (c) The uninterrupted reference compiles once per (bucket, phase) it meets: once.
    reference = train(cfg, examples, tmp_path / "reference", progress=False)
    ref_ckpt = tmp_path / "reference" / "checkpoints" / "latest"
    assert reference["step"] == STEPS
    assert reference["compiles"] == len(_batch_signatures(cfg, examples)) == 1
    assert _saved_steps(ref_ckpt) == list(range(CKPT_EVERY, STEPS + 1, CKPT_EVERY))

    # (b) A NaN batch stops the run with a clear error; the last good checkpoint stays.
    workdir = tmp_path / "crashed"
    with pytest.raises(NonFiniteLossError) as info:
        train(cfg, examples, workdir, progress=False, hooks=[InjectNaN(NAN_STEP)])
    last_good = (NAN_STEP // CKPT_EVERY) * CKPT_EVERY
    message = str(info.value)
    assert f"non-finite loss (nan) at step {NAN_STEP}" in message
    assert f"checkpoint (step {last_good})" in message and str(workdir) in message
    ckpt = workdir / "checkpoints" / "latest"
    assert _saved_steps(ckpt) == list(range(CKPT_EVERY, NAN_STEP, CKPT_EVERY))
    params, _ = load_params(ckpt)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(params))
    _assert_trees_identical(
        _restore(ckpt, last_good), _restore(ref_ckpt, last_good), "checkpoint before the NaN"
    )

    # (a) Resume the crashed run, stop after one step (a graceful stop checkpoints), and
    # resume again to the end: every leaf of the final state equals the reference's.
    stopped = train(cfg, examples, workdir, progress=False, hooks=[StopAfter(1)])
    assert stopped["step"] == last_good + 1
    assert _saved_steps(ckpt)[-1] == last_good + 1
    final = train(cfg, examples, workdir, progress=False)
    assert final["step"] == STEPS and final["compiles"] == 1
    _assert_trees_identical(final["state"], reference["state"], "resumed vs uninterrupted")
    _assert_trees_identical(_restore(ckpt, STEPS), _restore(ref_ckpt, STEPS), "saved states")
    # The loss curve still plots from a log in which steps 3.. were logged twice.
    assert (workdir / "loss_curve.png").is_file()


# --------------------------------------------------------------------------------------
# Slow: more buckets and phases; a real SIGKILL in a subprocess
# --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_compiles_equal_distinct_buckets_times_phases(tmp_path):
    meshes = _meshes(2, subdivisions=1) + _meshes(2, subdivisions=2, seed=1)
    examples = make_examples(meshes)
    cfg = _config(steps=8, scheme="alter", ckpt_every=0)
    signatures = _batch_signatures(cfg, examples)
    assert len({s for s, _ in signatures}) == 2  # two buckets...
    assert len({p for _, p in signatures}) == 2  # ...and two phases are used
    result = train(cfg, examples, tmp_path / "run", progress=False)
    assert result["compiles"] == len(signatures) == 4


_SCRIPT = """
import json, sys
import jax
import numpy as np
import trimesh

jax.config.update("jax_enable_x64", True)
from dmd_jax.config import preset
from dmd_jax.pipeline import make_examples
from dmd_jax.train import train

workdir, edits = sys.argv[1], json.loads(sys.argv[2])
s = trimesh.creation.icosphere(subdivisions=1)
v, f = np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)
rng = np.random.default_rng(0)
examples = make_examples([(v + 0.03 * rng.standard_normal(v.shape), f) for _ in range(3)])
result = train(preset("test").with_edits(edits), examples, workdir, progress=False)
print("finished at step", result["step"], flush=True)
"""


def _child(script: Path, workdir: Path, edits: dict, cache: Path) -> subprocess.Popen:
    """Starts one training run in a fresh Python; its output goes to `<workdir>.log`."""
    env = dict(os.environ)
    env.update(
        JAX_PLATFORMS="cpu",
        JAX_COMPILATION_CACHE_DIR=str(cache),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""),
    )
    with open(f"{workdir}.log", "a") as log:  # the child keeps its own descriptor
        proc = subprocess.Popen(
            [sys.executable, str(script), str(workdir), json.dumps(edits)],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    proc.log_path = Path(f"{workdir}.log")
    return proc


def _output(proc: subprocess.Popen) -> str:
    return proc.log_path.read_text()[-3000:]


def _finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    proc.wait(timeout=timeout)
    out = _output(proc)
    assert proc.returncode == 0, out
    return out


def _wait_for_checkpoints(proc, ckpt: Path, count: int, timeout: float = 300) -> float:
    """Polls until `count` checkpoints are finalised; returns the time it happened."""
    deadline = time.monotonic() + timeout
    while len(_saved_steps(ckpt)) < count:
        assert proc.poll() is None, _output(proc)
        assert time.monotonic() < deadline, f"fewer than {count} checkpoints in {timeout} s"
        time.sleep(0.005)
    return time.monotonic()


def _kill_while_writing_a_checkpoint(proc, ckpt: Path, timeout: float = 300) -> list[str]:
    """SIGKILLs the run while Orbax's temporary folder of a checkpoint exists."""
    deadline = time.monotonic() + timeout
    while True:
        names = [p.name for p in ckpt.iterdir()] if ckpt.is_dir() else []
        if any(n.isdigit() for n in names) and not all(n.isdigit() for n in names):
            os.kill(proc.pid, signal.SIGKILL)
            return names
        assert proc.poll() is None, "no checkpoint write was caught:\n" + _output(proc)
        assert time.monotonic() < deadline
        time.sleep(0.0005)


@pytest.mark.slow
def test_sigkill_mid_checkpoint_and_at_a_random_step_then_resume_is_bit_identical(tmp_path):
    steps, every = 30, 3
    edits = {
        "train": {
            "steps": steps,
            "ckpt_every": every,
            "ckpt_keep": 100,
            "batch_size": 1,
            "eval_every": 0,
        }
    }
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent(_SCRIPT))
    cache = tmp_path / "jax_cache"
    reference = tmp_path / "reference"
    _finish(_child(script, reference, edits, cache))
    victim = tmp_path / "victim"
    ckpt = victim / "checkpoints" / "latest"

    # Kill 1: while a checkpoint (not the first) is half written.
    proc = _child(script, victim, edits, cache)
    names = _kill_while_writing_a_checkpoint(proc, ckpt)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill ({names})"
    first = _saved_steps(ckpt)[-1]

    # Kill 2, in the resumed run: at a random moment 0-3 checkpoint intervals after its
    # second new checkpoint, i.e. at a random step, possibly again during a write.
    proc = _child(script, victim, edits, cache)
    t1 = _wait_for_checkpoints(proc, ckpt, len(_saved_steps(ckpt)) + 1)
    t2 = _wait_for_checkpoints(proc, ckpt, len(_saved_steps(ckpt)) + 1)
    delay = random.Random().uniform(0.0, 3.0 * (t2 - t1))
    time.sleep(delay)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)
    what = f"SIGKILL during a write ({names}) and {delay:.3f} s after a checkpoint"
    assert proc.returncode == -signal.SIGKILL, f"the run ended before the {what}"
    kept = _saved_steps(ckpt)
    assert first + 2 * every <= kept[-1] < steps, f"checkpoints {kept} after a {what}"

    out = _finish(_child(script, victim, edits, cache))
    assert f"finished at step {steps}" in out
    assert _saved_steps(ckpt) == list(range(every, steps + 1, every))
    ref_params, _ = load_params(reference / "checkpoints" / "latest")
    got_params, _ = load_params(ckpt)
    _assert_trees_identical(got_params, ref_params, f"resumed from step {kept[-1]} after {what}")
    _assert_trees_identical(
        _restore(ckpt, steps), _restore(reference / "checkpoints" / "latest", steps), "full state"
    )
