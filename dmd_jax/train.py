"""Training: one step builder for one device or many, the schemes, evaluation, the loop.

The step of each scheme and phase (`make_train_step`, `shared_train_step`, the optimizer
and the loss terms) is built in `dmd_jax.train_step`, whose names this module re-exports;
`Trainer` runs it on a device mesh. The loss curve is drawn by `dmd_jax.train_plots`.

The loop: `train_and_evaluate(cfg, workdir)` runs an experiment from its config alone
(as Flax's `examples/ogbg_molpcba/train.py`): it reads the training and evaluation sets
(`dmd_jax.data.training_sets`), the fine-tune's starting params (`TrainConfig.init_from`,
`init_params_from`), and calls `train`, the loop over given meshes, which resumes,
evaluates, logs and checkpoints. `dmd-jax train` only turns its flags into the config.
`TrainHook`s watch (or, in tests, steer) the loop: `StopAfter`, `InjectNaN`.

Checkpoints are Orbax (`dmd_jax.checkpoints`): ``<workdir>/checkpoints/latest`` keeps the
last ``ckpt_keep`` states and ``<workdir>/checkpoints/best`` the one with the lowest
normal error of the evaluation set that picks it. A run restarted in the same workdir
resumes from the latest state; since batches are a function of ``(seed, step)``, the
resumed run is bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from dmd_jax import metrics, parallel
from dmd_jax.checkpoints import (
    check_params,
    checkpoint_managers,
    graft_params,
    load_model,
    restore_checkpoint,
    save_checkpoint,
)
from dmd_jax.config import SCHEMES, ExperimentConfig, ModelConfig, NoiseConfig
from dmd_jax.io import write_text_atomic
from dmd_jax.model import DMDNet
from dmd_jax.model import init_params as init_model_params
from dmd_jax.pipeline import (
    Batch,
    CandidatePool,
    MeshExample,
    Prefetcher,
    evaluation_batches,
    largest_sizes,
    make_examples,
    size_classes,
    step_sizes,
    training_batch,
    unpadded_mesh,
)
from dmd_jax.protocol import benchmark_noise_config
from dmd_jax.train_plots import plot_curves

# The step's names, defined in `dmd_jax.train_step`, are re-exported from here too.
from dmd_jax.train_step import (
    FE_PREFIX,  # noqa: F401 (re-exported)
    PHASE_PARTS,  # noqa: F401 (re-exported)
    TrainState,
    _init_program,
    loss_terms,  # noqa: F401 (re-exported)
    make_optimizer,
    make_train_step,
    merge_params,
    phase_loss,  # noqa: F401 (re-exported)
    phase_of,
    shared_terms,  # noqa: F401 (re-exported)
    shared_train_step,  # noqa: F401 (re-exported)
    split_params,
    step_program_key,  # noqa: F401 (re-exported)
    step_values,  # noqa: F401 (re-exported)
)

# How `train` pads batches: each step to its own vertex bucket (a program per bucket it
# meets; the least padding, right for long runs), or every step to the largest batch
# the data can form (one program; right for short runs, where compiling, ~15 s of CPU a
# program for the `test` preset on 2 cores, costs more than the padding).
# `"classes"`: every step to the smallest of `PAD_CLASSES` sizes that holds it
# (`pipeline.size_classes`), every one compiled before the first step: a few programs,
# known up front, and less padding than `"largest"` (the candidate pool's default).
PAD_MODES = ("bucket", "largest", "classes")
PAD_CLASSES = 4
# `train_and_evaluate(pad="auto")` pads every batch to one shape for runs of at most this
# many steps (the test preset's 40 compile once instead of 5-6 times on a tiny dataset).
AUTO_PAD_MAX_STEPS = 500


class NonFiniteLossError(RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


class Trainer:
    """The steps of one experiment on one device mesh, built once per phase.

    Attributes:
      cfg: the experiment config.
      mesh: the device mesh (default: the first device alone).
      compiles: how many programs the steps have compiled so far (one per bucket and
        phase).
    """

    def __init__(self, cfg: ExperimentConfig, mesh: Mesh | None = None):
        if cfg.train.scheme not in SCHEMES:
            raise ValueError(f"unknown training scheme {cfg.train.scheme!r}; use one of {SCHEMES}")
        self.cfg = cfg
        self.mesh = parallel.batch_mesh(jax.devices()[:1]) if mesh is None else mesh
        self.model = DMDNet(cfg.model)
        self._step_fns: dict[str, Callable] = {}
        self._eval_fn = jax.jit(self._predict)

    @property
    def compiles(self) -> int:
        # The jit caches' own count: the step stays pure (no trace-time counter in it).
        return sum(fn._cache_size() for fn in self._step_fns.values())

    @property
    def eval_compiles(self) -> int:
        """Programs the evaluation has compiled so far (one per padded shape)."""
        return self._eval_fn._cache_size()

    def init(self, batch: Batch) -> TrainState:
        """A fresh state, replicated on the mesh; params from the config's seed.

        Args:
          batch: a training batch (its first group is used) or one padded group; only
            its shapes matter.
        """
        key = jax.random.PRNGKey(self.cfg.train.seed)
        first = jax.tree.map(lambda x: x[0], batch) if np.ndim(batch.noisy) == 3 else batch
        # Jitted: the forward pass is traced once and XLA keeps only the initialisers;
        # run eagerly, every primitive of the forward pass compiled on its own (~35 s of
        # wall time for the test preset on a loaded 2-core machine).
        init = _init_program(self.cfg.model)  # shared by the trainers of one model
        variables = init(
            {"params": key, "dropout": key},
            jnp.asarray(first.noisy),
            jax.tree.map(jnp.asarray, first.graph),
        )
        halves = split_params(variables["params"])
        tx = make_optimizer(self.cfg)
        opt_state = {k: tx.init(v) for k, v in halves.items()}
        state = TrainState(step=jnp.asarray(0, jnp.int32), params=halves, opt_state=opt_state)
        return parallel.replicate(self.mesh, state)

    def step_fn(self, step: int) -> Callable:
        t = self.cfg.train
        phase = phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)
        if phase not in self._step_fns:
            self._step_fns[phase] = make_train_step(self.cfg, phase, self.mesh)
        return self._step_fns[phase]

    def train_step(self, state: TrainState, batch: Batch) -> tuple[TrainState, dict]:
        """One step on a batch of this process's groups (`pipeline.training_batch`)."""
        step = int(state.step)
        rng = jax.random.fold_in(jax.random.PRNGKey(self.cfg.train.seed + 1), step)
        placed = parallel.shard_batch(self.mesh, batch)
        fn = self.step_fn(step)
        if placed.local is None:
            return fn(state, placed.noisy, placed.clean, placed.graph, rng)
        return fn(state, placed.noisy, placed.clean, placed.graph, rng, placed.local)

    # ---------------------------------------------------------------- eval
    def _predict(self, params, noisy, graph):
        # The passes the run trains (`TrainConfig.passes`); features of the first.
        out, feats, _ = self.model.apply({"params": params}, noisy, graph, deterministic=True)
        for _ in range(self.cfg.train.passes - 1):
            out, _, _ = self.model.apply({"params": params}, out, graph, deterministic=True)
        return out, feats

    def predict(self, params: dict, batch: Batch):
        return self._eval_fn(
            params, jnp.asarray(batch.noisy), jax.tree.map(jnp.asarray, batch.graph)
        )

    def evaluate(self, params: dict, batches: Sequence[tuple[Batch, Any]]) -> dict:
        """Mean metrics (vertex, normal°, chamfer) of model output and of the noisy input."""
        rows = []
        for batch, _ in batches:
            out, _ = self.predict(params, batch)
            noisy, clean, faces = unpadded_mesh(batch)
            pred = np.asarray(out[: noisy.shape[0]], np.float64)
            # Padded to the batch's rows: one metric program per evaluation shape.
            padded = batch.noisy.shape[0]
            m = metrics.mesh_metrics(pred, clean, faces, min_rows=padded)
            r = metrics.mesh_metrics(noisy, clean, faces, min_rows=padded)
            rows.append(
                {
                    **{k: float(v) for k, v in m.items()},
                    **{f"noisy_{k}": float(v) for k, v in r.items()},
                }
            )
        if not rows:
            return {}
        return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


# -------------------------------------------------------------------- loop


def _same_config(stored: dict, current: dict) -> bool:
    """Whether a workdir's `config.json` holds this run's config (`to_dict` form).

    A key the stored config lacks is a setting added since it was written (e.g.
    `data.dataset_dir`): it matches whatever this run sets, so older runs still resume.
    """
    if set(stored) - set(current):
        return False
    for key, value in stored.items():
        mine = current[key]
        if isinstance(value, dict) and isinstance(mine, dict):
            if not _same_config(value, mine):
                return False
        elif value != mine:
            return False
    return True


class TrainHook:
    """Watches the training loop, and may steer it (a base class; override either method).

    `train` calls `before_step` with each step's batch before the step runs, and
    `after_step` with its metrics once the step has run and its loss is finite. A hook
    that returns True from `after_step` ends the run there as if `train.steps` were
    reached early (the last rows are logged and the state is checkpointed; no final
    evaluation), so a later `train` call in the same workdir resumes from it.
    """

    def before_step(self, step: int, batch: Batch) -> Batch:
        """The batch step `step` (0-based) trains on; this one returns it unchanged.

        Args:
          step: the step about to run.
          batch: its batch, `noisy`/`clean` `[n_group, n_vertex, 3]`.
        """
        return batch

    def after_step(self, step: int, metrics: dict[str, Any]) -> bool | None:
        """Called after step `step` (0-based) ran; True stops the run after it.

        Args:
          step: the step that ran (`step + 1` steps are done).
          metrics: its `loss`, `grad_norm` and loss terms (scalar arrays).
        """
        return None

    def starting_state(self, state: TrainState) -> TrainState:
        """The state the loop starts from, given the one it would start from.

        Called once, after the workdir's newest checkpoint (if any) was restored; this
        one returns it unchanged. A hook may return another state of the same structure
        (e.g. one carried in from another machine, `dmd_jax.long_run`).
        """
        return state

    def checkpoint_due(self, done: int) -> bool:
        """Whether to checkpoint now, `done` steps done, beside `train.ckpt_every`'s
        schedule (e.g. every few minutes of wall time); this one never asks."""
        return False

    def on_checkpoint(self, state: TrainState) -> None:
        """Called after every checkpoint of the latest state, with that state."""


class StopAfter(TrainHook):
    """Stops after `steps` steps of this `train` call, as a killed run would have left
    it (resume tests); the stop checkpoints, as a graceful one does. It counts the steps
    it has seen, so each call takes a new one."""

    def __init__(self, steps: int):
        if steps < 1:
            raise ValueError(f"StopAfter needs at least 1 step, got {steps}")
        self.steps = steps
        self._done = 0

    def after_step(self, step: int, metrics: dict[str, Any]) -> bool:
        self._done += 1
        return self._done >= self.steps


class InjectNaN(TrainHook):
    """Replaces the noisy input of step `step` with NaNs (fault-injection tests): the
    loss turns non-finite and `train` raises `NonFiniteLossError`."""

    def __init__(self, step: int):
        self.step = step

    def before_step(self, step: int, batch: Batch) -> Batch:
        if step != self.step:
            return batch
        return batch._replace(noisy=np.full_like(batch.noisy, np.nan))


def train(
    cfg: ExperimentConfig,
    train_examples: Sequence[MeshExample],
    workdir,
    *,
    eval_sets: dict[str, Sequence[MeshExample]] | None = None,
    progress: bool = True,
    init_params: dict | None = None,
    data_parallel: bool = False,
    eval_noise: NoiseConfig | None = None,
    pad_to: str = "bucket",
    verbose: bool = False,
    hooks: Sequence[TrainHook] = (),
) -> dict:
    """Trains (or resumes) a run in `workdir`; returns the final evaluation.

    Args:
      cfg: the experiment config (model, loss, train, noise).
      train_examples: training meshes (clean, canonical), graphs prebuilt.
      workdir: where checkpoints, `log.jsonl`, `config.json` and `loss_curve.png` go.
      eval_sets: e.g. `{"test_intra": [...], "test_inter": [...]}`.
      progress: show a tqdm bar.
      init_params: start from these params (fine-tuning) instead of a fresh init; the
        optimizer starts fresh. Ignored when the workdir already holds a checkpoint.
      eval_noise: the noise of the evaluation sets (default: the training noise).
        With an eval set named `val`, the best checkpoint is chosen on its normal
        error; otherwise on `test_intra`'s.
      data_parallel: split each step's global batch over every device of every process
        (`parallel.batch_mesh()`; otherwise the mesh is the first device alone); the
        same steps as on one device up to the order of float sums, dropout masks aside. With several
        processes (`jax.distributed.initialize` first) each builds only its own groups,
        only process 0 writes `config.json`, `log.jsonl` and the plot, and Orbax writes
        the checkpoints from process 0: `workdir` must be one shared directory.
      pad_to: `"bucket"` (each training batch and evaluation mesh padded to its own
        vertex bucket) or `"largest"` (every training batch to the largest the training
        set can form, every evaluation mesh to the largest evaluation mesh: one training
        and one evaluation program) or `"classes"` (every training batch to the smallest
        of `PAD_CLASSES` sizes that holds it, `pipeline.size_classes`, each compiled
        before the first step; evaluation as `"largest"`); `PAD_MODES`.
      verbose: print a line when a program is compiled and how long it took.
      hooks: `TrainHook`s, called in order at every step (e.g. `StopAfter`, `InjectNaN`).

    Returns:
      `step` (the steps done), `compiles`, `eval_compiles`, the last evaluation's
      `<set>/<metric>` means (with `kind` and `step`) if there was one, and `state`, the
      final `TrainState`.

    Raises:
      NonFiniteLossError: the loss became NaN/inf; the last good checkpoint is kept.
      ValueError: with `data_parallel`, a global batch smaller than the device count.
    """
    from tqdm.auto import tqdm

    t = cfg.train
    if pad_to not in PAD_MODES:
        raise ValueError(f"pad_to must be one of {PAD_MODES}, got {pad_to!r}")
    mesh = parallel.batch_mesh() if data_parallel else parallel.batch_mesh(jax.devices()[:1])
    if t.batch_size < mesh.size:
        raise ValueError(
            f"data-parallel training needs at least one mesh per device: train.batch_size "
            f"is {t.batch_size} but there are {mesh.size} devices; set train.batch_size "
            f">= {mesh.size} or run on fewer devices"
        )
    trainer = Trainer(cfg, mesh)
    mine = parallel.local_groups(mesh)
    train_sizes = eval_sizes = classes = None
    if pad_to == "largest":
        train_sizes = largest_sizes(train_examples, -(-t.batch_size // mesh.size))
    if pad_to == "classes":
        classes = size_classes(train_examples, -(-t.batch_size // mesh.size), PAD_CLASSES)
        every_eval = [ex for exs in (eval_sets or {}).values() for ex in exs]
        eval_sizes = largest_sizes(every_eval, 1) if every_eval else None
        every_eval = [ex for exs in (eval_sets or {}).values() for ex in exs]
        eval_sizes = largest_sizes(every_eval, 1) if every_eval else None

    pool = None
    if t.candidate_pool > 0:
        pool = CandidatePool.from_config(
            train_examples, cfg, n_group=mesh.size, groups=mine, sizes=train_sizes
        )

    def make_batch(step: int, sizes=None) -> Batch:
        if sizes is None and classes is not None:
            sizes = step_sizes(
                train_examples,
                step,
                classes,
                batch_size=t.batch_size,
                seed=t.seed,
                n_group=mesh.size,
            )
        if pool is not None:
            return pool.batch(step, sizes)
        return training_batch(
            train_examples,
            step,
            batch_size=t.batch_size,
            seed=t.seed,
            noise=cfg.noise,
            rotate=t.rotate,
            encoding=cfg.model.encoding,
            n_group=mesh.size,
            groups=mine,
            sizes=train_sizes if sizes is None else sizes,
        )

    # Data-parallel processes share one workdir: only the first writes the run's files.
    primary = not data_parallel or jax.process_index() == 0
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    cfg_path = workdir / "config.json"
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        if not _same_config(old, cfg.to_dict()):
            raise ValueError(
                f"{workdir} holds a run with a different config; use another --workdir"
            )
    elif primary:
        write_text_atomic(cfg_path, json.dumps(cfg.to_dict(), indent=2))
    state = trainer.init(make_batch(0))
    if init_params is not None:
        fresh = jax.tree_util.tree_structure(merge_params(state.params))
        if jax.tree_util.tree_structure(init_params) != fresh:
            raise ValueError("init_params do not match the model of this config")
        halves = split_params(jax.tree.map(jnp.asarray, init_params))
        state = parallel.replicate(mesh, state._replace(params=halves))
    latest, best = checkpoint_managers(workdir, t.ckpt_keep)
    if latest.latest_step() is not None:
        state = parallel.replicate(mesh, restore_checkpoint(latest, state))
    if hooks:
        for hook in hooks:
            state = hook.starting_state(state)
        state = parallel.replicate(mesh, state)
    eval_batches = {
        name: evaluation_batches(
            ex,
            seed=t.seed + 12345,
            noise=cfg.noise if eval_noise is None else eval_noise,
            rotate=t.rotate,
            encoding=cfg.model.encoding,
            sizes=eval_sizes,
        )
        for name, ex in (eval_sets or {}).items()
        if ex
    }
    log_path = workdir / "log.jsonl"
    start = int(state.step)
    end = t.steps
    bar = tqdm(total=t.steps, initial=start, disable=not progress, desc="train", unit="step")
    last_eval: dict = {}
    t0 = time.time()

    def say(message: str) -> None:
        if verbose and primary:
            tqdm.write(message)

    if classes is not None and start < end:
        # Every class's program compiled now, on a coming step's batch padded up to it
        # (its update discarded), so that no step of the run compiles.
        def class_of(step):
            return step_sizes(
                train_examples,
                step,
                classes,
                batch_size=t.batch_size,
                seed=t.seed,
                n_group=mesh.size,
            )

        for c in classes:
            warm = next(
                (s for s in range(start, start + 1000) if class_of(s).n_vertex <= c.n_vertex),
                None,
            )
            if warm is None:
                continue  # no batch this small soon: it would compile when one comes
            started = time.perf_counter()
            jax.block_until_ready(trainer.train_step(state, make_batch(warm, c))[1])
            say(
                f"compiled the training step for {c.n_vertex:,} padded vertices in "
                f"{time.perf_counter() - started:.1f} s ({trainer.compiles} program(s), "
                "pad_to='classes')"
            )

    # With the pool, a background thread builds the next batches during the step.
    source = Prefetcher(make_batch, start) if pool is not None and start < end else None
    with (
        open(log_path if primary else os.devnull, "a") as log,
        contextlib.closing(source) if source is not None else contextlib.nullcontext(),
    ):
        if log.tell():
            with open(log_path, "rb") as fh:
                fh.seek(-1, 2)
                if fh.read(1) != b"\n":
                    log.write("\n")  # a killed run's cut-off row must not swallow the next
        for step in range(start, end):
            batch = make_batch(step) if source is None else source.get(step)
            for hook in hooks:
                batch = hook.before_step(step, batch)
            compiled = trainer.compiles
            started = time.perf_counter()
            new_state, out = trainer.train_step(state, batch)
            loss = float(out["loss"])
            if trainer.compiles > compiled:
                say(
                    f"compiled the training step for batches of {batch.noisy.shape[-2]:,} "
                    f"padded vertices in {time.perf_counter() - started:.1f} s (first step "
                    f"included; {trainer.compiles} program(s) so far, pad_to={pad_to!r})"
                )
            if not math.isfinite(loss):
                bar.close()
                raise NonFiniteLossError(
                    f"non-finite loss ({loss}) at step {step}; stopped. The last good "
                    f"checkpoint (step {latest.latest_step()}) is kept in {workdir}/checkpoints"
                )
            state = new_state
            done = step + 1
            # Every hook sees every step (no short-circuit); a stop ends the run here.
            stops = [bool(hook.after_step(step, out)) for hook in hooks]
            if any(stops):
                end = done
            if (t.log_every and done % t.log_every == 0) or done == end:
                row = {
                    "kind": "train",
                    "step": done,
                    "time": time.time() - t0,
                    **{k: float(v) for k, v in out.items()},
                }
                log.write(json.dumps(row) + "\n")
            bar.set_postfix(loss=f"{loss:.4g}")
            bar.update(1)
            if eval_batches and ((t.eval_every and done % t.eval_every == 0) or done == t.steps):
                # This process's copy of the params: evaluation needs no other device.
                params = parallel.local_copy(merge_params(state.params))
                last_eval = {"kind": "eval", "step": done}
                compiled = trainer.eval_compiles
                started = time.perf_counter()
                for name, batches in eval_batches.items():
                    for k, v in trainer.evaluate(params, batches).items():
                        last_eval[f"{name}/{k}"] = v
                if trainer.eval_compiles > compiled:
                    say(
                        f"evaluated {sum(map(len, eval_batches.values()))} meshes in "
                        f"{time.perf_counter() - started:.1f} s, compiling "
                        f"{trainer.eval_compiles - compiled} evaluation program(s)"
                    )
                log.write(json.dumps(last_eval) + "\n")
                log.flush()
                key = "val/normal_deg" if "val/normal_deg" in last_eval else "test_intra/normal_deg"
                if key in last_eval:
                    save_checkpoint(best, state, cfg, {"normal_deg": last_eval[key]})
            due = [bool(hook.checkpoint_due(done)) for hook in hooks]
            if (t.ckpt_every and done % t.ckpt_every == 0) or done == end or any(due):
                log.flush()
                save_checkpoint(latest, state, cfg)
                for hook in hooks:
                    hook.on_checkpoint(state)
            if done == end:
                break  # a hook stopped the run (or this was the last step)
    bar.close()
    if primary:
        plot_curves(log_path, workdir / "loss_curve.png")
    return {
        "step": int(state.step),
        "compiles": trainer.compiles,
        "eval_compiles": trainer.eval_compiles,
        **last_eval,
        "state": state,
    }


# ------------------------------------------------------------- experiment


def train_and_evaluate(
    cfg: ExperimentConfig,
    workdir,
    *,
    pad: str = "auto",
    data_parallel: bool = False,
    progress: bool = True,
    verbose: bool = False,
    hooks: Sequence[TrainHook] = (),
) -> dict:
    """Trains (or resumes) the run `cfg` describes in `workdir`, evaluating as it goes.

    The config alone says what the run is: the dataset and the evaluation sets
    (`cfg.data`, read by `data.training_sets.training_sets`), real-mesh patches and the
    `val` set that then picks the best checkpoint (`cfg.data.real_root`, evaluated with
    `protocol.benchmark_noise_config()`), and the params a fine-tune starts from
    (`cfg.train.init_from`, `init_params_from`). The keywords only say how it runs.

    Args:
      cfg: the experiment; `cfg.data.dataset_dir` must name a dataset.
      workdir: the run directory (`train`'s layout); a run there resumes.
      pad: `"bucket"`, `"largest"` (`train`'s `pad_to`) or `"auto"`: `"largest"` for
        runs of at most `AUTO_PAD_MAX_STEPS` steps, where compiling one program per
        vertex bucket (~15 s of CPU each for the test preset on 2 cores) would cost more
        than the padding, else `"bucket"`, or `"classes"` for a run with a candidate
        pool (`PAD_CLASSES` programs, all compiled before its first step).
      data_parallel: split each batch over every device of every process (`train`).
      progress: a progress bar (process 0 only).
      verbose: print what is trained on, and when a program compiles (process 0 only).
      hooks: `TrainHook`s for the loop (`train`).

    Returns:
      `train`'s result (`step`, `compiles`, `eval_compiles`, the last evaluation, the
      final `state`) and `wall_time_s`, the seconds `train` took.

    Raises:
      ValueError: no dataset, an `init_from` whose params do not fit, a bad `pad`, or
        any of `train`'s.
      FileNotFoundError: a missing dataset, real-mesh folder or `init_from`.
      NonFiniteLossError: the loss became NaN/inf.
    """
    from dmd_jax.data.training_sets import training_sets

    modes = ("auto", *PAD_MODES)
    if pad not in modes:
        raise ValueError(f"pad must be one of {modes}, got {pad!r}")
    primary = jax.process_index() == 0
    sets = training_sets(cfg.data, seed=cfg.train.seed)
    train_ex = make_examples(sets.train)
    evals = {name: make_examples(meshes) for name, meshes in sets.evals.items()}
    if verbose and primary:
        print(
            f"training {cfg.name} on {len(train_ex)} meshes from {cfg.data.dataset_dir}; "
            "evaluating on "
            + ", ".join(f"{k}: {len(v)}" for k, v in evals.items())
            + (f"; data-parallel over {jax.device_count()} devices" if data_parallel else "")
        )
    init = None
    if cfg.train.init_from is not None:
        init = init_params_from(cfg.train.init_from, cfg)
    if pad == "auto":
        # With the candidate pool: a few programs, all compiled before the first step.
        if cfg.train.steps <= AUTO_PAD_MAX_STEPS:
            pad = "largest"
        else:
            pad = "classes" if cfg.train.candidate_pool > 0 else "bucket"
    t0 = time.time()
    result = train(
        cfg,
        train_ex,
        workdir,
        eval_sets=evals,
        progress=progress and primary,
        init_params=init,
        data_parallel=data_parallel,
        # The real validation split is scored as the benchmark scores (Gaussian noise
        # along normals), and with it every other set, so their numbers compare.
        eval_noise=benchmark_noise_config() if cfg.data.real_root is not None else None,
        pad_to=pad,
        verbose=verbose,
        hooks=hooks,
    )
    result["wall_time_s"] = time.time() - t0
    return result


def init_params_from(path, cfg: ExperimentConfig) -> dict:
    """The params a fine-tune starts from: those of a checkpoint or weights file.

    The source's model may differ from `cfg.model` only in settings that hold no
    parameters (its params must pass `checkpoints.check_params` against `cfg`: the same
    paths, shapes and dtypes, finite), or by the added `head_consistency` input, whose
    zero-initialised layer is grafted on.

    Args:
      path: an Orbax checkpoint directory or a weights file (`checkpoints.load_model`).
      cfg: the fine-tune's config.

    Returns:
      The params, a nested dict of arrays shaped as `cfg.model`'s.

    Raises:
      ValueError: the params do not fit `cfg`'s model; the message names the differing
        model settings.
      FileNotFoundError: no such checkpoint or weights file.
    """
    source = load_model(path)
    src = source.config.model
    try:
        check_params(source.params, cfg, "the source")
        return source.params
    except ValueError as exc:
        problem = f"{exc}; model config differs: {_model_diff(src, cfg.model)}"
    if cfg.model.head_consistency and not src.head_consistency:
        # Adding the consistency input to a trained head: its Dense layer starts at
        # zero, so the run starts from the trained model's outputs.
        fresh = init_model_params(cfg.model, jax.random.PRNGKey(cfg.train.seed))
        try:
            return graft_params(fresh, source.params)
        except ValueError as exc:
            problem = f"{exc}; {problem}"
    raise ValueError(f"{path}: its parameters do not fit this run's model ({problem})")


def _model_diff(a: ModelConfig, b: ModelConfig) -> str:
    """`"width 8 vs 16; ..."`: the fields two model configs set differently."""
    diff = [
        f"{f.name} {getattr(a, f.name)!r} vs {getattr(b, f.name)!r}"
        for f in dataclasses.fields(a)
        if getattr(a, f.name) != getattr(b, f.name)
    ]
    return "; ".join(diff) or "same fields"
