"""Training: the jitted train step, the paper's training schemes, evaluation, checkpoints.

Schemes (paper appendix D):

* ``joint``: every loss, every parameter, every step.
* ``alter``: odd steps train the feature extractor on the FE loss alone; even steps train
  the rest of the network on the other losses, the feature extractor frozen.
* ``two_phase``: the first ``two_phase_fe_steps`` steps train the feature extractor alone,
  the rest train the rest of the network with the feature extractor frozen.
* ``u_fe``: the FE loss is off; the feature extractor learns only through the denoiser.

The feature extractor and the rest of the network have separate Adam states, so freezing
one half really freezes it (no momentum drift). Each (bucket, phase) compiles once.

Checkpoints are Orbax: ``<workdir>/checkpoints/latest`` keeps the last ``ckpt_keep``
states and ``<workdir>/checkpoints/best`` the one with the lowest test-intra normal error.
A run restarted in the same workdir resumes from the latest state; since batches are a
function of ``(seed, step)``, the resumed run is bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dmd_jax import geometry, losses, metrics
from dmd_jax.config import ExperimentConfig
from dmd_jax.graph import MeshGraph
from dmd_jax.io import atomic_write
from dmd_jax.model import DMDNet
from dmd_jax.pipeline import (
    Batch,
    MeshExample,
    NoiseSettings,
    evaluation_batches,
    training_batch,
)

FE_PREFIX = "feature_extractor"
SCHEMES = ("joint", "alter", "two_phase", "u_fe")


class NonFiniteLossError(RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


class TrainState(NamedTuple):
    step: Any  # int32 scalar array
    params: Any  # {'fe': ..., 'rest': ...}
    opt_state: Any  # {'fe': ..., 'rest': ...}


def split_params(params: dict) -> dict:
    """`{'fe': feature-extractor params, 'rest': everything else}` (both may be empty)."""
    fe = {k: v for k, v in params.items() if k.startswith(FE_PREFIX)}
    rest = {k: v for k, v in params.items() if not k.startswith(FE_PREFIX)}
    return {"fe": fe, "rest": rest}


def merge_params(halves: dict) -> dict:
    return {**halves["fe"], **halves["rest"]}


def make_optimizer(cfg: ExperimentConfig) -> optax.GradientTransformation:
    """Adam (β1, β2 from the config) with gradient clipping and the configured schedule."""
    t = cfg.train
    if t.schedule == "constant":
        lr = t.learning_rate
    elif t.schedule == "cosine":
        lr = optax.warmup_cosine_decay_schedule(
            0.0,
            t.learning_rate,
            max(t.warmup_steps, 1),
            max(t.steps, t.warmup_steps + 1),
            end_value=t.learning_rate * t.min_lr_ratio,
        )
    else:
        raise ValueError(f"unknown schedule {t.schedule!r}; use 'constant' or 'cosine'")
    chain = [optax.adam(lr, b1=t.b1, b2=t.b2)]
    if t.grad_clip and t.grad_clip > 0:
        chain.insert(0, optax.clip_by_global_norm(t.grad_clip))
    return optax.chain(*chain)


def phase_of(scheme: str, step: int, two_phase_fe_steps: int, alter_period: int = 1) -> str:
    """Which part trains at `step`: 'all', 'fe' (feature extractor) or 'rest'."""
    if scheme in ("joint", "u_fe"):
        return "all"
    if scheme == "alter":
        # The paper counts iterations from 1: odd iterations (our even steps) train the FE.
        return "fe" if (step // alter_period) % 2 == 0 else "rest"
    if scheme == "two_phase":
        return "fe" if step < two_phase_fe_steps else "rest"
    raise ValueError(f"unknown training scheme {scheme!r}; use one of {SCHEMES}")


def loss_weights_for(cfg: ExperimentConfig, phase: str) -> losses.LossWeights:
    """The loss weights of a phase of the configured scheme."""
    w = cfg.loss.weights()
    if cfg.train.scheme == "u_fe":
        return w._replace(feature=0.0)
    if phase == "fe":
        # The paper's FE phases train the feature extractor on its own loss alone.
        return losses.LossWeights(vertex=0.0, normal=0.0, curvature=0.0, chamfer=0.0, feature=1.0)
    if phase == "rest":
        return w._replace(feature=0.0)
    return w


def compute_loss(
    model: DMDNet,
    cfg: ExperimentConfig,
    params: dict,
    noisy,
    clean,
    graph: MeshGraph,
    *,
    weights: losses.LossWeights,
    rng=None,
):
    """Total loss and its components for one padded batch (all in canonical frames)."""
    deterministic = rng is None
    out, feats, aux = model.apply(
        {"params": params},
        noisy,
        graph,
        deterministic=deterministic,
        rngs=None if deterministic else {"dropout": rng},
    )
    target_feats = None
    if feats is not None:
        target_feats = geometry.vertex_features(clean, graph.faces)
        if cfg.loss.feature_curvature == "asinh":
            target_feats = target_feats.at[:, 3:].set(jnp.arcsinh(target_feats[:, 3:]))
    total, parts = losses.total_loss(
        out,
        clean,
        graph.faces,
        pred_features=feats,
        target_features=target_feats,
        weights=weights,
        gamma_h=cfg.loss.gamma_h,
        gamma_g=cfg.loss.gamma_g,
        vertex_mask=graph.vertex_mask,
        face_mask=graph.face_mask,
        vertex_graph=graph.vertex_graph,
        n_graph=graph.n_graph,
        chamfer_block=cfg.loss.chamfer_block,
    )
    if cfg.loss.face_normal and "face_normals" in aux and weights.vertex + weights.normal > 0:
        # The normal-first head's own prediction, before the vertex update.
        term = losses.predicted_normal_loss(
            aux["face_normals"], clean, graph.faces, face_mask=graph.face_mask
        )
        parts = {**parts, "face_normal": term}
        total = total + cfg.loss.face_normal * term
    return total, parts


class Trainer:
    """Owns the model, optimizer and jitted step of one experiment."""

    def __init__(self, cfg: ExperimentConfig):
        if cfg.train.scheme not in SCHEMES:
            raise ValueError(f"unknown training scheme {cfg.train.scheme!r}; use one of {SCHEMES}")
        self.cfg = cfg
        self.model = DMDNet(cfg.model)
        self.tx = make_optimizer(cfg)
        self.compiles = 0
        self._step_fns: dict[str, Callable] = {}
        self._eval_fn = jax.jit(self._predict)

    # ---------------------------------------------------------------- init
    def init(self, example: Batch) -> TrainState:
        key = jax.random.PRNGKey(self.cfg.train.seed)
        variables = self.model.init(
            {"params": key, "dropout": key},
            jnp.asarray(example.noisy),
            jax.tree.map(jnp.asarray, example.graph),
            deterministic=True,
        )
        halves = split_params(variables["params"])
        opt_state = {k: self.tx.init(v) for k, v in halves.items()}
        return TrainState(step=jnp.asarray(0, jnp.int32), params=halves, opt_state=opt_state)

    # ---------------------------------------------------------------- step
    def _make_step(self, phase: str) -> Callable:
        weights = loss_weights_for(self.cfg, phase)
        use_dropout = self.cfg.model.dropout > 0

        def step_fn(state: TrainState, noisy, clean, graph, rng):
            self.compiles += 1  # runs at trace time only: counts compilations

            def loss_of(halves):
                return compute_loss(
                    self.model,
                    self.cfg,
                    merge_params(halves),
                    noisy,
                    clean,
                    graph,
                    weights=weights,
                    rng=rng if use_dropout else None,
                )

            (loss, parts), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params)
            new_params, new_opt = dict(state.params), dict(state.opt_state)
            trained = {"all": ("fe", "rest"), "fe": ("fe",), "rest": ("rest",)}[phase]
            for part in trained:
                updates, new_opt[part] = self.tx.update(
                    grads[part], state.opt_state[part], state.params[part]
                )
                new_params[part] = optax.apply_updates(state.params[part], updates)
            grad_norm = optax.global_norm(grads)
            return (
                TrainState(state.step + 1, new_params, new_opt),
                {"loss": loss, "grad_norm": grad_norm, **parts},
            )

        return jax.jit(step_fn)

    def step_fn(self, step: int) -> Callable:
        t = self.cfg.train
        phase = phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)
        if phase not in self._step_fns:
            self._step_fns[phase] = self._make_step(phase)
        return self._step_fns[phase]

    def train_step(self, state: TrainState, batch: Batch) -> tuple[TrainState, dict]:
        step = int(state.step)
        rng = jax.random.fold_in(jax.random.PRNGKey(self.cfg.train.seed + 1), step)
        return self.step_fn(step)(
            state,
            jnp.asarray(batch.noisy),
            jnp.asarray(batch.clean),
            jax.tree.map(jnp.asarray, batch.graph),
            rng,
        )

    # ---------------------------------------------------------------- eval
    def _predict(self, params, noisy, graph):
        out, feats, _ = self.model.apply({"params": params}, noisy, graph, deterministic=True)
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
            n = int(batch.graph.n_vertex_per_graph[0])
            nf = int(batch.graph.n_face_per_graph[0])
            faces = np.asarray(batch.graph.faces[:nf])
            clean = np.asarray(batch.clean[:n], np.float64)
            pred = np.asarray(out[:n], np.float64)
            noisy = np.asarray(batch.noisy[:n], np.float64)
            m = metrics.mesh_metrics(pred, clean, faces)
            r = metrics.mesh_metrics(noisy, clean, faces)
            rows.append(
                {
                    **{k: float(v) for k, v in m.items()},
                    **{f"noisy_{k}": float(v) for k, v in r.items()},
                }
            )
        if not rows:
            return {}
        return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


# -------------------------------------------------------------------- checkpoints


def _checkpointers(workdir: Path, keep: int):
    import orbax.checkpoint as ocp

    latest = ocp.CheckpointManager(
        (workdir / "checkpoints" / "latest").absolute(),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=True, enable_async_checkpointing=False
        ),
    )
    best = ocp.CheckpointManager(
        (workdir / "checkpoints" / "best").absolute(),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=1,
            create=True,
            best_fn=lambda m: m["normal_deg"],
            best_mode="min",
            enable_async_checkpointing=False,
        ),
    )
    return latest, best


def save_checkpoint(
    manager, state: TrainState, cfg: ExperimentConfig, metrics_: dict | None = None
):
    import orbax.checkpoint as ocp

    manager.save(
        int(state.step),
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(jax.device_get(state._asdict())),
            config=ocp.args.JsonSave(cfg.to_dict()),
        ),
        metrics=metrics_,
    )
    manager.wait_until_finished()


def restore_checkpoint(manager, template: TrainState, step: int | None = None) -> TrainState:
    import orbax.checkpoint as ocp

    step = manager.latest_step() if step is None else step
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, jax.device_get(template._asdict()))
    restored = manager.restore(
        step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))
    )
    return TrainState(**restored["state"])


def load_params(checkpoint_dir) -> tuple[dict, ExperimentConfig]:
    """Params and config of the newest checkpoint in an Orbax manager directory."""
    import orbax.checkpoint as ocp

    checkpoint_dir = Path(checkpoint_dir).absolute()
    if not checkpoint_dir.is_dir():
        raise FileNotFoundError(f"{checkpoint_dir}: no such checkpoint directory")
    manager = ocp.CheckpointManager(checkpoint_dir)
    step = manager.latest_step()
    if step is None:
        raise ValueError(f"{checkpoint_dir}: holds no checkpoint")
    try:
        cfg_dict = manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        cfg = ExperimentConfig.from_dict(cfg_dict["config"])
        state = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))
    except FileNotFoundError:
        raise
    except Exception as exc:  # orbax raises assorted types on corrupt directories
        message = " ".join(str(exc).split())[:300]
        raise ValueError(
            f"{checkpoint_dir}: unreadable checkpoint of step {step} "
            f"({type(exc).__name__}: {message})"
        ) from exc
    return merge_params(state["state"]["params"]), cfg


# -------------------------------------------------------------------- loop


def _plot_curves(log_path: Path, png_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # A killed run can leave a cut-off last line, and its resumed run logs the steps after
    # the last checkpoint again: skip unreadable lines, keep the latest row of each step.
    train_rows, eval_rows = {}, {}
    for line in log_path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if row.get("kind") == "train":
            train_rows[row["step"]] = row["loss"]
        elif row.get("kind") == "eval" and "test_intra/normal_deg" in row:
            eval_rows[row["step"]] = row["test_intra/normal_deg"]
    steps, loss = sorted(train_rows), [train_rows[s] for s in sorted(train_rows)]
    ev_steps, ev = sorted(eval_rows), [eval_rows[s] for s in sorted(eval_rows)]
    if not steps:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(steps, loss, lw=0.6, alpha=0.5, label="loss")
    if len(loss) >= 20:
        w = max(len(loss) // 50, 5)
        ax[0].plot(steps[w - 1 :], np.convolve(loss, np.ones(w) / w, "valid"), label=f"mean of {w}")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("step")
    ax[0].legend()
    ax[0].set_title("training loss")
    if ev:
        ax[1].plot(ev_steps, ev, "o-")
    ax[1].set_xlabel("step")
    ax[1].set_title("test-intra normal error (deg)")
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)


class _Steps(NamedTuple):
    """How `train` runs a step: on one device, or data-parallel (chosen once per run)."""

    trainer: Any  # `Trainer` or `parallel.ParallelTrainer`: `train_step`, `compiles`
    base: Trainer  # init and evaluation
    first: Batch  # a batch for `base.init`
    run: Callable  # (state, step, nan) -> (state, metrics): builds the batch, steps
    place: Callable  # state on the host or one device -> state as `run` takes it
    local: Callable  # params of a placed state -> params for `base.evaluate`


def _nan_batch(batch: Batch) -> Batch:
    return batch._replace(noisy=np.full_like(batch.noisy, np.nan))


def _single_device_steps(cfg: ExperimentConfig, examples, noise: NoiseSettings) -> _Steps:
    t = cfg.train
    trainer = Trainer(cfg)

    def make_batch(step: int) -> Batch:
        return training_batch(
            examples,
            step,
            batch_size=t.batch_size,
            seed=t.seed,
            noise=noise,
            rotate=t.rotate,
            encoding=cfg.model.encoding,
        )

    def run(state: TrainState, step: int, nan: bool):
        batch = make_batch(step)
        return trainer.train_step(state, _nan_batch(batch) if nan else batch)

    def same(x):
        return x

    return _Steps(trainer, trainer, make_batch(0), run, same, same)


def _data_parallel_steps(cfg: ExperimentConfig, examples, noise: NoiseSettings) -> _Steps:
    """Steps of `parallel.ParallelTrainer` over every device of every process."""
    from dmd_jax import parallel

    t = cfg.train
    mesh = parallel.batch_mesh()
    if t.batch_size < mesh.size:
        raise ValueError(
            f"data-parallel training needs at least one mesh per device: train.batch_size "
            f"is {t.batch_size} but there are {mesh.size} devices; set train.batch_size "
            f">= {mesh.size} or run on fewer devices"
        )
    trainer = parallel.ParallelTrainer(cfg, mesh)
    mine = parallel.local_groups(mesh)

    def make_groups(step: int) -> dict[int, Batch]:
        return parallel.device_batches(
            examples,
            step,
            n_group=mesh.size,
            batch_size=t.batch_size,
            seed=t.seed,
            noise=noise,
            rotate=t.rotate,
            groups=mine,
            encoding=cfg.model.encoding,
        )

    def run(state: TrainState, step: int, nan: bool):
        groups = make_groups(step)
        if nan:
            groups = {i: _nan_batch(b) for i, b in groups.items()}
        return trainer.train_step(state, parallel.shard_batch(mesh, groups))

    def place(state: TrainState) -> TrainState:
        return parallel.replicate(mesh, state)

    def local(params: dict) -> dict:
        # The copy on this process's first device: evaluation needs no other device.
        return jax.tree.map(lambda x: x.addressable_data(0), params)

    return _Steps(trainer, trainer.base, make_groups(0)[mine[0]], run, place, local)


def train(
    cfg: ExperimentConfig,
    train_examples: Sequence[MeshExample],
    workdir,
    *,
    eval_sets: dict[str, Sequence[MeshExample]] | None = None,
    progress: bool = True,
    stop_after: int | None = None,
    inject_nan_at: int | None = None,
    init_params: dict | None = None,
    data_parallel: bool = False,
    eval_noise: NoiseSettings | None = None,
) -> dict:
    """Trains (or resumes) a run in `workdir`; returns the final evaluation.

    Args:
      cfg: the experiment config (model, loss, train, noise).
      train_examples: training meshes (clean, canonical), graphs prebuilt.
      workdir: where checkpoints, `log.jsonl`, `config.json` and `loss_curve.png` go.
      eval_sets: e.g. `{"test_intra": [...], "test_inter": [...]}`.
      progress: show a tqdm bar.
      stop_after: stop (as if killed) after this many steps of this call (for tests).
      inject_nan_at: replace the batch of this step with NaNs (fault-injection tests).
      init_params: start from these params (fine-tuning) instead of a fresh init; the
        optimizer starts fresh. Ignored when the workdir already holds a checkpoint.
      eval_noise: the noise of the evaluation sets (default: the training noise).
        With an eval set named `val`, the best checkpoint is chosen on its normal
        error; otherwise on `test_intra`'s.
      data_parallel: split each step's global batch over every device of every process
        (`parallel.ParallelTrainer` on `parallel.batch_mesh()`); the same steps as on one
        device up to the order of float sums, dropout masks aside. With several
        processes (`jax.distributed.initialize` first) each builds only its own groups,
        only process 0 writes `config.json`, `log.jsonl` and the plot, and Orbax writes
        the checkpoints from process 0: `workdir` must be one shared directory.

    Raises:
      NonFiniteLossError: the loss became NaN/inf; the last good checkpoint is kept.
      ValueError: with `data_parallel`, a global batch smaller than the device count.
    """
    from tqdm.auto import tqdm

    t = cfg.train
    noise = (
        NoiseSettings(**cfg.noise.settings()) if hasattr(cfg.noise, "settings") else NoiseSettings()
    )
    steps = (_data_parallel_steps if data_parallel else _single_device_steps)(
        cfg, train_examples, noise
    )
    trainer = steps.trainer
    # Data-parallel processes share one workdir: only the first writes the run's files.
    primary = not data_parallel or jax.process_index() == 0
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    cfg_path = workdir / "config.json"
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text())
        if old != cfg.to_dict():
            raise ValueError(
                f"{workdir} holds a run with a different config; use another --workdir"
            )
    elif primary:
        text = json.dumps(cfg.to_dict(), indent=2)
        atomic_write(cfg_path, lambda tmp: Path(tmp).write_text(text))
    state = steps.base.init(steps.first)
    if init_params is not None:
        fresh = jax.tree_util.tree_structure(merge_params(state.params))
        if jax.tree_util.tree_structure(init_params) != fresh:
            raise ValueError("init_params do not match the model of this config")
        state = state._replace(params=split_params(jax.tree.map(jnp.asarray, init_params)))
    latest, best = _checkpointers(workdir, t.ckpt_keep)
    if latest.latest_step() is not None:
        state = restore_checkpoint(latest, state)
    state = steps.place(state)
    eval_batches = {
        name: evaluation_batches(
            ex,
            seed=t.seed + 12345,
            noise=noise if eval_noise is None else eval_noise,
            rotate=t.rotate,
            encoding=cfg.model.encoding,
        )
        for name, ex in (eval_sets or {}).items()
        if ex
    }
    log_path = workdir / "log.jsonl"
    start = int(state.step)
    end = t.steps if stop_after is None else min(t.steps, start + stop_after)
    bar = tqdm(total=t.steps, initial=start, disable=not progress, desc="train", unit="step")
    last_eval: dict = {}
    t0 = time.time()
    with open(log_path if primary else os.devnull, "a") as log:
        if log.tell():
            with open(log_path, "rb") as fh:
                fh.seek(-1, 2)
                if fh.read(1) != b"\n":
                    log.write("\n")  # a killed run's cut-off row must not swallow the next
        for step in range(start, end):
            new_state, out = steps.run(
                state, step, inject_nan_at is not None and step == inject_nan_at
            )
            loss = float(out["loss"])
            if not math.isfinite(loss):
                bar.close()
                raise NonFiniteLossError(
                    f"non-finite loss ({loss}) at step {step}; stopped. The last good "
                    f"checkpoint (step {latest.latest_step()}) is kept in {workdir}/checkpoints"
                )
            state = new_state
            row = {
                "kind": "train",
                "step": step + 1,
                "time": time.time() - t0,
                **{k: float(v) for k, v in out.items()},
            }
            log.write(json.dumps(row) + "\n")
            bar.set_postfix(loss=f"{loss:.4g}")
            bar.update(1)
            done = step + 1
            if eval_batches and ((t.eval_every and done % t.eval_every == 0) or done == t.steps):
                params = steps.local(merge_params(state.params))
                last_eval = {"kind": "eval", "step": done}
                for name, batches in eval_batches.items():
                    for k, v in steps.base.evaluate(params, batches).items():
                        last_eval[f"{name}/{k}"] = v
                log.write(json.dumps(last_eval) + "\n")
                log.flush()
                key = "val/normal_deg" if "val/normal_deg" in last_eval else "test_intra/normal_deg"
                if key in last_eval:
                    save_checkpoint(best, state, cfg, {"normal_deg": last_eval[key]})
            if (t.ckpt_every and done % t.ckpt_every == 0) or done == end:
                log.flush()
                save_checkpoint(latest, state, cfg)
    bar.close()
    if primary:
        _plot_curves(log_path, workdir / "loss_curve.png")
    return {"step": int(state.step), "compiles": trainer.compiles, **last_eval, "state": state}
