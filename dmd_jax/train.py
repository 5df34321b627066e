"""Training: one step builder for one device or many, the schemes, evaluation, the loop.

Schemes (paper appendix D):

* ``joint``: every loss, every parameter, every step.
* ``alter``: odd steps train the feature extractor on the FE loss alone; even steps train
  the rest of the network on the other losses, the feature extractor frozen.
* ``two_phase``: the first ``two_phase_fe_steps`` steps train the feature extractor alone,
  the rest train the rest of the network with the feature extractor frozen.
* ``u_fe``: the FE loss is off; the feature extractor learns only through the denoiser.

The feature extractor and the rest of the network have separate Adam states, so freezing
one half really freezes it (no momentum drift). Each (bucket, phase) compiles once.

One engine: `make_train_step` builds the step of a phase for a device mesh
(`parallel.batch_mesh`). A batch is one group of meshes per device, stacked on a leading
axis (`pipeline.training_batch`); `parallel.sum_over_groups` (a `jax.shard_map` on
several devices) gives every device its group, the groups' loss terms (`losses.Term`:
sums and counts) are added across devices, and `losses.reduce_terms` divides once, so k
steps on n devices are k steps on the whole batch, up to the order of float sums.
Training on one device is the same code on a one-device mesh, with a batch of one group.

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

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from dmd_jax import geometry, losses, metrics, parallel
from dmd_jax.checkpoints import (
    check_params,
    checkpoint_managers,
    graft_params,
    load_model,
    restore_checkpoint,
    save_checkpoint,
)
from dmd_jax.config import SCHEMES, ExperimentConfig, LossConfig, ModelConfig, NoiseConfig
from dmd_jax.graph import MeshGraph
from dmd_jax.io import write_text_atomic
from dmd_jax.model import DMDNet
from dmd_jax.model import init_params as init_model_params
from dmd_jax.pipeline import (
    Batch,
    MeshExample,
    evaluation_batches,
    largest_sizes,
    make_examples,
    training_batch,
    unpadded_mesh,
)
from dmd_jax.protocol import benchmark_noise_config

FE_PREFIX = "feature_extractor"
# How `train` pads batches: each step to its own vertex bucket (a program per bucket it
# meets; the least padding, right for long runs), or every step to the largest batch
# the data can form (one program; right for short runs, where compiling, ~15 s of CPU a
# program for the `test` preset on 2 cores, costs more than the padding).
PAD_MODES = ("bucket", "largest")
# `train_and_evaluate(pad="auto")` pads every batch to one shape for runs of at most this
# many steps (the test preset's 40 compile once instead of 5-6 times on a tiny dataset).
AUTO_PAD_MAX_STEPS = 500
# Which param halves a phase trains.
PHASE_PARTS = {"all": ("fe", "rest"), "fe": ("fe",), "rest": ("rest",)}


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
    """Adam (β1, β2, ε from the config) with gradient clipping and the configured schedule."""
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
    chain = [optax.adam(lr, b1=t.b1, b2=t.b2, eps=t.eps)]
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


def phase_loss(cfg: ExperimentConfig, phase: str) -> LossConfig:
    """The loss of a phase of the configured scheme: `cfg.loss` with some weights at 0."""
    if phase == "fe" and cfg.train.scheme != "u_fe":
        # The paper's FE phases train the feature extractor on its own loss alone.
        off = ("vertex", "normal", "curvature", "chamfer", "face_normal")
        return cfg.loss.with_edits({name: 0.0 for name in off} | {"feature": 1.0})
    if cfg.train.scheme == "u_fe" or phase == "rest":
        return cfg.loss.with_edits({"feature": 0.0})
    return cfg.loss


def loss_terms(
    model: DMDNet,
    cfg: ExperimentConfig,
    params: dict,
    noisy,
    clean,
    graph: MeshGraph,
    *,
    loss: LossConfig,
    rng=None,
) -> dict[str, losses.Term]:
    """The loss terms (sums and counts) of one padded group of meshes.

    With `cfg.train.passes` above 1 the network runs that many times, each pass on the
    last one's output (gradient stopped there), and the terms of every pass are added:
    their means are the loss averaged over the passes.

    Args:
      model: `DMDNet(cfg.model)`.
      cfg: the experiment config (how feature targets are expressed, the passes).
      params: the model's params.
      noisy, clean: `[n_vertex, 3]` in the frame of the model's encoding.
      graph: the group's padded `MeshGraph`.
      loss: the weights of the phase (`phase_loss`).
      rng: dropout key, or None (deterministic).
    """
    deterministic = rng is None
    target_feats = None
    face_weight = None
    if loss.crease_weight != 1.0:
        crease = losses.crease_face_mask(
            clean, graph.faces, graph.face_senders, graph.face_receivers
        )
        face_weight = jnp.where(crease, loss.crease_weight, 1.0)
    total: dict[str, losses.Term] = {}
    x = noisy
    for k in range(cfg.train.passes):
        out, feats, aux = model.apply(
            {"params": params},
            x,
            graph,
            deterministic=deterministic,
            rngs=None
            if deterministic
            else {"dropout": rng if k == 0 else jax.random.fold_in(rng, k)},
        )
        if feats is not None and target_feats is None:
            target_feats = geometry.vertex_features(clean, graph.faces)
            if cfg.loss.feature_curvature == "asinh":
                target_feats = target_feats.at[:, 3:].set(jnp.arcsinh(target_feats[:, 3:]))
        terms = losses.loss_terms(
            out,
            clean,
            graph.faces,
            pred_features=feats,
            target_features=target_feats,
            weights=loss,
            # The normal-first head's own prediction, before its vertex update.
            pred_face_normals=aux.get("face_normals"),
            vertex_mask=graph.vertex_mask,
            face_mask=graph.face_mask,
            face_weight=face_weight,
            vertex_graph=graph.vertex_graph,
            n_graph=graph.n_graph,
        )
        total = terms if not total else jax.tree.map(jnp.add, total, terms)
        # The next pass learns to denoise this output as given: no gradient flows back
        # through it (a cascade of one shared network, as `denoise` runs it).
        x = jax.lax.stop_gradient(out)
    return total


def make_train_step(cfg: ExperimentConfig, phase: str, mesh: Mesh) -> Callable:
    """The jitted train step of one phase on a device mesh (a pure function of its inputs).

    Args:
      cfg: the experiment config.
      phase: `"all"`, `"fe"` or `"rest"` (`phase_of`).
      mesh: a one-axis device mesh (`parallel.batch_mesh`); one device is a mesh too.

    Returns:
      `step(state, noisy, clean, graph, rng) -> (state, metrics)`: `noisy`, `clean` are
      `[n_group, n_vertex, 3]` and `graph` a `MeshGraph` of `[n_group, ...]` arrays,
      one group per device along the batch axis (`parallel.shard_batch`); `state` is
      replicated (`parallel.replicate`); `rng` is the step's dropout key. The new state
      and the metrics (`loss`, `grad_norm` and every term's mean) come back replicated.
    """
    model = DMDNet(cfg.model)
    tx = make_optimizer(cfg)
    loss = phase_loss(cfg, phase)
    use_dropout = cfg.model.dropout > 0
    axis = parallel.BATCH_AXIS

    def group_terms(index, params, noisy, clean, graph, rng):
        # One device's block: its group, with a leading axis of 1.
        noisy, clean, graph = jax.tree.map(lambda x: x[0], (noisy, clean, graph))
        group_rng = jax.random.fold_in(rng, index) if use_dropout else None
        return loss_terms(model, cfg, params, noisy, clean, graph, loss=loss, rng=group_rng)

    batch_terms = parallel.sum_over_groups(
        group_terms, mesh, in_specs=(P(), P(axis), P(axis), P(axis), P())
    )

    def step(state: TrainState, noisy, clean, graph, rng):
        def loss_of(halves):
            terms = batch_terms(merge_params(halves), noisy, clean, graph, rng)
            return losses.reduce_terms(terms, loss)

        (total, means), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params)
        new_params, new_opt = dict(state.params), dict(state.opt_state)
        for part in PHASE_PARTS[phase]:
            updates, new_opt[part] = tx.update(
                grads[part], state.opt_state[part], state.params[part]
            )
            new_params[part] = optax.apply_updates(state.params[part], updates)
        metrics_ = {"loss": total, "grad_norm": optax.tree.norm(grads), **means}
        return TrainState(state.step + 1, new_params, new_opt), metrics_

    replicated = NamedSharding(mesh, P())
    return jax.jit(step, out_shardings=(replicated, replicated))


# ------------------------------------------------------------ shared step programs
# Train settings the host reads, not the step: which phase runs at which step (scheme,
# alter_period, two_phase_split), the init / dropout key (seed, an input), the starting
# params (init_from), the batch's augmentation (rotate: `pipeline.training_batch` rotates
# on the host) and when to log, evaluate or checkpoint.
_HOST_TRAIN_FIELDS = (
    "seed",
    "scheme",
    "alter_period",
    "two_phase_split",
    "init_from",
    "rotate",
    "eval_every",
    "ckpt_every",
    "ckpt_keep",
    "log_every",
)
# Config sections only the host reads: the noise drawn into each batch, the dataset.
_HOST_SECTIONS = ("noise", "data")


def step_program_key(cfg: ExperimentConfig) -> str:
    """What the program of `shared_train_step(cfg, ...)` depends on.

    Configs with equal keys compile to one program (per padded shape): the key is the
    config as JSON without its name, seed, scheme switches and loss weights, with the
    dropout rate reduced to on/off; the weights, the phase and the rate reach the
    program as traced arguments (`step_values`). The program computes every loss term
    the model can give (`shared_terms`) and weights them by the traced values, so rows
    that only switch terms off, and every phase of a scheme, share it. What only the host
    reads (`_HOST_TRAIN_FIELDS`, `_HOST_SECTIONS`: the noise and rotation of the
    batches, logging and checkpoint intervals) is left out; everything else (model,
    optimiser, loss settings, schedule) stays in the key, so a setting added later
    separates programs until it is known not to matter.
    """
    d = cfg.to_dict()
    d.pop("name", None)
    for section in _HOST_SECTIONS:
        d.pop(section, None)
    for name in _HOST_TRAIN_FIELDS:
        d["train"].pop(name, None)
    for name in losses.TERMS:
        d["loss"].pop(name, None)
    d["model"]["dropout"] = bool(cfg.model.dropout > 0)
    return json.dumps(d, sort_keys=True)


def shared_terms(cfg: ExperimentConfig) -> tuple[str, ...]:
    """The loss terms a `shared_train_step` program computes: every term of
    `losses.TERMS` the model gives inputs for (the feature term needs a feature
    extractor, the face-normal term a normal-first head), whatever their weights."""
    return tuple(
        name
        for name in losses.TERMS
        if (name != "feature" or cfg.model.uses_feature_extractor)
        and (name != "face_normal" or cfg.model.head == "normal")
    )


def step_values(cfg: ExperimentConfig, phase: str) -> dict[str, Any]:
    """The traced arguments of a `shared_train_step` program for one config and phase.

    Returns:
      `{"weights": {term: float32 []}` (the phase's weight of every term of
      `shared_terms`, 0 where the phase has it off),
      `"train": {"fe": bool [], "rest": bool []}` (the param halves the phase updates),
      `"keep_prob": float64 []}` (`1 - dropout`, at JAX's default float width once
      traced; unused when dropout is off).
    """
    loss = phase_loss(cfg, phase)
    weights = {n: np.float32(getattr(loss, n)) for n in shared_terms(cfg)}
    return {
        "weights": weights,
        "train": {part: np.bool_(part in PHASE_PARTS[phase]) for part in ("fe", "rest")},
        # A float64 scalar, which JAX takes at its default float width: flax's static
        # `1.0 - rate` is a Python float and draws its Bernoulli mask at that width.
        "keep_prob": np.float64(1.0 - cfg.model.dropout),
    }


def _dropout_at(keep_prob) -> Callable:
    """A flax method interceptor: every active `nn.Dropout` keeps `keep_prob` (traced).

    `nn.Dropout` reads its rate as a Python number (`rate == 0.0` decides whether it
    runs), so a traced rate cannot go through the module; this replays its `__call__`
    (same key, same Bernoulli draw) with the traced keep probability. The scale is
    `x * (1 / keep)`, the form XLA rewrites flax's `x / keep` constant into, so the
    result is the per-config program's bit for bit on CPU (`tests/test_ablations.py`).
    """

    def interceptor(next_fun, args, kwargs, context):
        module = context.module
        if not isinstance(module, nn.Dropout) or context.method_name != "__call__":
            return next_fun(*args, **kwargs)
        inputs = args[0]
        deterministic = kwargs.get("deterministic", args[1] if len(args) > 1 else None)
        deterministic = nn.merge_param("deterministic", module.deterministic, deterministic)
        if module.rate == 0.0 or deterministic:  # static: this config has no dropout
            return next_fun(*args, **kwargs)
        rng = kwargs.get("rng", args[2] if len(args) > 2 else None)
        if rng is None:
            rng = module.make_rng(module.rng_collection)
        shape = list(inputs.shape)
        for dim in module.broadcast_dims:
            shape[dim] = 1
        mask = jnp.broadcast_to(jax.random.bernoulli(rng, p=keep_prob, shape=shape), inputs.shape)
        keep = jnp.asarray(keep_prob, inputs.dtype)
        return jax.lax.select(mask, inputs * (1 / keep), jnp.zeros_like(inputs))

    return interceptor


def shared_train_step(cfg: ExperimentConfig, mesh: Mesh) -> Callable:
    """`make_train_step`'s step with the loss weights, dropout rate and phase traced.

    One program serves every config of one `step_program_key`: in an ablation sweep
    the rows that differ only in loss weights (a term switched off included), dropout
    rate or training scheme share it, every phase included
    (`experiments.multiseed.seeds_step` keeps one per key). It computes what the
    config's own `make_train_step` computes, up to the order of float operations: every
    term of `shared_terms`, those of weight 0 selected out of the loss (their values
    still come back in the metrics), and the phase's frozen half kept by a select
    instead of being left out of the update. Computing a term that is off costs its
    share of a step's run time, which in a short sweep is far less than the compile it
    saves.

    Args:
      cfg: any config of the key; only its static settings are read (the phase's
        weights and halves come traced, `step_values`).
      mesh: a one-axis device mesh (`parallel.batch_mesh`).

    Returns:
      `step(state, noisy, clean, graph, rng, values) -> (state, metrics)`, not jitted:
      the arguments of `make_train_step`'s step plus `values` (`step_values`).
    """
    model = DMDNet(cfg.model)
    tx = make_optimizer(cfg)
    # Every term the model gives is computed; its weight (0 when off) comes traced.
    loss = cfg.loss.with_edits({name: float(name in shared_terms(cfg)) for name in losses.TERMS})
    use_dropout = cfg.model.dropout > 0
    axis = parallel.BATCH_AXIS

    def group_terms(index, params, noisy, clean, graph, rng, keep_prob):
        noisy, clean, graph = jax.tree.map(lambda x: x[0], (noisy, clean, graph))
        group_rng = jax.random.fold_in(rng, index) if use_dropout else None
        with nn.intercept_methods(_dropout_at(keep_prob)):
            return loss_terms(model, cfg, params, noisy, clean, graph, loss=loss, rng=group_rng)

    batch_terms = parallel.sum_over_groups(
        group_terms, mesh, in_specs=(P(), P(axis), P(axis), P(axis), P(), P())
    )

    def step(state: TrainState, noisy, clean, graph, rng, values):
        def loss_of(halves):
            terms = batch_terms(merge_params(halves), noisy, clean, graph, rng, values["keep_prob"])
            # `losses.reduce_terms` with traced weights, in its order.
            means = {name: term.mean() for name, term in terms.items()}
            dtype = next(iter(means.values())).dtype if means else jnp.float32
            w = values["weights"]
            # A select, not 0 * m: an off term's non-finite value must not reach the loss.
            total = sum(
                (
                    jnp.where(w[name] > 0, w[name].astype(m.dtype) * m, 0.0)
                    for name, m in means.items()
                ),
                jnp.zeros((), dtype),
            )
            return total, means

        (total, means), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params)
        new_params, new_opt = {}, {}
        for part in ("fe", "rest"):
            updates, opt = tx.update(grads[part], state.opt_state[part], state.params[part])
            params = optax.apply_updates(state.params[part], updates)
            # A frozen half keeps its params and Adam state exactly (a select, no drift).
            on = values["train"][part]
            new_params[part] = jax.tree.map(
                lambda a, b, on=on: jnp.where(on, a, b), params, state.params[part]
            )
            new_opt[part] = jax.tree.map(
                lambda a, b, on=on: jnp.where(on, a, b), opt, state.opt_state[part]
            )
        metrics_ = {"loss": total, "grad_norm": optax.tree.norm(grads), **means}
        return TrainState(state.step + 1, new_params, new_opt), metrics_

    return step


# Jitted model inits, one per model config of the process (the dropout rate left out:
# init runs the model deterministic, so the rate changes no parameter), so that the
# trainers of a sweep's rows share one compiled init instead of one each.
_INIT_PROGRAMS: dict[str, Callable] = {}


def _init_program(model_cfg: ModelConfig) -> Callable:
    model_cfg = model_cfg.with_edits({"dropout": 0.0})
    key = json.dumps(model_cfg.to_dict(), sort_keys=True)
    if key not in _INIT_PROGRAMS:
        model = DMDNet(model_cfg)
        _INIT_PROGRAMS[key] = jax.jit(lambda rngs, x, g: model.init(rngs, x, g, deterministic=True))
    return _INIT_PROGRAMS[key]


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
        return self.step_fn(step)(state, placed.noisy, placed.clean, placed.graph, rng)

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
        and one evaluation program); `PAD_MODES`.
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
    train_sizes = eval_sizes = None
    if pad_to == "largest":
        train_sizes = largest_sizes(train_examples, -(-t.batch_size // mesh.size))
        every_eval = [ex for exs in (eval_sets or {}).values() for ex in exs]
        eval_sizes = largest_sizes(every_eval, 1) if every_eval else None

    def make_batch(step: int) -> Batch:
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
            sizes=train_sizes,
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

    with open(log_path if primary else os.devnull, "a") as log:
        if log.tell():
            with open(log_path, "rb") as fh:
                fh.seek(-1, 2)
                if fh.read(1) != b"\n":
                    log.write("\n")  # a killed run's cut-off row must not swallow the next
        for step in range(start, end):
            batch = make_batch(step)
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
            if (t.ckpt_every and done % t.ckpt_every == 0) or done == end:
                log.flush()
                save_checkpoint(latest, state, cfg)
            if done == end:
                break  # a hook stopped the run (or this was the last step)
    bar.close()
    if primary:
        _plot_curves(log_path, workdir / "loss_curve.png")
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
        than the padding, else `"bucket"`.
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
        pad = "largest" if cfg.train.steps <= AUTO_PAD_MAX_STEPS else "bucket"
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
