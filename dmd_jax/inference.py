"""`denoise`: a noisy mesh in any frame in, denoised vertices in the same frame out.

The weights it runs come from `dmd_jax.checkpoints` (`load_pretrained`, `load_weights`,
`load_model`); the padded graph it runs on from `dmd_jax.graph`.

Memory: a mesh whose whole-mesh run fits the memory budget (`max_memory`) runs at once,
as it always did; a larger one runs patch by patch (`dmd_jax.patches`): first the
per-mesh pools, summed over the patches, then every patch with those pools, keeping its
owned vertices. Both give the same result up to float32 summation order. Patches are
dispatched to every local device (`jax.local_devices()`), one in flight per device,
while the host prepares the next.
"""

from __future__ import annotations

import math
import re
import sys
from collections import deque
from functools import lru_cache
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import patches as patch_lib
from dmd_jax.checkpoints import as_bundle
from dmd_jax.config import ExperimentConfig, ModelConfig
from dmd_jax.encoding import mesh_frame
from dmd_jax.graph import (
    build_mesh_graph,
    fine_padded_sizes_for,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    sizes_for_vertices,
    undirected_vertex_edges,
    with_ell_layout,
)
from dmd_jax.mesh import CanonicalFrame, canonical_frame, validate_mesh
from dmd_jax.presmooth import laplacian_steps, roughness, steps_for
from dmd_jax.relax import relax_tangential

AGGREGATIONS = ("auto", "ell", "segment_sum")
# `auto` keeps a graph's ELL table while it holds at most this many slots per distinct
# edge. The shared meshes, padded, need 1.8-2.9 (vertex graph) and 1.2-1.4 (face graph);
# truck.obj, with a vertex of valence 36, 6.6, where its table still beat the segment sum
# (benchmarks/README.md). A pole of valence 1000 would need hundreds.
AUTO_MAX_FILL = 8.0


@lru_cache(maxsize=8)
def _predictor(config: ExperimentConfig):
    """The jitted forward pass of a config (configs are frozen and hashable: the key)."""
    from dmd_jax.model import DMDNet

    model = DMDNet(config.model)

    @jax.jit
    def predict(params, noisy, graph):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True)
        return out

    return predict


# --------------------------------------------------------------------------------------
# Memory budget
# --------------------------------------------------------------------------------------

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
# Owned sets are graph Voronoi cells of a target size (`patches.compact_partition`); on
# noisy grids of 5M faces, cells of 100k-200k vertices spanned 0.65-1.5 times the target
# with a median of 0.95. The patch size is chosen so that a cell this many times the
# target still fits the budget; larger ones are split.
CELL_SLACK = 1.25
# What the patch path holds besides patches and the mesh: compiled programs (a handful:
# one per rung of patch shapes and pass) and XLA's compiler working memory. Measured: a
# 300k-face run with a 1 GiB budget peaked 0.34 GiB above it with 16 programs compiled.
RUNTIME_BYTES = 512 * 2**20
# Below this many faces a whole-mesh run is taken without measuring the network (a
# compilation): `paper`, the widest preset, needs about 0.6 GB there.
_SMALL_MESH_FACES = 20_000
# From this many faces the whole-mesh path pads each count to within 6 %
# (`fine_padded_sizes_for`) instead of the shared coarse buckets: at 100k faces those
# carry 129k face rows, and the network ran about 25 % faster on 100k rows
# (docs/design-decisions.md). Smaller meshes keep the coarse buckets: there a
# compilation costs more than the padding, and similar meshes share a program.
FINE_PADDING_MIN_FACES = 20_000
_UNITS = {"": 1, "b": 1, "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12}
_UNITS.update({"kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12})
_UNITS.update({"kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40})


def parse_memory(value) -> int:
    """A memory size in bytes from a number of bytes or a string such as `"6GiB"`, `"8GB"`,
    `"500M"` (k/M/G/T are powers of 1000, KiB/MiB/GiB/TiB of 1024).

    Raises:
      ValueError: an unreadable or non-positive size.
    """
    if isinstance(value, str):
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", value)
        if m is None or m.group(2).lower() not in _UNITS:
            raise ValueError(
                f"cannot read the memory size {value!r}; write e.g. 8GB, 6GiB, 500MB or a "
                "number of bytes"
            )
        size = float(m.group(1)) * _UNITS[m.group(2).lower()]
    elif isinstance(value, int | float) and not isinstance(value, bool):
        size = float(value)
    else:
        raise ValueError(f"max_memory must be a number of bytes or a string, got {value!r}")
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"max_memory must be positive, got {value!r}")
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


def _format_bytes(n: float) -> str:
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
    side. Cached per config (one compilation, about a second).

    Args:
      config: the model config.

    Returns:
      Bytes per padded vertex.
    """
    x, graph = _probe_graph()
    noisy = pad_vertex_array(x.astype(np.float32), graph.n_vertex)
    predict = _patch_predictor(config)
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


def _padded_vertices_estimate(n_vertex: int, n_face: int) -> int:
    """The padded vertex count of a mesh's whole-mesh graph, from its counts alone."""
    # Edge counts of a triangle mesh: e ~ 1.5 f (primal, both ways plus loops: 3f + v) and
    # 3 f dual edges (plus loops: 4 f), as `graph.sizes_for_vertices` sizes them.
    return sizes_for_vertices(n_vertex, n_face, 3 * n_face + n_vertex, 4 * n_face, 1).n_vertex


def _mesh_bytes(n_vertex: int, n_face: int) -> int:
    """Bytes the patch path holds for the whole mesh and the runtime (not the patches)."""
    return MESH_BYTES_PER_VERTEX * n_vertex + MESH_BYTES_PER_FACE * n_face + RUNTIME_BYTES


# --------------------------------------------------------------------------------------
# Whole mesh and patches
# --------------------------------------------------------------------------------------


@lru_cache(maxsize=8)
def _patch_predictor(config: ExperimentConfig | ModelConfig):
    """The jitted forward pass with every per-mesh pool given (`DMDNet(pooled=...)`)."""
    from dmd_jax.model import DMDNet

    model = DMDNet(config.model if isinstance(config, ExperimentConfig) else config)

    @jax.jit
    def predict(params, noisy, graph, pooled):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True, pooled=pooled)
        return out

    return predict


@lru_cache(maxsize=8)
def _pool_predictor(config: ModelConfig, names: tuple[str, ...]):
    """The jitted forward pass up to the pools `names` (earlier stages given).

    Only the pools are returned, so XLA drops everything that does not feed them (the
    denoiser, the vertex update).
    """
    from dmd_jax.model import DMDNet

    model = DMDNet(config)

    @jax.jit
    def pools(params, noisy, graph, pooled):
        _, state = model.apply(
            {"params": params},
            noisy,
            graph,
            deterministic=True,
            pooled=pooled,
            mutable=["intermediates"],
        )
        found = dict(_find_sown(state["intermediates"]))
        return {name: found[name][0] for name in names}  # row 0: the patch's graph

    return pools


def _find_sown(tree):
    """`(name, value)` of every value `Module.sow` recorded, at any depth."""
    for key, value in tree.items():
        if isinstance(value, tuple):
            yield key, value[-1]
        else:
            yield from _find_sown(value)


def _prepared_graph(faces: np.ndarray, n_vertex: int, aggregation: str):
    """The padded graph `denoise` runs on (edge lists, and ELL tables unless
    `aggregation="segment_sum"`), as NumPy."""
    graph = build_mesh_graph(faces, n_vertex)
    if faces.shape[0] >= FINE_PADDING_MIN_FACES:
        graph = pad_mesh_graph(graph, fine_padded_sizes_for(graph))
    else:
        graph = pad_mesh_graph(graph, padded_sizes_for(graph))
    if aggregation != "segment_sum":
        graph = with_ell_layout(graph, max_fill=AUTO_MAX_FILL if aggregation == "auto" else None)
    return graph


def _ell_widths(graph) -> tuple:
    return tuple(
        None if e is None else e.neighbours.shape[1] for e in (graph.vertex_ell, graph.face_ell)
    )


def _widen_ell(graph, widths):
    """`graph` with its ELL tables widened to `widths` by unused slots (weight 0, pointing
    at their own row, their own reverse slot), which change nothing; a table that is None
    on either side stays as it is."""
    out = []
    for ell, width in zip((graph.vertex_ell, graph.face_ell), widths, strict=True):
        if ell is None or width is None or ell.neighbours.shape[1] >= width:
            out.append(ell)
            continue
        n, w = ell.neighbours.shape
        extra = width - w
        rows = np.broadcast_to(np.arange(n, dtype=np.int32)[:, None], (n, extra))
        slots = np.broadcast_to(np.arange(w, width, dtype=np.int32)[None, :], (n, extra))
        out.append(
            type(ell)(
                np.concatenate([ell.neighbours, rows], 1),
                np.concatenate([ell.weights, np.zeros((n, extra), ell.weights.dtype)], 1),
                np.concatenate([ell.reverse_slot, slots], 1),
            )
        )
    return graph._replace(vertex_ell=out[0], face_ell=out[1])


def lean_mesh_frame(encoding: str, vertices: np.ndarray, faces: np.ndarray) -> CanonicalFrame:
    """`encoding.mesh_frame` in a few bytes a face, for meshes of tens of millions of faces.

    The mean edge length of the `"local"` frame over unique edges as `mesh_frame` takes
    it, but from one int64 key per half-edge sorted in place and lengths summed in
    blocks (`mesh.mean_edge_length` holds several `[3 n_face, 2]` int64 copies at once).
    Equal to `mesh_frame` up to float64 summation order.
    """
    box = canonical_frame(vertices)
    if encoding == "xyz":
        return box
    n = np.int64(vertices.shape[0])
    key = np.empty(3 * faces.shape[0], np.int64)
    m = faces.shape[0]
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        a, b = faces[:, i].astype(np.int64), faces[:, j].astype(np.int64)
        key[k * m : (k + 1) * m] = np.minimum(a, b) * n + np.maximum(a, b)
        del a, b
    key.sort()
    first = np.ones(key.size, bool)
    first[1:] = key[1:] != key[:-1]
    key = key[first]
    del first
    total, block = 0.0, 1 << 22
    for start in range(0, key.size, block):
        a, b = np.divmod(key[start : start + block], n)
        total += float(np.linalg.norm(vertices[a] - vertices[b], axis=1).sum())
    h = total / key.size
    if not (np.isfinite(h) and h > 0):
        raise ValueError("the mesh's mean edge length is zero: no edge-unit frame exists")
    return CanonicalFrame(centre=box.centre, scale=h)


def _check_steps(name: str, value, what: str = "a non-negative number of steps") -> None:
    """`value` is a whole number >= 0 (a bool is not), else a `ValueError` naming `name`."""
    if isinstance(value, bool) or int(value) != value or value < 0:
        raise ValueError(f"{name} must be {what}, got {value!r}")


def denoise(
    vertices,
    faces,
    params,
    *,
    config: ExperimentConfig | None = None,
    iterations: int | None = None,
    aggregation: str = "auto",
    max_memory=None,
    patch_size: int | None = None,
    progress: bool | None = None,
    devices=None,
    info: dict | None = None,
    relax: int = 0,
    presmooth: int | None = None,
) -> np.ndarray:
    """Denoises a triangle mesh with a trained DMD-Net, in bounded memory.

    The mesh is mapped to the frame of the model's encoding (`encoding.mesh_frame`:
    bounding box centred, and longest side 1 or mean edge length 1), denoised, and
    mapped back, so the result is translation- and scale-equivariant.

    A mesh whose whole-mesh run fits `max_memory` runs at once. A larger one runs patch
    by patch (`dmd_jax.patches`): compact owned vertex sets (graph Voronoi cells), each
    grown by a halo as deep as the network's receptive field; the per-mesh pools of the transformer
    (and STN) are computed first over all patches. The result equals the whole-mesh run
    up to float32 summation order (`tests/test_patches.py`: within 2e-5 mean edge
    lengths for the bundled model).

    Args:
      vertices: `[n_vertex, 3]` in any frame; float16/32/64 or integer.
      faces: `[n_face, 3]` integer indices.
      params: a `ModelBundle` (from `load_pretrained()`, `load_weights()` or a training
        checkpoint via `load_model`), a path for `load_model`, or raw params with
        `config`.
      config: the experiment config, needed only with raw params.
      iterations: how many times to apply the network (each pass starts from the last),
        or None (default): the model's own policy, `ModelConfig.pass_tolerance`. For the
        bundled weights that is one pass, and a second (up to `AUTO_MAX_PASSES`) while
        the last pass moved the vertices by more than 0.18 mean edges on average, as
        it does after heavy noise (`benchmarks/results/pass_tolerance.md`).
      aggregation: how the GCN aggregations run (the same operator either way, equal up
        to float summation order): `"ell"` through padded neighbour tables
        (`graph.with_ell_layout`; faster on CPU, no scatter), `"segment_sum"` over the
        edge lists, as in training, or `"auto"`: the tables of the vertex and face
        graphs, except a table padded to more than `AUTO_MAX_FILL` slots per edge (a
        vertex of very high valence), whose graph then uses its edge lists. Attention
        models use the edge lists regardless.
      max_memory: the memory this call may use beyond what the process holds when it
        starts, in bytes or as a string (`"6GiB"`, `"8GB"`); default
        `DEFAULT_MEMORY_FRACTION` of the memory available (`available_memory`). The
        estimate: the network's XLA buffers per padded vertex (`network_bytes_per_vertex`,
        measured by compiling once) plus `WHOLE_HOST_BYTES_PER_PADDED_VERTEX` (whole
        mesh) or `HOST_BYTES_PER_PADDED_VERTEX` and the mesh's own arrays (patches).
      patch_size: owned vertices per patch; forces the patch path (tests, tuning). Default:
        the largest patches the budget allows.
      progress: a tqdm progress bar over the patches on stderr (default: when stderr is a
        terminal and there are several patches).
      devices: the devices patches run on (default `jax.local_devices()`).
      info: a dict to fill with how the call ran: `path` (`"whole"` or `"patches"`),
        `budget_bytes`, `passes`, `presmooth_steps` (Laplacian steps run before the
        network), `roughness` (the noisy mesh's, in degrees, when the model's rule
        chose the steps; else None), and for patches `patch_size` (owned vertices),
        `patches` (run over every pass), `largest_padded_vertices`, `halo_rings`,
        `devices`.
      relax: steps of feature-preserving tangential relaxation applied to the result
        (`dmd_jax.relax.relax_tangential`; 0, the default, leaves it as the network
        made it). For noise with a tangential part (per-coordinate noise, the paper's
        Table II): the network moves vertices along normals only. On the validation
        split, 3 steps took the mean normal error at 0.2 edges of per-coordinate noise
        from 24.2° to 18.4°, at 0.1 / 0.3 edges along normals from 12.5 / 19.8° to
        11.8 / 18.3°, but a clean mesh's from 7.2° to 8.9° (README, "Tangential
        relaxation"). Runs on the whole mesh, about 300 bytes per vertex.
      presmooth: uniform Laplacian steps run before the network (`dmd_jax.presmooth`),
        or None (default): the model's own rule (`ModelConfig.presmooth_start`), as
        many steps as the noisy mesh's roughness asks for. For the bundled weights that
        is none for noise up to about a third of an edge along the normals and for
        clean meshes, and up to `presmooth.MAX_STEPS` for noise of several edges
        (`benchmarks/results/presmooth_fit.md`). 0 gives the network the mesh as it is.
        The steps are linear in the positions and the roughness is scale free, so the
        result stays translation- and scale-equivariant.

    Returns:
      `[n_vertex, 3]` denoised vertices in the input frame; float32 for float32 input,
      float64 otherwise.

    Raises:
      ValueError: bad mesh (see `dmd_jax.mesh.validate_mesh`), bad params, an unknown
        `aggregation`, a bad `max_memory` or `patch_size`, or a budget too small for a
        single patch (the message names the budget and what one patch needs).
    """
    if iterations is not None:
        _pass_plan(iterations, None)  # a bad count fails before any work
    _check_steps("relax", relax)
    if presmooth is not None:
        _check_steps("presmooth", presmooth, "a non-negative number of steps or None")
    if aggregation not in AGGREGATIONS:
        raise ValueError(
            f"unknown aggregation {aggregation!r}; choose one of {', '.join(AGGREGATIONS)}"
        )
    if patch_size is not None and (isinstance(patch_size, bool) or int(patch_size) < 1):
        raise ValueError(f"patch_size must be a positive number of vertices, got {patch_size}")
    budget = None if max_memory is None else parse_memory(max_memory)
    v, f = validate_mesh(vertices, faces)
    in_dtype = np.asarray(vertices).dtype
    bundle = as_bundle(params, config)
    cfg = bundle.config.model
    passes = _pass_plan(iterations, cfg)
    rough, steps = None, presmooth
    if presmooth is None:
        steps = 0
        if cfg.presmooth_start > 0:
            rough = roughness(v, f)
            steps = steps_for(rough, cfg.presmooth_start, cfg.presmooth_per_step)
    if steps:
        v = laplacian_steps(v, f, int(steps))
    n, m = v.shape[0], f.shape[0]
    whole = patch_size is None and budget is None and m < _SMALL_MESH_FACES
    if patch_size is None and not whole:
        if budget is None:
            budget = default_memory_budget()
        if budget <= _mesh_bytes(n, m):
            raise ValueError(
                f"the memory budget of {_format_bytes(budget)} cannot even hold the mesh's "
                f"own arrays ({_format_bytes(_mesh_bytes(n, m))} for {n:,} vertices and "
                f"{m:,} faces); raise max_memory / --max-memory"
            )
        per_vertex = network_bytes_per_vertex(cfg) + WHOLE_HOST_BYTES_PER_PADDED_VERTEX
        whole = per_vertex * _padded_vertices_estimate(n, m) <= budget
    if info is not None:
        info.clear()
        info.update(
            path="whole" if whole else "patches",
            budget_bytes=budget,
            presmooth_steps=int(steps),
            roughness=rough,
        )
    if whole:
        result = _denoise_whole(v, f, bundle, in_dtype, passes, aggregation, info)
    else:
        result = _denoise_patches(
            v,
            f,
            bundle,
            in_dtype,
            passes,
            aggregation,
            budget,
            patch_size,
            devices,
            progress,
            info,
        )
    if relax:
        result = relax_tangential(result, f, int(relax)).astype(result.dtype)
    return result


def _denoise_patches(
    v, f, bundle, in_dtype, passes, aggregation, budget, patch_size, devices, progress, info
) -> np.ndarray:
    """The patch path of `denoise` (a given `patch_size`, or one chosen from `budget`)."""
    cfg = bundle.config.model
    frame = lean_mesh_frame(cfg.encoding, v, f)
    x = frame.apply(v)
    runner = _PatchRunner(bundle, f, v.shape[0], aggregation, devices, progress)
    del v
    if patch_size is None:
        per_vertex = network_bytes_per_vertex(cfg) + HOST_BYTES_PER_PADDED_VERTEX
        runner.size_from_budget(x, budget, per_vertex)
    else:
        runner.patch_size = int(patch_size)
    patches_run = 0

    def one_pass(x):
        nonlocal patches_run
        out = runner.run(x)
        patches_run += runner.patches_run
        return out

    x, done = _run_passes(one_pass, x, passes)
    if info is not None:
        info.update(
            passes=done,
            path="patches",
            budget_bytes=budget,
            patch_size=runner.patch_size,
            patches=patches_run,
            largest_padded_vertices=runner.largest_patch,
            halo_rings=runner.halo.output,
            devices=len(runner.devices),
        )
    result = frame.invert(x)
    return result.astype(np.float32) if in_dtype == np.float32 else result


class _Passes(NamedTuple):
    """How many network passes `denoise` runs: up to `most`, stopping after a pass that
    moved the vertices by at most `tolerance` on average (frame units; -1: never)."""

    most: int
    tolerance: float


# The most passes `denoise` runs under a model's `pass_tolerance`, a bound on the time of
# a mesh that keeps moving. On the validation split no mesh needed a third pass
# (benchmarks/results/pass_tolerance.md); fixed pass counts kept improving up to 8 on
# the paper's Table II levels (experiments/results/sota/sota.md).
AUTO_MAX_PASSES = 8


def _pass_plan(iterations, model: ModelConfig | None) -> _Passes:
    if iterations is None:
        if model.pass_tolerance > 0:
            return _Passes(AUTO_MAX_PASSES, float(model.pass_tolerance))
        return _Passes(1, -1.0)
    if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
        raise ValueError(f"iterations must be a positive integer or None, got {iterations!r}")
    return _Passes(int(iterations), -1.0)


def _run_passes(one_pass, x: np.ndarray, passes: _Passes) -> tuple[np.ndarray, int]:
    """Applies `one_pass` (positions -> positions, frame units) as `passes` says: up to
    `passes.most` times, stopping after a pass whose mean vertex move is at most
    `passes.tolerance`. Returns the positions and the passes run."""
    done, moved = 0, np.inf
    while done < passes.most and moved > passes.tolerance:
        out = one_pass(x)
        if not np.all(np.isfinite(out)):
            raise ValueError("the network produced non-finite vertices (broken weights?)")
        moved = float(np.linalg.norm(out - x, axis=1).mean()) if len(out) else 0.0
        x, done = out, done + 1
    return x, done


def _denoise_whole(v, f, bundle, in_dtype, passes: _Passes, aggregation: str, info) -> np.ndarray:
    """The whole mesh at once (the path of every mesh that fits the budget)."""
    # The padded graph does not change between passes: build it (edge lists, ELL
    # tables) and move it to the device once, not once per pass.
    graph = _prepared_graph(f, v.shape[0], aggregation)
    edges = undirected_vertex_edges(graph)
    frame = mesh_frame(bundle.config.model.encoding, v, f, edges=edges)
    x = frame.apply(v)
    graph = jax.tree.map(jnp.asarray, graph)
    predict = _predictor(bundle.config)
    n, n_padded = v.shape[0], graph.n_vertex

    def one_pass(x):
        # As training pads the noisy positions: float32, zeros on padding rows.
        noisy = pad_vertex_array(x.astype(np.float32), n_padded)
        return np.asarray(predict(bundle.params, jnp.asarray(noisy), graph)[:n], np.float64)

    x, done = _run_passes(one_pass, x, passes)
    if info is not None:
        info["passes"] = done
    result = frame.invert(x)
    return result.astype(np.float32) if in_dtype == np.float32 else result


class _PatchRunner:
    """Runs one network pass over a mesh patch by patch (see `denoise`).

    Args:
      bundle: the model bundle.
      faces: `[n_face, 3]` int32 faces of the whole mesh.
      n_vertex: its vertex count.
      aggregation: as `denoise`'s.
      devices: devices to spread the patches over (default `jax.local_devices()`).
      progress: as `denoise`'s.
    """

    def __init__(self, bundle, faces, n_vertex: int, aggregation: str, devices, progress):
        from dmd_jax.model import pooled_names

        self.bundle = bundle
        self.cfg = bundle.config.model
        self.faces = faces
        self.n_vertex = int(n_vertex)
        self.aggregation = aggregation
        self.devices = list(jax.local_devices() if devices is None else devices)
        if not self.devices:
            raise ValueError("denoise needs at least one device")
        self.progress = progress
        self.grower = patch_lib.PatchGrower(faces, n_vertex)
        self.halo = patch_lib.halo_rings(self.cfg)
        self.stages = pooled_names(self.cfg)
        self.patch_size = None
        self.max_padded_vertices = None  # None: no limit (a forced patch_size)
        self.budget = None
        self.order = None
        self.partition = None  # patches.Partition of `patch_size`
        self._params = {}
        self._shapes = {}  # padded sizes compiled so far -> their ELL table widths
        self.reference = None  # padded vertices of a typical full patch (the ladder's top)
        self.patches_run = 0  # patches of the last `run`, over every pass (benchmarks)
        self.largest_patch = 0  # most padded vertices of any patch so far

    def size_from_budget(self, x: np.ndarray, budget: int, per_vertex: int) -> None:
        """Chooses the owned vertices per patch so that a padded patch fits `budget`.

        Starts from a disc of owned vertices on a remeshed surface (radius r rings: about
        3 r^2 vertices) whose halo keeps the patch at 3/4 of the limit, then shrinks it
        by 4/5 while a disc of that many vertices from the middle of the mesh (grown by
        the output halo) is over the limit, or grows it by 5/4 while the next step still
        fits. The disc is made `CELL_SLACK` times the size: the owned sets are graph
        Voronoi cells (`patches.compact_partition`), most of them within that factor of
        their target. A cell found too large later is split (`_patches`).

        Args:
          x: `[n_vertex, 3]` positions (for the Morton order).
          budget: bytes for the whole call.
          per_vertex: bytes per padded vertex of a patch.

        Raises:
          ValueError: the mesh's own arrays leave no room for a patch.
        """
        self.budget = budget
        self._ensure_order(x)
        room = budget - _mesh_bytes(self.n_vertex, self.faces.shape[0])
        self.max_padded_vertices = room // per_vertex
        if self.max_padded_vertices < 256:
            raise ValueError(
                f"the memory budget of {_format_bytes(budget)} leaves "
                f"{_format_bytes(max(room, 0))} for patches after the mesh's own arrays "
                f"({_format_bytes(_mesh_bytes(self.n_vertex, self.faces.shape[0]))}); a "
                f"patch needs {per_vertex} bytes a padded vertex and its halo "
                f"{self.halo.output} rings; raise max_memory / --max-memory"
            )
        limit = self.max_padded_vertices
        r0 = max(math.sqrt(0.75 * limit / 3.0) - self.halo.output, 1.0)
        size = min(max(int(3.0 * r0 * r0), 1), self.n_vertex)
        # The middle of the Morton order: away from the mesh's corners, whose patches
        # lose part of their halo and come out smaller.
        seed = int(self.order[self.n_vertex // 2])

        def padded(k: int) -> int:
            owned = self.grower.disc(seed, max(int(CELL_SLACK * k), 1))
            patch = self.grower.grow(owned, self.halo.output)
            return padded_sizes_for(build_mesh_graph(patch.faces, patch.vertices.size)).n_vertex

        while size > 1 and padded(size) > limit:
            size = max(size * 4 // 5, 1)
        while size < self.n_vertex and padded(min(size * 5 // 4 + 1, self.n_vertex)) <= limit:
            size = min(size * 5 // 4 + 1, self.n_vertex)
        self.patch_size = size
        self.reference = padded(size)

    def _ensure_order(self, x: np.ndarray) -> None:
        if self.order is None:
            self.order = patch_lib.morton_order(x)

    def _ensure_partition(self, x: np.ndarray) -> None:
        """The owned sets for `patch_size`, made once (passes and iterations share them:
        `patch_size` is fixed before the first pass)."""
        self._ensure_order(x)
        if self.partition is None:
            self.partition = patch_lib.compact_partition(
                x, self.faces, self.grower.incidence, self.order, self.patch_size
            )

    # ----------------------------------------------------------------------------------

    def _device_params(self, device):
        if device not in self._params:
            self._params[device] = jax.device_put(self.bundle.params, device)
        return self._params[device]

    def _shaped_graph(self, graph, natural):
        """The padded graph of a patch's `graph` (natural sizes `natural`).

        Patches are padded to a ladder of shapes, the reference patch's padded vertex
        count times 1, 3/4, 1/2, 3/8, ... (`self.reference`), so a sweep compiles about
        one program per rung instead of one per bucket that patch sizes happen to hit;
        a patch above the reference keeps its own bucket. ELL tables are widened to the
        width the shape first had.
        """
        sizes = natural
        if self.reference is not None and natural.n_vertex <= self.reference:
            rungs, r = [self.reference], self.reference
            while r // 2 >= 1024:  # 1, 3/4, 1/2, 3/8, ... of it: at most a third wasted
                rungs += [r * 3 // 4, r // 2]
                r //= 2
            rung = min(r for r in rungs if r >= natural.n_vertex)
            sizes = sizes_for_vertices(rung - 1, 0, 0, 0, natural.n_graph - 1)
            if any(a < b for a, b in zip(sizes, natural, strict=True)):
                sizes = natural
        graph = pad_mesh_graph(graph, sizes)
        if self.aggregation != "segment_sum":
            auto = self.aggregation == "auto"
            graph = with_ell_layout(graph, max_fill=AUTO_MAX_FILL if auto else None)
            widths = self._shapes.get(sizes)
            if widths is not None and _ell_widths(graph) != widths:
                graph = _widen_ell(graph, widths)
        self._shapes.setdefault(sizes, _ell_widths(graph))
        return graph

    def _patches(self, rings: int):
        """Yields `(patch, padded graph)`; splits owned sets whose patch is too large."""
        todo = deque(self.partition.sets())
        while todo:
            owned = todo.popleft()
            patch = self.grower.grow(owned, rings)
            limit = self.max_padded_vertices
            raw = build_mesh_graph(patch.faces, patch.vertices.size)
            n_padded = padded_sizes_for(raw)
            if limit is not None and n_padded.n_vertex > limit:
                if owned.size == 1:
                    raise ValueError(
                        f"the memory budget of {_format_bytes(self.budget)} cannot hold a "
                        f"single patch: one vertex with its {rings}-ring halo is "
                        f"{patch.vertices.size} vertices ({n_padded.n_vertex} padded, "
                        f"{limit} fit); raise max_memory / --max-memory"
                    )
                half = owned.size // 2  # in Morton order: two halves compact in space
                todo.appendleft(owned[half:])
                todo.appendleft(owned[:half])
                continue
            graph = self._shaped_graph(raw, n_padded)
            self.largest_patch = max(self.largest_patch, graph.n_vertex)
            yield patch, graph

    def _sweep(self, x, rings: int, fn, desc: str):
        """Runs `fn(device, patch, graph)` (async) over every patch, several devices at
        once; yields `(patch, result)` as NumPy in patch order."""
        bar = None
        show = self.progress
        if show is None:
            show = sys.stderr.isatty() and self.n_vertex > 2 * (self.patch_size or 1)
        if show:
            from tqdm.auto import tqdm

            bar = tqdm(total=self.n_vertex, desc=desc, unit="vertex", unit_scale=True)
        inflight = deque()
        k = 0
        depth = len(self.devices) - (1 if self.devices[0].platform == "cpu" else 0)
        try:
            for patch, graph in self._patches(rings):
                device = self.devices[k % len(self.devices)]
                k += 1
                inflight.append((patch, fn(device, patch, graph)))
                # Accelerators: one patch per device runs while the host prepares the
                # next. CPU devices share the host's cores and memory, so there the host
                # waits instead (no second patch's graph alive beside a running one).
                if len(inflight) > depth:
                    patch, out = inflight.popleft()
                    yield patch, jax.device_get(out)
                    if bar is not None:
                        bar.update(int(patch.owned.sum()))
            while inflight:
                patch, out = inflight.popleft()
                yield patch, jax.device_get(out)
                if bar is not None:
                    bar.update(int(patch.owned.sum()))
        finally:
            if bar is not None:
                bar.close()
        self.patches_run += k

    def _inputs(self, device, x, patch, graph, pooled, owned_mask: bool):
        noisy = pad_vertex_array(x[patch.vertices].astype(np.float32), graph.n_vertex)
        if owned_mask:
            # The pools average over the owned vertices only: each vertex counts once
            # over all patches (`vertex_mask` reaches nothing but the pools).
            graph = graph._replace(vertex_mask=pad_vertex_array(patch.owned, graph.n_vertex))
        return jax.device_put((noisy, graph, pooled), device)

    def run(self, x: np.ndarray) -> np.ndarray:
        """One pass of the network: `[n_vertex, 3]` frame positions in, out."""
        self._ensure_partition(x)
        self.patches_run = 0
        params_dtype = np.float64 if self.cfg.dtype == "float64" else np.float32
        pooled: dict = {}
        n_pass = len(self.stages) + 1
        for s, names in enumerate(self.stages):
            predict = _pool_predictor(self.cfg, names)
            sums = None

            def pool_fn(device, patch, graph, predict=predict, pooled=pooled):
                args = self._inputs(device, x, patch, graph, pooled, owned_mask=True)
                return predict(self._device_params(device), *args)

            desc = f"pools {s + 1}/{n_pass}"
            for patch, out in self._sweep(x, self.halo.pools[s], pool_fn, desc):
                count = float(patch.owned.sum())
                part = {k: np.asarray(v, np.float64) * count for k, v in out.items()}
                sums = part if sums is None else {k: sums[k] + part[k] for k in sums}
            pooled = {
                **pooled,
                **{k: (v / self.n_vertex).astype(params_dtype) for k, v in sums.items()},
            }
        predict = _patch_predictor(self.cfg)
        result = np.empty_like(x)

        def run_fn(device, patch, graph):
            args = self._inputs(device, x, patch, graph, pooled, owned_mask=False)
            return predict(self._device_params(device), *args)

        desc = f"patches {n_pass}/{n_pass}" if n_pass > 1 else "patches"
        for patch, out in self._sweep(x, self.halo.output, run_fn, desc):
            keep = patch.owned
            result[patch.vertices[keep]] = out[: patch.vertices.size][keep]
        return result
