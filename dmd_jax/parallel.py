"""Data-parallel training over several devices, on one host or many, with `jax.sharding`.

The global batch of a step (the same meshes and noise as `pipeline.training_batch`) is
split into one group of meshes per device. Each group is a padded disjoint union, as
`pipeline.collate` builds it, but padded to sizes COMMON to all groups so the groups
stack into `[n_device, ...]` arrays. The stacked batch is sharded over a one-axis
device `Mesh` (`'batch'`) with `NamedSharding(mesh, P('batch'))`; params and optimizer
state are replicated. The step vmaps `train.compute_loss` over the device axis and
combines the groups' loss terms; XLA's SPMD partitioner gives every device its own
group and inserts the all-reduces of the loss and the gradients.

The groups' terms are combined with the weights the single-device loss gives them, not
averaged: the vertex, curvature and feature terms of `losses.total_loss` are means over
the valid vertices of the batch, the normal term over its valid faces, the chamfer term
over its meshes, so a group's term counts in proportion to its vertices (faces, meshes).
Then k steps on n devices equal k steps of `train.Trainer` on the same global batch up
to the order of floating-point sums, whatever the group sizes (`tests/test_parallel.py`
checks 2 CPU devices against 1). Dropout masks differ from single-device training (each
group draws its own).

Multi-host: call `jax.distributed.initialize(...)` first (README, "Multi-device and
multi-host training"); `jax.devices()` then lists every host's devices, the mesh spans
them, and every process builds only the groups of its own devices (`local_groups`). The
common sizes depend only on which meshes a step draws, not on the noise, so every
process computes them alike without building the other processes' groups.

`train.train(..., data_parallel=True)` (`dmd-jax train --data-parallel`) runs this step
inside the full training loop: checkpoints, resume, evaluation, log.

Usage::

    mesh = batch_mesh()                       # every device of every process
    trainer = ParallelTrainer(cfg, mesh)
    state = trainer.init(first_group)         # any one group (a `pipeline.Batch`)
    for step in range(cfg.train.steps):
        groups = device_batches(examples, step, n_group=mesh.size, ...)
        state, metrics = trainer.train_step(state, shard_batch(mesh, groups))
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from dmd_jax import losses, train
from dmd_jax.config import ExperimentConfig
from dmd_jax.graph import (
    MeshGraph,
    PaddedSizes,
    batch_mesh_graphs,
    pad_mesh_graph,
    pad_vertex_array,
)
from dmd_jax.pipeline import (
    Batch,
    MeshExample,
    NoiseSettings,
    batch_indices,
    corrupt,
    sizes_for_vertices,
    step_key,
)

BATCH_AXIS = "batch"


# --------------------------------------------------------------------------------------
# Device mesh and placement
# --------------------------------------------------------------------------------------


def batch_mesh(devices: Sequence | None = None) -> Mesh:
    """A one-axis device mesh `('batch',)` over `devices` (default: all, every process)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("batch_mesh needs at least one device")
    return Mesh(np.asarray(devices), (BATCH_AXIS,))


def _check_mesh(mesh: Mesh) -> None:
    if mesh.axis_names != (BATCH_AXIS,):
        raise ValueError(
            f"expected a one-axis mesh named ({BATCH_AXIS!r},), got axes {mesh.axis_names}"
        )


def local_groups(mesh: Mesh) -> list[int]:
    """Positions along the batch axis whose device belongs to this process.

    On one host that is every position; on several, each process builds (and
    `shard_batch` places) only these groups.
    """
    _check_mesh(mesh)
    me = jax.process_index()
    return [i for i, d in enumerate(mesh.devices.flat) if d.process_index == me]


def replicate(mesh: Mesh, tree):
    """Copies a pytree of arrays to every device of `mesh` (`NamedSharding(mesh, P())`).

    Every process must pass the same values (as `train.Trainer.init` gives them: the
    params depend only on the config's seed).
    """
    sharding = NamedSharding(mesh, P())

    def put(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree.map(put, jax.device_get(tree))


def shard_batch(mesh: Mesh, groups: Mapping[int, Batch]) -> Batch:
    """Stacks per-device groups into a global `Batch` of `[n_device, ...]` arrays.

    The arrays are sharded over the batch axis (`NamedSharding(mesh, P('batch'))`):
    group `i` lives on device `i` of the mesh, and nothing is copied to the others.

    Args:
      mesh: from `batch_mesh`.
      groups: position along the batch axis -> `Batch`, for exactly the positions of
        `local_groups(mesh)`, all padded to the same sizes (`device_batches` does both).

    Raises:
      ValueError: missing or extra groups, or groups of different shapes.
    """
    _check_mesh(mesh)
    mine = local_groups(mesh)
    if sorted(groups) != mine:
        raise ValueError(
            f"shard_batch needs the groups of this process's devices {mine}, got {sorted(groups)}"
        )
    shapes = {tuple(np.shape(x) for x in jax.tree.leaves(groups[i])) for i in mine}
    if len(shapes) != 1:
        raise ValueError("the groups must be padded to common sizes (see device_batches)")
    sharding = NamedSharding(mesh, P(BATCH_AXIS))
    devices = list(mesh.devices.flat)
    leaves = {i: jax.tree.leaves(groups[i]) for i in mine}
    treedef = jax.tree.structure(groups[mine[0]])
    out = []
    for k, first in enumerate(leaves[mine[0]]):
        shape = (mesh.size,) + np.shape(first)
        parts = [jax.device_put(np.asarray(leaves[i][k])[None], devices[i]) for i in mine]
        out.append(jax.make_array_from_single_device_arrays(shape, sharding, parts))
    return jax.tree.unflatten(treedef, out)


# --------------------------------------------------------------------------------------
# Per-device groups of a step
# --------------------------------------------------------------------------------------


def common_sizes(groups: Sequence[Sequence[MeshGraph]]) -> PaddedSizes:
    """Padded sizes that hold the disjoint union of every group (one vertex bucket).

    Args:
      groups: per device, the graphs of its meshes.
    """
    if not groups or any(len(g) == 0 for g in groups):
        raise ValueError("every device needs at least one mesh")

    def most(fn):
        return max(sum(fn(g) for g in group) for group in groups)

    return sizes_for_vertices(
        most(lambda g: g.n_vertex),
        most(lambda g: g.n_face),
        most(lambda g: g.vertex_senders.shape[0]),
        most(lambda g: g.face_senders.shape[0]),
        max(len(group) for group in groups),
    )


def collate_to(
    noisy: Sequence[np.ndarray],
    clean: Sequence[np.ndarray],
    graphs: Sequence[MeshGraph],
    sizes: PaddedSizes,
) -> Batch:
    """`pipeline.collate` with given padded sizes instead of the group's own bucket."""
    padded = pad_mesh_graph(batch_mesh_graphs(list(graphs)), sizes)
    return Batch(
        noisy=pad_vertex_array(np.concatenate(noisy).astype(np.float32), sizes.n_vertex),
        clean=pad_vertex_array(np.concatenate(clean).astype(np.float32), sizes.n_vertex),
        graph=padded,
    )


def split_slots(batch_size: int, n_group: int) -> list[np.ndarray]:
    """Slots `0..batch_size-1` of a global batch, cut into `n_group` contiguous groups
    whose sizes differ by at most one."""
    if n_group < 1 or batch_size < n_group:
        raise ValueError(
            f"a global batch of {batch_size} meshes cannot feed {n_group} devices "
            "(every device needs at least one mesh)"
        )
    return np.array_split(np.arange(batch_size), n_group)


def device_batches(
    examples: Sequence[MeshExample],
    step: int,
    *,
    n_group: int,
    batch_size: int,
    seed: int,
    noise: NoiseSettings,
    rotate: bool = True,
    groups: Sequence[int] | None = None,
    encoding: str = "xyz",
) -> dict[int, Batch]:
    """The global batch of `step`, as per-device groups padded to common sizes.

    Slot `j` of the global batch gets the mesh and noise it gets in
    `pipeline.training_batch(examples, step, batch_size=batch_size, seed=seed, ...)`,
    so the groups together are exactly that batch, split differently.

    Args:
      examples: the training meshes.
      step: the step number.
      n_group: devices along the batch axis (`mesh.size`).
      batch_size: the global batch size (at least `n_group`).
      seed, noise, rotate: as for `pipeline.training_batch`.
      groups: the groups to build (default all; pass `local_groups(mesh)` on several
        hosts). The padded sizes always account for every group.

    Returns:
      group index -> `Batch`.
    """
    idx = batch_indices(step, len(examples), batch_size, seed)
    slots = split_slots(batch_size, n_group)
    sizes = common_sizes([[examples[int(idx[j])].graph for j in s] for s in slots])
    key = step_key(seed, step)
    wanted = range(n_group) if groups is None else groups
    out = {}
    for g in wanted:
        noisy, clean, graphs = [], [], []
        for j in slots[g]:
            ex = examples[int(idx[j])]
            n, c, _ = corrupt(
                jax.random.fold_in(key, int(j)),
                ex.vertices,
                ex.faces,
                rotate=rotate,
                noise=noise,
                encoding=encoding,
            )
            noisy.append(n)
            clean.append(c)
            graphs.append(ex.graph)
        out[int(g)] = collate_to(noisy, clean, graphs, sizes)
    return out


# --------------------------------------------------------------------------------------
# The loss of a global batch
# --------------------------------------------------------------------------------------


def term_counts(clean, graph: MeshGraph) -> dict[str, jnp.ndarray]:
    """How many items each loss term of one group averages over (see module docstring).

    Returns:
      `{term: scalar}`: valid vertices (vertex, curvature, feature), valid faces with a
      non-degenerate target (normal), meshes with at least one valid vertex (chamfer).
    """
    n_vertex = jnp.sum(graph.vertex_mask)
    _, target_ok = losses.face_normal_angles(clean, clean, graph.faces)
    per_graph = jax.ops.segment_sum(
        graph.vertex_mask.astype(jnp.int32), graph.vertex_graph, num_segments=graph.n_graph
    )
    return {
        "vertex": n_vertex,
        "curvature": n_vertex,
        "feature": n_vertex,
        "normal": jnp.sum(graph.face_mask & target_ok),
        "chamfer": jnp.sum(per_graph > 0),
    }


def global_loss(
    model,
    cfg: ExperimentConfig,
    params: dict,
    noisy,
    clean,
    graph: MeshGraph,
    *,
    weights: losses.LossWeights,
    rngs=None,
):
    """The loss of the global batch from its stacked groups.

    Args:
      model, cfg, params: as for `train.compute_loss`.
      noisy, clean: `[n_group, n_vertex, 3]`.
      graph: a `MeshGraph` of `[n_group, ...]` arrays.
      weights: static loss weights.
      rngs: `[n_group]` dropout keys, or None (deterministic).

    Returns:
      `(total, terms)` as `train.compute_loss` returns them for the whole batch.
    """

    def one(n, c, g, r):
        _, parts = train.compute_loss(model, cfg, params, n, c, g, weights=weights, rng=r)
        counts = term_counts(c, g)
        return parts, {k: counts[k] for k in parts}

    parts, counts = jax.vmap(one)(noisy, clean, graph, rngs)
    terms = {}
    for name, values in parts.items():
        count = counts[name].astype(values.dtype)
        terms[name] = jnp.sum(count * values) / jnp.maximum(jnp.sum(count), 1.0)
    w = weights._asdict()
    dtype = next(iter(terms.values())).dtype if terms else jnp.float32
    total = sum((w[name] * value for name, value in terms.items()), jnp.zeros((), dtype))
    return total, terms


# --------------------------------------------------------------------------------------
# Trainer
# --------------------------------------------------------------------------------------


class ParallelTrainer:
    """`train.Trainer`'s step, data-parallel over the batch axis of a device mesh.

    Same optimizer (`train.make_optimizer`), param halves (`train.split_params`), schemes
    and phases (`train.phase_of`), and the same loss (`train.compute_loss`) on the whole
    global batch. `compiles` counts traces of the step, as `Trainer.compiles` does.
    """

    def __init__(self, cfg: ExperimentConfig, mesh: Mesh | None = None):
        self.mesh = batch_mesh() if mesh is None else mesh
        _check_mesh(self.mesh)
        self.base = train.Trainer(cfg)
        self.cfg = cfg
        self.model = self.base.model
        self.tx = self.base.tx
        self.compiles = 0
        self._step_fns: dict[str, Callable] = {}
        self.replicated = NamedSharding(self.mesh, P())

    def init(self, example: Batch) -> train.TrainState:
        """Initial state (as `Trainer.init` on any one group), replicated on the mesh."""
        return replicate(self.mesh, self.base.init(example))

    def _make_step(self, phase: str) -> Callable:
        cfg = self.cfg
        weights = train.loss_weights_for(cfg, phase)
        use_dropout = cfg.model.dropout > 0
        trained = {"all": ("fe", "rest"), "fe": ("fe",), "rest": ("rest",)}[phase]

        def step_fn(state: train.TrainState, noisy, clean, graph, rng):
            self.compiles += 1  # runs at trace time only: counts compilations
            rngs = jax.random.split(rng, noisy.shape[0]) if use_dropout else None

            def loss_of(halves):
                return global_loss(
                    self.model,
                    cfg,
                    train.merge_params(halves),
                    noisy,
                    clean,
                    graph,
                    weights=weights,
                    rngs=rngs,
                )

            (loss, parts), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params)
            new_params, new_opt = dict(state.params), dict(state.opt_state)
            for part in trained:
                updates, new_opt[part] = self.tx.update(
                    grads[part], state.opt_state[part], state.params[part]
                )
                new_params[part] = optax.apply_updates(state.params[part], updates)
            metrics = {"loss": loss, "grad_norm": optax.global_norm(grads), **parts}
            return train.TrainState(state.step + 1, new_params, new_opt), metrics

        return jax.jit(step_fn, out_shardings=(self.replicated, self.replicated))

    def step_fn(self, step: int) -> Callable:
        t = self.cfg.train
        phase = train.phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)
        if phase not in self._step_fns:
            self._step_fns[phase] = self._make_step(phase)
        return self._step_fns[phase]

    def train_step(self, state: train.TrainState, batch: Batch) -> tuple[train.TrainState, dict]:
        """One step on a global batch from `shard_batch`; the same rng as `Trainer`."""
        if np.ndim(batch.noisy) != 3 or batch.noisy.shape[0] != self.mesh.size:
            raise ValueError(
                f"expected a stacked batch [n_device={self.mesh.size}, n_vertex, 3] from "
                f"shard_batch, got noisy of shape {np.shape(batch.noisy)}"
            )
        step = int(state.step)
        rng = jax.random.fold_in(jax.random.PRNGKey(self.cfg.train.seed + 1), step)
        return self.step_fn(step)(state, batch.noisy, batch.clean, batch.graph, rng)
