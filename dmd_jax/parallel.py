"""Device placement for training on several devices, on one host or many (`jax.sharding`).

A training batch is one group of meshes per device, stacked on a leading axis
(`pipeline.training_batch(..., n_group=mesh.size)`). This module places it: the stacked
arrays are sharded over a one-axis device `Mesh` (`'batch'`) with
`NamedSharding(mesh, P('batch'))`, so group `i` lives on device `i`; params and optimizer
state are replicated. The step itself is `train.make_train_step`, the same code for one
device (a one-device mesh) and for many.

Multi-host: call `jax.distributed.initialize(...)` first (docs/training.md, "Multi-device
and multi-host training"); `jax.devices()` then lists every host's devices, the mesh spans
them, and every process builds and places only the groups of its own devices
(`local_groups`).

Usage::

    mesh = batch_mesh()                              # every device of every process
    trainer = train.Trainer(cfg, mesh)
    batch = pipeline.training_batch(examples, step, n_group=mesh.size,
                                     groups=local_groups(mesh), ...)
    state, metrics = trainer.train_step(state, batch)  # places it with shard_batch
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

BATCH_AXIS = "batch"


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


def local_copy(tree):
    """This process's first copy of a replicated pytree (evaluation needs no other device)."""
    return jax.tree.map(lambda x: x.addressable_data(0), tree)


def shard_batch(mesh: Mesh, batch):
    """Places a pytree of stacked groups `[n_local, ...]` on the batch axis of `mesh`.

    Row `k` of every array goes to the device of the `k`-th position of
    `local_groups(mesh)` and nowhere else; the result is a global array `[mesh.size, ...]`
    sharded with `NamedSharding(mesh, P('batch'))`.

    Args:
      mesh: from `batch_mesh`.
      batch: e.g. a `pipeline.Batch` from `training_batch(..., n_group=mesh.size,
        groups=local_groups(mesh))`.

    Raises:
      ValueError: a leading axis that is not this process's group count.
    """
    _check_mesh(mesh)
    mine = local_groups(mesh)
    leaves, treedef = jax.tree.flatten(batch)
    shapes = {np.shape(x)[:1] for x in leaves}
    if shapes != {(len(mine),)}:
        raise ValueError(
            f"expected the {len(mine)} groups of this process's devices stacked on a leading "
            f"axis, got leading shapes {sorted(shapes)}"
        )
    sharding = NamedSharding(mesh, P(BATCH_AXIS))
    if len(mine) == mesh.size:
        # Every device is this process's: one transfer of the whole tree (half the host
        # time of one array per device and leaf, on one CPU device).
        return jax.device_put(batch, sharding)
    devices = list(mesh.devices.flat)
    out = []
    for x in leaves:
        x = np.asarray(x)
        parts = [jax.device_put(x[k : k + 1], devices[i]) for k, i in enumerate(mine)]
        out.append(
            jax.make_array_from_single_device_arrays((mesh.size,) + x.shape[1:], sharding, parts)
        )
    return jax.tree.unflatten(treedef, out)


def sum_over_groups(group_fn: Callable, mesh: Mesh, in_specs: tuple) -> Callable:
    """`group_fn(index, *blocks)` on every device's block of the batch, summed over devices.

    Each device calls `group_fn` with its position on the batch axis and its blocks of
    the arguments (`in_specs`: `P('batch')` for stacked groups, `P()` for replicated
    ones); the results are summed (`jax.lax.psum`) and come back replicated.

    On a one-device mesh the block is the whole argument and the sum is the one result,
    so `group_fn(0, *args)` is called directly rather than through `jax.shard_map`: the
    same values, and about 20 % less tracing (every transformation above a shard_map
    traces its body again; ~1 s of the ~5 s a test-preset train step takes to trace).

    Returns:
      `f(*args)`, a pytree like `group_fn`'s result.
    """
    _check_mesh(mesh)
    if mesh.size == 1:
        return lambda *args: group_fn(0, *args)

    def body(*args):
        return jax.lax.psum(group_fn(jax.lax.axis_index(BATCH_AXIS), *args), BATCH_AXIS)

    return jax.shard_map(body, mesh=mesh, in_specs=in_specs, out_specs=P())
