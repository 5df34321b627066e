"""The memory plan of `denoise`: the budget, what a run of each path needs, which path.

A mesh whose whole-mesh run fits the budget runs at once; a larger one patch by patch
(`dmd_jax.patch_runner`). The estimate is the network's XLA buffers per padded vertex
(`network_bytes_per_vertex`, measured by compiling once) plus the host's own arrays per
padded vertex and per mesh element, whose constants below were measured
(`benchmarks/results/inference.md`, `inference_scale.md`).
"""

from __future__ import annotations

import math
import re
from functools import lru_cache
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import compile_cache, shape_ladder
from dmd_jax.config import ModelConfig
from dmd_jax.forward import patch_predictor
from dmd_jax.graph import (
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    with_ell_layout,
)

# The default budget: this fraction of the memory the OS reports available when `denoise`
# starts (MemAvailable), leaving room for other processes and for the estimate's error.
DEFAULT_MEMORY_FRACTION = 0.5
# Host memory per padded vertex of a run besides XLA's own buffers: the NumPy graph and its
# build temporaries (sorted int64 edge keys), the ELL tables, the arguments' device copies
# and the output. Measured: `small` at 999,698 faces (524,288 padded vertices) peaks at
# 4.48 GiB resident, 0.53 GiB before the call and 2.60 GiB of XLA temporaries
# (benchmarks/results/inference.md): 1.35 GiB / 524,288 = 2.8 kB. A 20M-face patch-wise
# run with 3.5 kB here (patches of up to ~509k padded vertices, the next one prepared
# while one ran) peaked 0.8 GiB over its budget: about 4.9 kB. Hence 5 kB, and CPU
# devices no longer overlap host preparation with a running patch.
HOST_BYTES_PER_PADDED_VERTEX = 5000
# The whole-mesh path holds more beside XLA's buffers: the whole mesh's graph is built in
# one go (int64 keys of every edge, sorted) next to its padded copy and ELL tables.
# Measured (bench_inference_scale, default malloc): `small` at 999,698 faces used 6.41 GiB
# above its starting RSS with 2.60 GiB of XLA temporaries: (6.41 - 2.60) GiB / 524,288
# padded vertices = 7.8 kB.
WHOLE_HOST_BYTES_PER_PADDED_VERTEX = 7800
# Whole-mesh state of the patch path per vertex and face: the validated copies, positions
# in the frame (float64), the result, the Morton order, the partition into owned sets,
# the vertex-face incidence and the BFS stamps (see `_mesh_bytes`).
MESH_BYTES_PER_VERTEX = 128
MESH_BYTES_PER_FACE = 40
# What the patch path holds besides patches and the mesh: compiled programs (a handful:
# one per rung of patch shapes and pass) and XLA's compiler working memory. Measured: a
# 300k-face run with a 1 GiB budget peaked 0.34 GiB above it with 16 programs compiled.
RUNTIME_BYTES = 512 * 2**20
# Below this many faces a whole-mesh run is taken without measuring the network (a
# compilation): `paper`, the widest preset, needs about 0.6 GB there.
SMALL_MESH_FACES = 20_000
# An upper bound on `network_bytes_per_vertex` that needs no compile: this many bytes per
# padded vertex per unit of the model's width, plus `NETWORK_BOUND_BASE`. Measured (XLA's
# memory analysis, `_measured_bytes_per_vertex`): 275 (`test`, width 8), 125 (`small`,
# 32) and 105 (`paper`, 512) bytes per unit of width; `tests/test_shape_ladder.py`
# checks the bound for those presets and the attention and STN variants. A mesh that fits the
# budget under the bound runs whole without the measurement's compile (seconds of a
# first call); a larger one is measured.
NETWORK_BOUND_PER_WIDTH = 1000
NETWORK_BOUND_BASE = 4000
_UNITS = {"": 1, "b": 1, "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12}
_UNITS.update({"kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12})
_UNITS.update({"kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40})


# The largest budget taken: 2**63 - 1 bytes (8 EiB), beyond any machine's memory.
MAX_MEMORY_BYTES = 2**63 - 1


def parse_memory(value, name: str = "max_memory") -> int:
    """A memory size in bytes from a number of bytes or a string such as `"6GiB"`, `"8GB"`,
    `"500M"` (k/M/G/T are powers of 1000, KiB/MiB/GiB/TiB of 1024); a number without
    a unit counts bytes (`"1e3"` is 1000 bytes).

    Args:
      value: the size.
      name: the argument named in errors (`--max-memory` on the command line).

    Raises:
      ValueError: an unreadable size, one below a byte, or one beyond `MAX_MEMORY_BYTES`.
    """
    if isinstance(value, str):
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([a-zA-Z]*)\s*", value)
        if m is None or m.group(2).lower() not in _UNITS:
            raise ValueError(
                f"{name}: cannot read the memory size {value!r}; write e.g. 8GB, 6GiB, 500MB "
                "or a number of bytes"
            )
        size = float(m.group(1)) * _UNITS[m.group(2).lower()]
    elif isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    ):
        size = float(value)
    else:
        raise ValueError(f"{name} must be a number of bytes or a string, got {value!r}")
    if size == 0 and isinstance(value, str) and re.search(r"[1-9]", value.split("e")[0]):
        size = 0.5  # a positive size below float64's range (1e-400): less than a byte
    if math.isnan(size) or size <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    if size > MAX_MEMORY_BYTES:
        shown = "beyond float64's range" if math.isinf(size) else f"{size:.3g} bytes"
        raise ValueError(
            f"{name} {value!r} is {shown}, more than any machine's memory (at most "
            f"{MAX_MEMORY_BYTES:.3g} bytes); write e.g. 8GB"
        )
    if size < 1:
        raise ValueError(f"{name} {value!r} is less than one byte")
    return int(size)


def available_memory() -> int:
    """Bytes the OS reports available (`MemAvailable` of /proc/meminfo; psutil elsewhere).

    Raises:
      RuntimeError: neither source exists (pass `max_memory` then).
    """
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:
        raise RuntimeError(
            "cannot tell the available memory (no /proc/meminfo, no psutil); pass max_memory"
        ) from None


def default_memory_budget() -> int:
    """`DEFAULT_MEMORY_FRACTION` of the memory available now, in bytes."""
    return int(DEFAULT_MEMORY_FRACTION * available_memory())


def format_bytes(n: float) -> str:
    if n >= 2**30:
        return f"{n / 2**30:.2f} GiB"
    if n >= 2**20:
        return f"{n / 2**20:.0f} MiB"
    return f"{int(n)} bytes"


def _probe_graph():
    """A padded ~8k-vertex triangulated grid with its ELL tables (for `network_bytes`)."""
    k = 64
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1), indexing="ij")
    a = (i * k + j).ravel()
    faces = np.concatenate(
        [np.stack([a, a + 1, a + k], 1), np.stack([a + 1, a + k + 1, a + k], 1)]
    ).astype(np.int32)
    x = np.stack(
        [*np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), np.zeros((k, k))], -1
    ).reshape(-1, 3)
    graph = build_mesh_graph(faces, k * k)
    graph = with_ell_layout(pad_mesh_graph(graph, padded_sizes_for(graph)))
    return x, graph


@lru_cache(maxsize=8)
def network_bytes_per_vertex(config: ModelConfig) -> int:
    """XLA's memory for one padded vertex of `config`'s forward pass, measured.

    Compiles the forward pass (the patch pass, with its pools given) for a small padded
    grid and divides what `compiled.memory_analysis()` reports (temporaries, arguments,
    output) by its padded vertex count. Memory is linear in size (the `small` preset's
    temporaries were 5.2 kB per padded vertex at 57k and at 524k padded vertices), so
    this scales; the fixed part inflates it slightly at the probe's size, on the safe
    side. Cached per config (one compilation, about a second), in this process and
    on disk (`compile_cache.remembered`: a new process neither traces nor loads the
    probe).

    Args:
      config: the model config.

    Returns:
      Bytes per padded vertex.
    """
    return int(
        compile_cache.remembered(
            "network-bytes", repr(config), lambda: _measured_bytes_per_vertex(config)
        )
    )


def _measured_bytes_per_vertex(config: ModelConfig) -> int:
    x, graph = _probe_graph()
    noisy = pad_vertex_array(x.astype(np.float32), graph.n_vertex)
    predict = patch_predictor(config)
    params = _abstract_params(config)
    pooled = _abstract_pools(config)
    compiled = predict.lower(params, noisy, jax.tree.map(np.asarray, graph), pooled).compile()
    mem = compiled.memory_analysis()
    total = mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes
    return int(math.ceil(total / graph.n_vertex))


def _abstract_params(config: ModelConfig):
    from dmd_jax.model import param_shapes

    return param_shapes(config)


def _abstract_pools(config: ModelConfig) -> dict:
    """Shape structs of every pool `DMDNet(pooled=...)` takes (the patch pass's)."""
    from dmd_jax.model import pooled_names

    dtype = jnp.float64 if config.dtype == "float64" else jnp.float32
    out = {}
    for stage in pooled_names(config):
        for name in stage:
            if name == "stn":
                d = 2 * config.stn_width
            else:
                k = int(name[len("w_tf") :])
                rows = config.transform_in_dim
                cols = config.width if k == config.n_transforms - 1 else rows
                d = rows * cols
            out[name] = jax.ShapeDtypeStruct((d,), dtype)
    return out


def padded_vertices_estimate(n_vertex: int, n_face: int) -> int:
    """The padded vertex count of a mesh's whole-mesh graph, from its counts alone: its
    rung of the shape ladder (`shape_ladder.rung_estimate`)."""
    return shape_ladder.rung_estimate(n_vertex, n_face)


def mesh_bytes(n_vertex: int, n_face: int) -> int:
    """Bytes the patch path holds for the whole mesh and the runtime (not the patches)."""
    return MESH_BYTES_PER_VERTEX * n_vertex + MESH_BYTES_PER_FACE * n_face + RUNTIME_BYTES


class MemoryPlan(NamedTuple):
    """Which path `denoise` takes and the budget it planned with.

    Attributes:
      whole: run the whole mesh at once (else patch by patch).
      budget: the budget in bytes; None for a small mesh run whole without one.
    """

    whole: bool
    budget: int | None


def plan(
    config: ModelConfig, n_vertex: int, n_face: int, max_memory=None, patch_size=None
) -> MemoryPlan:
    """Chooses the path of a mesh of `n_vertex` vertices and `n_face` faces.

    A forced `patch_size` takes the patch path. Below `SMALL_MESH_FACES` faces without a
    `max_memory`, the whole mesh runs without measuring the network. Otherwise the whole
    mesh runs if its estimate fits the budget (`max_memory`, default
    `default_memory_budget()`).

    Raises:
      ValueError: a bad `max_memory`, or a budget that cannot hold the mesh's own arrays.
    """
    budget = None if max_memory is None else parse_memory(max_memory)
    if patch_size is None and budget is None and n_face < SMALL_MESH_FACES:
        return MemoryPlan(True, None)
    if patch_size is not None:
        return MemoryPlan(False, budget)
    if budget is None:
        budget = default_memory_budget()
    if budget <= mesh_bytes(n_vertex, n_face):
        raise ValueError(
            f"the memory budget of {format_bytes(budget)} cannot even hold the mesh's "
            f"own arrays ({format_bytes(mesh_bytes(n_vertex, n_face))} for {n_vertex:,} "
            f"vertices and {n_face:,} faces); raise max_memory / --max-memory"
        )
    padded = padded_vertices_estimate(n_vertex, n_face)
    bound = network_bytes_bound(config) + WHOLE_HOST_BYTES_PER_PADDED_VERTEX
    if bound * padded <= budget:
        return MemoryPlan(True, budget)
    per_vertex = network_bytes_per_vertex(config) + WHOLE_HOST_BYTES_PER_PADDED_VERTEX
    return MemoryPlan(per_vertex * padded <= budget, budget)


def whole_without_measuring(
    config: ModelConfig, n_vertex: int, n_face: int, max_memory=None, patch_size=None
) -> bool:
    """Whether `plan` surely takes the whole-mesh path, known without measuring the
    network or raising: a small mesh without a budget, or one whose bound fits it. False
    may still end whole (after measuring); `inference` starts loading the whole-mesh
    program early only when True.
    """
    if patch_size is not None:
        return False
    try:
        budget = None if max_memory is None else parse_memory(max_memory)
    except ValueError:  # `plan` says so, later
        return False
    if budget is None and n_face < SMALL_MESH_FACES:
        return True
    if budget is None:
        budget = default_memory_budget()
    padded = padded_vertices_estimate(n_vertex, n_face)
    bound = network_bytes_bound(config) + WHOLE_HOST_BYTES_PER_PADDED_VERTEX
    return budget > mesh_bytes(n_vertex, n_face) and bound * padded <= budget


def network_bytes_bound(config: ModelConfig) -> int:
    """An upper bound on `network_bytes_per_vertex(config)` from the config alone."""
    width = max(
        config.width, config.hidden_transformer_width, config.stn_width if config.stn else 0
    )
    return NETWORK_BOUND_PER_WIDTH * width + NETWORK_BOUND_BASE
