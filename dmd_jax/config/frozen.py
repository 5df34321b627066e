"""Frozen dataclasses that are pytrees: `flax.struct.dataclass` without importing Flax.

The configs and `DenoisePolicy` are read by every `dmd-jax denoise` process, which
runs a stored executable and never traces the Flax model; importing Flax for its
`struct` module alone cost such a process 0.15-0.25 s on 2 cores (docs/cold-start.md).
A class made here is what `flax.struct.dataclass` makes of it, but for Flax's
`serialization` state-dict hooks, which no config or policy goes through: a frozen
dataclass with a `replace` method, registered with `jax.tree_util.register_dataclass`
(fields with `pytree_node=False` metadata static, the others leaves).
"""

from __future__ import annotations

import dataclasses
from typing import Any


def field(*, pytree_node: bool = True, **kwargs: Any):
    """`dataclasses.field` with `pytree_node` metadata (False: static, in the treedef)."""
    return dataclasses.field(metadata={"pytree_node": pytree_node}, **kwargs)


def dataclass(cls):
    """Makes `cls` a frozen dataclass registered as a pytree, with `replace(**changes)`."""
    import jax

    if "_dmd_jax_frozen" in cls.__dict__:
        return cls
    data_cls = dataclasses.dataclass(frozen=True)(cls)
    data, meta = [], []
    for f in dataclasses.fields(data_cls):
        (data if f.metadata.get("pytree_node", True) else meta).append(f.name)

    def replace(self, **updates):
        """A copy with the given fields replaced (validated again)."""
        return dataclasses.replace(self, **updates)

    data_cls.replace = replace
    jax.tree_util.register_dataclass(data_cls, data, meta)
    data_cls._dmd_jax_frozen = True
    return data_cls
