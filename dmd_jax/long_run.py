"""The long training run that outlives sessions: its whole state in one portable file.

No session on two CPU cores can hold a run of 100,000 steps, and a run's Orbax
checkpoints live in an ignored folder that a new machine does not have. So the run's
state (params, optimiser state and step; batches and noise are functions of
`(train.seed, step)`, `dmd_jax.pipeline.training_batch`, so the step is the data
position and the PRNG state) travels in one msgpack file committed to the repository,
replaced in place, and its learning curve in a CSV beside it. Each session resumes the
run from that file (`make train-long`), trains beside its other work, and commits the
state back before it stops (`make train-long-save`); `make train-long-status` says
where it is. The layout and the rules are in `docs/training.md`.

A state file holds `meta` (format, step, the run's config, the SHA-256 of the state
file it grew from, the seconds of training it holds) and `state` (Flax's state dict of
the `TrainState`). Resuming refuses a file of another recipe, and saving refuses to
replace a committed state the run did not grow from (another session committed a newer
one meanwhile): both would silently throw compute away.

    python -m dmd_jax.long_run status --workdir runs/long/ft --state training/long_run.msgpack
    python -m dmd_jax.long_run save --workdir runs/long/ft --state training/long_run.msgpack \\
        --curve training/long_run_curve.csv
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dmd_jax.io import write_text_atomic
from dmd_jax.io._files import atomic_write
from dmd_jax.train import TrainHook

FORMAT = "dmd_jax.long_run/1"
# The local export a checkpoint writes, and the record of what the workdir grew from.
LOCAL_STATE = "state.msgpack"
ORIGIN = "long_run.json"
STOP_FILE = "STOP"
PID_FILE = "pid"
# Milestones (issue 62): the run's state at every multiple of MILESTONE_EVERY steps, kept
# in <workdir>/milestones/step_NNNNNN/ (`milestone_dir`) because the rolling checkpoints
# (`train.ckpt_keep`) and the local export are overwritten within minutes.
MILESTONE_EVERY = 10_000
MILESTONES = "milestones"
MILESTONE_INFO = "milestone.json"
CURVE_FIELDS = ("step", "kind", "name", "value")


class StateConflictError(RuntimeError):
    """A state file that cannot be resumed or replaced without losing training."""


def file_sha(path) -> str:
    """SHA-256 of a file's bytes (hex), or "" when there is no such file."""
    path = Path(path)
    if not path.is_file():
        return ""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def state_bytes(state, config: dict, *, parent: str, seconds: float) -> bytes:
    """A training state and what it is, as the bytes of a state file.

    Args:
      state: a `train_step.TrainState` (device or host arrays).
      config: the run's `ExperimentConfig.to_dict()`.
      parent: SHA-256 of the state file this state grew from ("" for a fresh start).
      seconds: wall seconds of training that went into the state, all sessions.
    """
    import jax
    from flax import serialization

    host = jax.device_get(state)
    meta = {
        "format": FORMAT,
        "step": int(host.step),
        "config": json.dumps(config, sort_keys=True),
        "parent": parent,
        "seconds": float(seconds),
        "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    return serialization.msgpack_serialize(
        {"meta": meta, "state": serialization.to_state_dict(host)}
    )


def read_meta(path) -> dict:
    """The `meta` of a state file: format, step, config (a dict), parent, seconds.

    Raises:
      FileNotFoundError: no such file.
      ValueError: not a state file of this format.
    """
    raw = _read(path)
    meta = dict(raw["meta"])
    meta["config"] = json.loads(meta["config"])
    return meta


def read_state(path, template):
    """The training state a state file holds, shaped like `template` (a `TrainState`).

    Raises:
      FileNotFoundError: no such file.
      ValueError: not a state file of this format, or of another structure than
        `template` (another model or optimiser).
    """
    from flax import serialization

    raw = _read(path)
    try:
        return serialization.from_state_dict(template, raw["state"])
    except (KeyError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: the state does not fit this run's model ({err})") from None


def _read(path) -> dict:
    from flax import serialization

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no state file at {path}")
    try:
        raw = serialization.msgpack_restore(path.read_bytes())
    except Exception as err:  # msgpack raises several unrelated types for bad bytes
        raise ValueError(f"{path} is not a long-run state file ({err})") from None
    if not isinstance(raw, dict) or raw.get("meta", {}).get("format") != FORMAT:
        raise ValueError(f"{path} is not a long-run state file (format {FORMAT})")
    return raw


def _write_bytes(path, data: bytes) -> None:
    atomic_write(Path(path), lambda tmp: Path(tmp).write_bytes(data), overwrite=True)


def _origin(workdir: Path) -> dict:
    path = workdir / ORIGIN
    return json.loads(path.read_text()) if path.is_file() else {}


def _set_origin(workdir: Path, sha: str, step: int, seconds: float) -> None:
    write_text_atomic(
        workdir / ORIGIN,
        json.dumps({"resumed_from": sha, "step": step, "seconds": seconds}, indent=2),
    )


class LongRun(TrainHook):
    """Resumes a run from a committed state file and exports its state as it goes.

    At the start it takes the committed state when the workdir holds none or an older
    one, keeps the workdir's when it grew from the committed one, and refuses a state
    of another recipe or lineage (`StateConflictError`). Then it checkpoints at least
    every `checkpoint_seconds` of wall time, exports every checkpoint to
    `<workdir>/state.msgpack`, and stops the run (checkpointing it) after the step
    during which `<workdir>/STOP` appeared or SIGTERM/SIGINT arrived.

    Args:
      workdir: the run's directory (`train`'s layout).
      state_file: the committed state file (read here; written by `save`).
      config: the run's `ExperimentConfig.to_dict()`.
      checkpoint_seconds: the longest wall time between two checkpoints.
      milestone_every: keep the first checkpoint at or past every multiple of this many
        steps that the run crosses (`keep_milestone`; 0: none).
      say: where the hook's one-line notes go.
    """

    def __init__(
        self,
        workdir,
        state_file,
        config: dict,
        *,
        checkpoint_seconds=600.0,
        milestone_every: int = MILESTONE_EVERY,
        say=print,
    ):
        self.workdir = Path(workdir)
        self.state_file = Path(state_file)
        self.config = config
        self.checkpoint_seconds = float(checkpoint_seconds)
        self.milestone_every = int(milestone_every)
        self.say = say
        self._checkpointed = 0  # the step of the last checkpoint (or of the start)
        self._stop = False
        self._last = time.monotonic()
        self._seconds0 = 0.0
        self._started = time.monotonic()

    # ----------------------------------------------------------------- lifecycle
    def starting_state(self, state):
        self.workdir.mkdir(parents=True, exist_ok=True)
        (self.workdir / STOP_FILE).unlink(missing_ok=True)
        local_step = int(np.asarray(state.step))
        origin = _origin(self.workdir)
        if not self.state_file.is_file():
            self.say(f"long run: no committed state at {self.state_file}; step {local_step}")
            if not origin:
                _set_origin(self.workdir, "", local_step, 0.0)
            self._seconds0 = float(_origin(self.workdir).get("seconds", 0.0))
            return self._begin(state)
        meta = read_meta(self.state_file)
        difference = recipe_difference(meta["config"], self.config)
        if difference:
            raise StateConflictError(
                f"{self.state_file} holds a run of another recipe (its config differs from "
                f"this run's: {difference}); start the new recipe with another state "
                "file, or run the committed one's recipe"
            )
        sha = file_sha(self.state_file)
        if local_step > meta["step"]:
            if origin.get("resumed_from") != sha:
                raise StateConflictError(
                    f"{self.workdir} is at step {local_step} but did not grow from the "
                    f"committed state (step {meta['step']}, {self.state_file}): one of the two "
                    "would be lost; move the workdir away to resume from the committed state"
                )
            self.say(
                f"long run: resuming the workdir's step {local_step} (ahead of the "
                f"committed {meta['step']})"
            )
            self._seconds0 = float(origin.get("seconds", meta["seconds"]))
            return self._begin(state)
        if local_step:
            self.say(
                f"long run: the workdir's step {local_step} is not ahead of the committed "
                f"step {meta['step']}; resuming from the committed state"
            )
        else:
            self.say(f"long run: resuming from the committed state, step {meta['step']}")
        state = read_state(self.state_file, state)
        _set_origin(self.workdir, sha, meta["step"], meta["seconds"])
        self._seconds0 = float(meta["seconds"])
        return self._begin(state)

    def _begin(self, state):
        self._started = self._last = time.monotonic()
        self._checkpointed = int(np.asarray(state.step))
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                signal.signal(sig, self._on_signal)
            except ValueError:  # not the main thread: only the stop file stops the run
                pass
        return state

    def _on_signal(self, signum, frame) -> None:
        self._stop = True

    # ----------------------------------------------------------------- per step
    def after_step(self, step: int, metrics: dict[str, Any]) -> bool:
        return self._stop or (self.workdir / STOP_FILE).exists()

    def checkpoint_due(self, done: int) -> bool:
        return time.monotonic() - self._last >= self.checkpoint_seconds

    def on_checkpoint(self, state) -> None:
        self._last = time.monotonic()
        origin = _origin(self.workdir)
        seconds = self._seconds0 + (self._last - self._started)
        data = state_bytes(
            state, self.config, parent=origin.get("resumed_from", ""), seconds=seconds
        )
        _write_bytes(self.workdir / LOCAL_STATE, data)
        step = int(np.asarray(state.step))
        every = self.milestone_every
        if every > 0 and step // every > self._checkpointed // every:
            milestone = (step // every) * every
            where = keep_milestone(self.workdir, milestone, step, data)
            self.say(f"long run: milestone {milestone:,} kept at step {step} in {where}")
        self._checkpointed = step


def milestone_dir(workdir, milestone: int) -> Path:
    """`<workdir>/milestones/step_NNNNNN`: where the milestone of that step is kept."""
    return Path(workdir) / MILESTONES / f"step_{int(milestone):06d}"


def keep_milestone(workdir, milestone: int, step: int, data: bytes) -> Path:
    """Keeps a checkpoint as the run's milestone and returns its folder.

    The folder (`milestone_dir`) gets the state file's bytes `data` (`state.msgpack`,
    the long-run format), a copy of the Orbax checkpoint of `step` when the workdir has
    one (`checkpoint/<step>`: an Orbax manager folder, what `dmd-jax export-weights`
    reads) and `milestone.json` (the milestone, the exact step it was kept at, when).
    An existing milestone is left alone. Written beside and renamed into place, so a
    folder that exists is whole.
    """
    import shutil

    target = milestone_dir(workdir, milestone)
    if target.exists():
        return target
    tmp = target.with_name(target.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    (tmp / LOCAL_STATE).write_bytes(data)
    orbax = Path(workdir) / "checkpoints" / "latest" / str(int(step))
    if orbax.is_dir():
        shutil.copytree(orbax, tmp / "checkpoint" / str(int(step)))
    info = {
        "milestone": int(milestone),
        "step": int(step),
        "kept": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    (tmp / MILESTONE_INFO).write_text(json.dumps(info, indent=2) + "\n")
    tmp.rename(target)
    return target


def milestones(workdir) -> list[dict]:
    """The kept milestones of a run, oldest first: each `milestone.json` plus `dir`."""
    out = []
    for info in sorted((Path(workdir) / MILESTONES).glob(f"step_*/{MILESTONE_INFO}")):
        row = json.loads(info.read_text())
        row["dir"] = str(info.parent)
        out.append(row)
    return sorted(out, key=lambda r: r["milestone"])


def recipe_difference(stored: dict, current: dict) -> str:
    """The first setting in which two runs' configs differ, or "" when they are one recipe.

    Stricter than a workdir's resume check (`train._same_config`): a setting the stored
    config lacks (added to the code since) counts as its default, so switching a new
    setting on is another recipe, not a silent change of the committed run.
    """
    from dmd_jax.config import ExperimentConfig

    try:
        filled = ExperimentConfig.from_dict(stored).to_dict()
    except (TypeError, ValueError) as err:
        return f"the stored config is unreadable ({err})"
    return _first_difference(filled, current)


def _first_difference(a: dict, b: dict, prefix: str = "") -> str:
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            found = _first_difference(x, y, f"{prefix}{key}.")
            if found:
                return found
        elif x != y:
            return f"{prefix}{key} is {x!r} there, {y!r} here"
    return ""


# --------------------------------------------------------------------- the log


def log_rows(workdir) -> list[dict]:
    """The rows of a run's `log.jsonl`, the last of each (kind, step) kept (a resumed
    run logs again the steps after its last checkpoint), in step order."""
    path = Path(workdir) / "log.jsonl"
    rows: dict[tuple, dict] = {}
    if path.is_file():
        for line in path.read_text().split("\n"):
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # a killed run's cut-off row
            rows[(row.get("kind"), row.get("step"))] = row
    return sorted(rows.values(), key=lambda r: (r["step"], r["kind"] != "train"))


def curve_rows(rows: list[dict], after: int, upto: int) -> list[dict]:
    """Long-format curve rows (`CURVE_FIELDS`) of the log rows with `after < step <= upto`:
    every train metric and every evaluation mean."""
    out = []
    for row in rows:
        if not after < row["step"] <= upto:
            continue
        for name, value in row.items():
            if name in ("kind", "step", "time") or not isinstance(value, int | float):
                continue
            out.append(
                {"step": row["step"], "kind": row["kind"], "name": name, "value": f"{value:.6g}"}
            )
    return out


def _curve_last_step(path: Path) -> int:
    if not path.is_file():
        return 0
    with open(path, newline="") as fh:
        return max((int(r["step"]) for r in csv.DictReader(fh)), default=0)


def steps_per_hour(rows: list[dict]) -> float | None:
    """Steps per hour over the newest process's training rows (their `time` restarts at
    each resume), or None with fewer than two rows."""
    train = [r for r in rows if r["kind"] == "train"]
    seg = train[-1:]
    for r in reversed(train[:-1]):
        if r["time"] >= seg[0]["time"]:
            break
        seg.insert(0, r)
    if len(seg) < 2 or seg[-1]["time"] <= seg[0]["time"]:
        return None
    return 3600.0 * (seg[-1]["step"] - seg[0]["step"]) / (seg[-1]["time"] - seg[0]["time"])


def running_pid(workdir) -> int | None:
    """The pid of the run's process if it is alive, else None."""
    path = Path(workdir) / PID_FILE
    try:
        pid = int(path.read_text().strip())
        os.kill(pid, 0)
    except (FileNotFoundError, ValueError, ProcessLookupError, PermissionError):
        return None
    return pid


# --------------------------------------------------------------- save, status


def status_line(workdir, state_file) -> str:
    """One line: `step N`, running or not, steps per hour, the last validation figures."""
    workdir, state_file = Path(workdir), Path(state_file)
    rows = log_rows(workdir)
    local = max((r["step"] for r in rows), default=0)
    committed = read_meta(state_file)["step"] if state_file.is_file() else 0
    step = max(local, committed)
    pid = running_pid(workdir)
    parts = [f"step {step}", f"running (pid {pid})" if pid else "not running"]
    parts.append(f"committed step {committed}")
    rate = steps_per_hour(rows)
    if rate is not None:
        parts.append(f"{rate:,.0f} steps/h")
    evals = [r for r in rows if r["kind"] == "eval"]
    if evals:
        last = evals[-1]
        figures = ", ".join(
            f"{k.split('/')[0]} {v:.2f}°"
            for k, v in sorted(last.items())
            if k.endswith("/normal_deg") and "noisy" not in k
        )
        parts.append(f"last evaluation at step {last['step']}: normal error {figures}")
    else:
        parts.append("no evaluation yet")
    return "; ".join(parts)


def save(workdir, state_file, curve_file) -> int:
    """Replaces the committed state with the workdir's last export and appends its
    curve; returns the step saved.

    Raises:
      StateConflictError: the run still runs, has exported nothing, or did not grow
        from the committed state (another session committed a newer one).
    """
    workdir, state_file, curve_file = Path(workdir), Path(state_file), Path(curve_file)
    pid = running_pid(workdir)
    if pid is not None:
        raise StateConflictError(f"the run is still running (pid {pid}); stop it first")
    local = workdir / LOCAL_STATE
    if not local.is_file():
        raise StateConflictError(f"{workdir} has exported no state yet ({LOCAL_STATE})")
    origin = _origin(workdir)
    committed = file_sha(state_file)
    if committed != origin.get("resumed_from", ""):
        raise StateConflictError(
            f"{state_file} changed since this run resumed from it (another session committed "
            "a state); this run's state would replace training it does not hold"
        )
    meta = read_meta(local)
    if state_file.is_file() and meta["step"] <= read_meta(state_file)["step"]:
        return int(meta["step"])  # nothing new
    after = _curve_last_step(curve_file)
    new = curve_rows(log_rows(workdir), after, meta["step"])
    text = curve_file.read_text() if curve_file.is_file() else ""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, CURVE_FIELDS, lineterminator="\n")
    if not text:
        writer.writeheader()
    writer.writerows(new)
    state_file.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(curve_file, text + buf.getvalue())
    data = local.read_bytes()
    _write_bytes(state_file, data)
    _set_origin(workdir, hashlib.sha256(data).hexdigest(), meta["step"], meta["seconds"])
    return int(meta["step"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m dmd_jax.long_run", description=__doc__.splitlines()[0]
    )
    parser.add_argument("command", choices=("status", "save"))
    parser.add_argument("--workdir", type=Path, required=True, help="the run's directory")
    parser.add_argument("--state", type=Path, required=True, help="the committed state file")
    parser.add_argument("--curve", type=Path, help="the committed curve CSV (save)")
    args = parser.parse_args(argv)
    try:
        if args.command == "status":
            print(status_line(args.workdir, args.state))
            return 0
        if args.curve is None:
            parser.error("save needs --curve")
        step = save(args.workdir, args.state, args.curve)
        print(f"saved step {step} to {args.state} and {args.curve}")
        return 0
    except (StateConflictError, ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
