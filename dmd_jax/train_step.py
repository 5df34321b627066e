"""The train step: the schemes, the optimizer, the loss terms, the step programs.

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

`shared_train_step` is the same step with the loss weights, dropout rate and phase
traced, so that the rows of a sweep share one program (`step_program_key`;
`experiments.multiseed` runs several seeds of it as one program). The loop that runs
these steps, evaluates and checkpoints is `dmd_jax.train`, which re-exports every name
defined here.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from dmd_jax import geometry, losses, parallel
from dmd_jax.config import SCHEMES, ExperimentConfig, LossConfig, ModelConfig
from dmd_jax.encoding import LocalInputs
from dmd_jax.graph import MeshGraph
from dmd_jax.model import DMDNet

FE_PREFIX = "feature_extractor"
# Which param halves a phase trains.
PHASE_PARTS = {"all": ("fe", "rest"), "fe": ("fe",), "rest": ("rest",)}


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
    local: LocalInputs | None = None,
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
      local: the `"local"` encoding's inputs of `noisy` on `graph`, computed beforehand
        (`encoding.LocalInputs`; the candidate pool's), or None: the model computes them.
        Only the first pass uses them; later passes start from another mesh.
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
            local=local if k == 0 else None,
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
      `step(state, noisy, clean, graph, rng, local=None) -> (state, metrics)`: `noisy`,
      `clean` are `[n_group, n_vertex, 3]`, `graph` a `MeshGraph` of `[n_group, ...]`
      arrays and `local` None or the batch's precomputed `encoding.LocalInputs` (stacked
      groups, `pipeline.CandidatePool`),
      one group per device along the batch axis (`parallel.shard_batch`); `state` is
      replicated (`parallel.replicate`); `rng` is the step's dropout key. The new state
      and the metrics (`loss`, `grad_norm` and every term's mean) come back replicated.
    """
    model = DMDNet(cfg.model)
    tx = make_optimizer(cfg)
    loss = phase_loss(cfg, phase)
    use_dropout = cfg.model.dropout > 0
    axis = parallel.BATCH_AXIS

    def group_terms(index, params, noisy, clean, graph, rng, local):
        # One device's block: its group, with a leading axis of 1.
        noisy, clean, graph, local = jax.tree.map(lambda x: x[0], (noisy, clean, graph, local))
        group_rng = jax.random.fold_in(rng, index) if use_dropout else None
        return loss_terms(
            model, cfg, params, noisy, clean, graph, loss=loss, rng=group_rng, local=local
        )

    batch_terms = parallel.sum_over_groups(
        group_terms, mesh, in_specs=(P(), P(axis), P(axis), P(axis), P(), P(axis))
    )

    def step(state: TrainState, noisy, clean, graph, rng, local=None):
        def loss_of(halves):
            terms = batch_terms(merge_params(halves), noisy, clean, graph, rng, local)
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
