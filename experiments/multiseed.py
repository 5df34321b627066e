"""Several seeds of one config trained side by side as one compiled program.

The ablation models are small: one step of one seed leaves most of a CPU idle between
tiny operations. `seeds_step` wraps `dmd_jax.train.shared_train_step` (the library's
train step with loss weights, dropout rate and phase as traced arguments) in `jax.vmap`
over a leading *seeds* axis of the state, the batch and the dropout key, so the seeds of
a row run as one program with operations `n_seeds` times larger; rows that differ only
in those traced values share that program (one compile per padded shape). Nothing else
about training changes: each seed keeps its own parameter-init key (`train.seed`), its
own data order, noise and rotations (`pipeline.training_batch` at its own seed), its own
dropout keys and its own Adam state; the batches of all seeds are padded to one common
bucket so that they stack. Seed `s` trained here follows the same
steps as `dmd_jax.train.train` with `train.seed = s`, up to the order of float sums
(`tests/test_multiseed.py`).

Each seed keeps its own run directory (`config.json`, `log.jsonl`, Orbax checkpoints under
`checkpoints/latest`), written in `train`'s layout, so a seed can be resumed, evaluated
or loaded (`checkpoints.load_model`) on its own.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import metrics, parallel
from dmd_jax.checkpoints import checkpoint_managers, restore_checkpoint, save_checkpoint
from dmd_jax.config import ExperimentConfig
from dmd_jax.io import write_text_atomic
from dmd_jax.pipeline import (
    MeshExample,
    batch_indices,
    common_sizes,
    evaluation_batches,
    largest_sizes,
    split_slots,
    training_batch,
    unpadded_mesh,
)
from dmd_jax.train import (
    Trainer,
    TrainHook,
    merge_params,
    phase_of,
    shared_train_step,
    step_program_key,
    step_values,
)


def same_but_seed(cfgs: Sequence[ExperimentConfig]) -> None:
    """Raises `ValueError` unless the configs differ only in `train.seed` and `name`."""

    def key(c):
        d = c.to_dict()
        d.pop("name", None)
        d["train"].pop("seed", None)
        return json.dumps(d, sort_keys=True)

    if len({key(c) for c in cfgs}) > 1:
        raise ValueError("seeds trained together must share every setting but train.seed")
    seeds = [c.train.seed for c in cfgs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"repeated seeds {seeds}")


def stack_trees(trees: Sequence[Any]):
    """Pytrees of equal structure stacked on a new leading (seeds) axis."""
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *trees)


def unstack_tree(tree, n: int) -> list:
    """Inverse of `stack_trees`: the `n` slices along the leading axis."""
    return [jax.tree.map(lambda x, i=i: x[i], tree) for i in range(n)]


# One jitted, vmapped program per `train.step_program_key` in this process: the rows of
# a sweep that differ only in loss weights (terms switched off included), dropout rate or
# scheme reuse it (one compile per padded shape for all of them, every phase) instead of
# compiling a program of their own.
_SEEDS_PROGRAMS: dict[str, Callable] = {}


class SeedsStep:
    """A shared seeds program with one config's traced values (`train.step_values`).

    Attributes:
      program: the jitted `jax.vmap` of `train.shared_train_step`, shared by key.
      values: this config's loss weights, phase halves and keep probability.
    """

    def __init__(self, program: Callable, values: dict):
        self.program, self.values = program, values
        # The program computes every term; the config's metrics are its own terms'.
        self._off = {name for name, w in values["weights"].items() if not w > 0}

    def __call__(self, states, noisy, clean, graph, rngs):
        states, metrics = self.program(states, noisy, clean, graph, rngs, self.values)
        return states, {k: v for k, v in metrics.items() if k not in self._off}

    def _cache_size(self) -> int:
        """Programs the shared step holds (every config of its key counts)."""
        return self.program._cache_size()


def _one_seed(step: Callable) -> Callable:
    """`jax.vmap(step)` for a seeds axis of size 1: the slice, the step, a new axis.

    Same values as the vmap; tracing it skips the batching of every primitive, a third
    of a train step's trace time, which is most of a smoke run's work.
    """

    def squeeze(tree):
        return jax.tree.map(lambda x: x[0], tree)

    def one(states, noisy, clean, graph, rngs, values):
        out = step(*(squeeze(a) for a in (states, noisy, clean, graph, rngs)), values)
        return jax.tree.map(lambda x: x[None], out)

    return one


def seeds_step(cfg: ExperimentConfig, phase: str, n_seeds: int | None = None) -> SeedsStep:
    """The train step of one phase, vmapped over a leading seeds axis of every input.

    The program is shared by every config of this process with the same
    `train.step_program_key` (see `_SEEDS_PROGRAMS`); the values that differ between
    them are passed in, not compiled in.

    Returns:
      `step(states, noisy, clean, graph, rngs) -> (states, metrics)`, each argument the
      per-seed argument of `make_train_step`'s step stacked on axis 0 (states from
      `stack_trees`; `noisy` `[n_seeds, n_group, n_vertex, 3]`); every metric comes back
      as `[n_seeds]`. One device (a one-device mesh): seeds replace data parallelism.
      With `n_seeds=1` the program is `_one_seed`'s (no vmap), which only takes a
      seeds axis of size 1; any other `n_seeds` (or `None`) gets the vmap.
    """
    key = json.dumps([step_program_key(cfg), n_seeds == 1])
    if key not in _SEEDS_PROGRAMS:
        step = shared_train_step(cfg, parallel.batch_mesh(jax.devices()[:1]))
        # The values are the same for every seed: not vmapped.
        seeds = _one_seed(step) if n_seeds == 1 else jax.vmap(step, in_axes=(0, 0, 0, 0, 0, None))
        _SEEDS_PROGRAMS[key] = jax.jit(seeds)
    return SeedsStep(_SEEDS_PROGRAMS[key], step_values(cfg, phase))


# One evaluation `Trainer` per model config and trained pass count (dropout left out:
# evaluation runs the model deterministic), so the rows and seeds of one model share its
# compiled predictor.
_EVAL_TRAINERS: dict[str, Trainer] = {}


def eval_trainer(cfg: ExperimentConfig) -> Trainer:
    """A `Trainer` whose `predict` serves every config with `cfg`'s model (any dropout)
    and `cfg`'s `train.passes` (the passes evaluation runs)."""
    model = cfg.model.with_edits({"dropout": 0.0})
    key = json.dumps([model.to_dict(), cfg.train.passes], sort_keys=True)
    if key not in _EVAL_TRAINERS:
        _EVAL_TRAINERS[key] = Trainer(cfg.with_edits({"model": {"dropout": 0.0}}))
    return _EVAL_TRAINERS[key]


def seeds_batch(examples: Sequence[MeshExample], cfgs: Sequence[ExperimentConfig], step: int):
    """The step's batch of every seed, padded to the bucket of the largest, stacked."""
    t = cfgs[0].train
    slots = split_slots(t.batch_size, 1)
    groups = []
    for c in cfgs:
        idx = batch_indices(step, len(examples), t.batch_size, c.train.seed)
        groups += [[examples[int(idx[j])].graph for j in s] for s in slots]
    sizes = common_sizes(groups)
    batches = [
        training_batch(
            examples,
            step,
            batch_size=t.batch_size,
            seed=c.train.seed,
            noise=c.noise,
            rotate=t.rotate,
            encoding=c.model.encoding,
            sizes=sizes,
        )
        for c in cfgs
    ]
    return jax.tree.map(lambda *xs: np.stack(xs), *batches)


def step_rngs(cfgs: Sequence[ExperimentConfig], step: int):
    """Each seed's dropout key of `step`, as `Trainer.train_step` derives it."""
    return jnp.stack([jax.random.fold_in(jax.random.PRNGKey(c.train.seed + 1), step) for c in cfgs])


def evaluate_per_mesh(trainer: Trainer, params, batches) -> list[dict[str, float]]:
    """`Trainer.evaluate`'s metrics, one dict per mesh instead of their mean."""
    rows = []
    for batch, _ in batches:
        out, _ = trainer.predict(params, batch)
        noisy, clean, faces = unpadded_mesh(batch)
        m = metrics.mesh_metrics(np.asarray(out[: noisy.shape[0]], np.float64), clean, faces)
        r = metrics.mesh_metrics(noisy, clean, faces)
        rows.append({**m, **{f"noisy_{k}": v for k, v in r.items()}})
    return rows


def resume_step(home) -> int:
    """The step a run directory resumes from (0: a fresh start)."""
    latest = Path(home) / "checkpoints" / "latest"
    if not latest.is_dir():
        return 0
    steps = [int(p.name) for p in latest.iterdir() if p.name.isdigit()]
    return max(steps) if steps else 0


def train_seeds(
    cfgs: Sequence[ExperimentConfig],
    train_examples: Sequence[MeshExample],
    workdirs: Sequence,
    *,
    eval_sets: dict[str, Sequence[MeshExample]] | None = None,
    progress: bool = True,
    desc: str = "train",
    eval_seed: int | None = None,
    hooks: Sequence[TrainHook] = (),
) -> list[dict]:
    """Trains (or resumes) several seeds of one config together; evaluates each.

    Args:
      cfgs: one config per seed, equal but for `train.seed` (`same_but_seed`).
      train_examples: the training meshes.
      workdirs: one run directory per seed (`train`'s layout: `config.json`,
        `log.jsonl`, `checkpoints/latest`). All must resume from the same step.
      eval_sets: e.g. `{"test_intra": [...], "test_inter": [...]}`, evaluated after the
        last step with each seed's own fixed evaluation noise (`train`'s protocol).
      progress: a tqdm bar over steps with the remaining-time estimate.
      desc: the progress bar's label.
      eval_seed: the key of the evaluation noise, the same for every seed, so that all
        seeds (and all rows) are scored on the same noisy test meshes; `None` gives each
        seed its own, `train.seed + 12345`, as `dmd_jax.train.train` does.
      hooks: `dmd_jax.train.TrainHook`s, as in `train.train`: `before_step` sees the
        seeds' stacked batch, `after_step` their stacked metrics (`[n_seed]` arrays); a
        stop (e.g. `train.StopAfter`) checkpoints every seed there.

    Returns:
      Per seed: `status` (`ok` or `diverged`), `error`, `step` (the last good step),
      `resumed_from`, `metrics` (`<split>/<metric>` means), `per_mesh` (`<split>/<metric>`
      lists, test meshes in order), `compiles` (train-step programs this call compiled;
      0 when it reused those of an earlier row of its key), `step_times` (seconds of
      each timed step of the group, compile steps left out).

    Raises:
      ValueError: configs that differ in more than the seed, or runs at different steps.
    """
    from tqdm.auto import tqdm

    same_but_seed(cfgs)
    n = len(cfgs)
    t = cfgs[0].train
    workdirs = [Path(w) for w in workdirs]
    starts = {resume_step(w) for w in workdirs}
    if len(starts) > 1:
        raise ValueError(f"seeds at different steps {sorted(starts)}: train them apart")
    for cfg, w in zip(cfgs, workdirs, strict=True):
        w.mkdir(parents=True, exist_ok=True)
        path = w / "config.json"
        if path.exists() and json.loads(path.read_text()) != cfg.to_dict():
            raise ValueError(f"{w} holds a run with a different config")
        if not path.exists():
            write_text_atomic(path, json.dumps(cfg.to_dict(), indent=2))
    trainers = [Trainer(c) for c in cfgs]
    first = seeds_batch(train_examples, cfgs, 0)
    states = [tr.init(jax.tree.map(lambda x, i=i: x[i], first)) for i, tr in enumerate(trainers)]
    managers = [checkpoint_managers(w, t.ckpt_keep)[0] for w in workdirs]
    start = starts.pop()
    if start:
        states = [restore_checkpoint(m, s) for m, s in zip(managers, states, strict=True)]
    state = stack_trees(states)
    end = t.steps
    fns: dict[str, SeedsStep] = {}
    compiles = 0  # programs this call compiled (0 when it reused another row's)
    alive = [True] * n
    last_good = [start] * n
    errors: list[str | None] = [None] * n
    times: list[float] = []
    logs = [open(w / "log.jsonl", "a") for w in workdirs]
    bar = tqdm(
        total=t.steps,
        initial=start,
        disable=not progress,
        desc=desc,
        unit="step",
        position=1,  # under the sweep's bar
        leave=False,
    )
    t0 = time.time()
    try:
        for step in range(start, end):
            phase = phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)
            if phase not in fns:
                fns[phase] = seeds_step(cfgs[0], phase, n)
            programs = fns[phase]._cache_size()
            batch = seeds_batch(train_examples, cfgs, step)
            for hook in hooks:
                batch = hook.before_step(step, batch)
            ts = time.perf_counter()
            rngs = step_rngs(cfgs, step)
            new, out = fns[phase](state, batch.noisy, batch.clean, batch.graph, rngs)
            loss = np.asarray(out["loss"])
            # The shared program grew: this step compiled (for this run or any config).
            compiled = fns[phase]._cache_size() - programs
            compiles += compiled
            if not compiled:
                times.append(time.perf_counter() - ts)
            state = new
            done = step + 1
            for i in range(n):
                if alive[i] and not math.isfinite(float(loss[i])):
                    # vmap keeps the seeds apart: the others train on; this one keeps its
                    # last good checkpoint, as `train` does.
                    alive[i] = False
                    errors[i] = f"non-finite loss ({float(loss[i])}) at step {step}"
            # Every hook sees every step (no short-circuit); a stop ends the run here.
            stops = [bool(hook.after_step(step, out)) for hook in hooks]
            if any(stops):
                end = done
            write_log = (t.log_every and done % t.log_every == 0) or done == end
            save = (t.ckpt_every and done % t.ckpt_every == 0) or done == end
            if write_log or save:
                host = jax.device_get(out) if write_log else None
                per_seed = unstack_tree(state, n) if save else None
                for i in range(n):
                    if not alive[i]:
                        continue
                    if write_log:
                        row = {"kind": "train", "step": done, "time": time.time() - t0}
                        row |= {k: float(v[i]) for k, v in host.items()}
                        logs[i].write(json.dumps(row) + "\n")
                        logs[i].flush()
                    if save:
                        save_checkpoint(managers[i], per_seed[i], cfgs[i])
                        last_good[i] = done
            bar.set_postfix(loss=" ".join(f"{x:.3g}" for x in loss))
            bar.update(1)
            if done == end:
                break  # a hook stopped the run (or this was the last step)
    finally:
        bar.close()
        for fh in logs:
            fh.close()
    results = []
    params = unstack_tree(merge_params(state.params), n)
    # Every evaluation mesh padded to the largest (`train.train`'s `pad_to="largest"`):
    # the one evaluation after the last step then compiles one predictor per model
    # instead of one per vertex bucket, which costs more than the padding.
    every_eval = [ex for split in (eval_sets or {}).values() for ex in split]
    eval_sizes = largest_sizes(every_eval, 1) if every_eval else None
    for i, cfg in enumerate(cfgs):
        res: dict[str, Any] = {
            "status": "ok" if alive[i] else "diverged",
            "error": errors[i],
            "step": end if alive[i] else last_good[i],
            "resumed_from": start or None,
            "compiles": compiles,
            "step_times": times,
            "metrics": {},
            "per_mesh": {},
        }
        if alive[i] and end == t.steps and eval_sets:
            for split, examples in eval_sets.items():
                if not examples:
                    continue
                batches = evaluation_batches(
                    examples,
                    seed=cfg.train.seed + 12345 if eval_seed is None else eval_seed,
                    noise=cfg.noise,
                    rotate=t.rotate,
                    encoding=cfg.model.encoding,
                    sizes=eval_sizes,
                )
                rows = evaluate_per_mesh(eval_trainer(cfg), params[i], batches)
                for k in rows[0]:
                    vals = [float(r[k]) for r in rows]
                    res["per_mesh"][f"{split}/{k}"] = vals
                    res["metrics"][f"{split}/{k}"] = float(np.mean(vals))
        results.append(res)
    return results
