"""`denoise`: a noisy mesh in any frame in, denoised vertices in the same frame out.

What runs, in order: the policy's pre-smoothing rule (`dmd_jax.policy`), the network's
passes over the whole mesh or patch by patch (`dmd_jax.memory_plan` chooses,
`dmd_jax.patch_runner` runs the patches), the policy's relaxation. The weights and the
policy come from `dmd_jax.checkpoints` (`load_pretrained`, `load_weights`,
`load_model`); the padded graph from `dmd_jax.graph`.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from dmd_jax import shape_ladder
from dmd_jax.checkpoints import as_bundle
from dmd_jax.consistency import (
    STILL_REASON,
    exact_tolerance,
    exact_vertices,
    oriented_faces,
    scale_groups,
    still_vertices,
)
from dmd_jax.encoding import mesh_frame
from dmd_jax.forward import predictor
from dmd_jax.graph import (
    build_mesh_graph,
    check_aggregation,
    pad_mesh_graph,
    pad_vertex_array,
    undirected_vertex_edges,
)
from dmd_jax.memory_plan import plan, whole_without_measuring
from dmd_jax.mesh import face_normals_np, validate_mesh
from dmd_jax.patch_runner import denoise_patches
from dmd_jax.policy import (
    MAX_PASSES_LIMIT,
    MAX_RELAX_STEPS,
    PRESMOOTH_RULE,
    DenoisePolicy,
    check_count,
    presmooth_plan,
    run_passes,
)
from dmd_jax.topology import adjacent_faces, edge_groups

# The most owned vertices a caller may force per patch (a bound on one patch's graph).
MAX_PATCH_SIZE = 2**31 - 1
# The longest `repr(DenoiseInfo)`: a summary a notebook prints on one screen.
INFO_REPR_MAX = 2000
# Sequences longer than this show as their length in the summary.
_REPR_MAX_ITEMS = 8


def _summary(value) -> str:
    """A short text for one field of `DenoiseInfo`'s repr: arrays by shape and dtype,
    long sequences by length, configs field by field, floats to 4 significant digits."""
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"array[{', '.join(map(str, value.shape))}] {value.dtype}"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list | tuple) and len(value) > _REPR_MAX_ITEMS:
        return f"<{type(value).__name__} of {len(value)}>"
    if hasattr(value, "to_dict") and dataclasses.is_dataclass(value):
        inner = (f"{f.name}={_summary(getattr(value, f.name))}" for f in dataclasses.fields(value))
        return f"{type(value).__name__}({', '.join(inner)})"
    return repr(value)


@dataclasses.dataclass(frozen=True)
class DenoiseInfo:
    """How a `denoise` call ran (`return_info=True`).

    Attributes:
      path: `"whole"` (the network on the mesh at once) or `"patches"`.
      budget_bytes: the memory budget planned with; None for a small mesh run whole.
      passes: network passes run.
      presmooth_steps: uniform Laplacian steps run before the network.
      roughness: the noisy mesh's roughness in degrees when the policy's rule chose the
        steps, else None.
      relax_steps: tangential relaxation steps run after the network.
      unused_vertices: vertices no face references (returned exactly as given).
      policy: the policy the call ran (the weights' with the caller's overrides).
      patch_size, patches, largest_padded_vertices, halo_rings, devices: for the patch
        path, the owned vertices per patch, patches run over every pass, the largest
        padded patch, the halo depth in rings and the devices used; else None.
      flipped_faces: faces whose winding was flipped to agree with their component's
        (`consistency.oriented_faces`; the returned mesh keeps the caller's faces).
      exact_vertices: vertices of exactly flat faces, creases and corners held where
        they are (`consistency.exact_vertices`; 0 on a noisy mesh).
      scale_groups: runs of components of very different sizes
        (`consistency.scale_groups`); the other fields are those of the largest's run,
        but `flipped_faces`, `exact_vertices` and `still_vertices`, summed.
      still_vertices: vertices of parts with nothing to denoise (all creases, a lone
        triangle, no area: `consistency.still_faces`), returned exactly as given.
      unchanged: why the whole mesh came back as given, without any work (`path` is
        then `"unchanged"`); None when the network ran.
      controller: what the learned smoothing controller chose and from what, in one
        line (`controller.Decision.describe`), when it chose; None otherwise. With
        `path` `"no network"`, it chose no network pass.

    Its `repr` is a summary of at most `INFO_REPR_MAX` characters (fields that are None
    left out, arrays shown by shape, long sequences by length); every field stays
    reachable as an attribute.
    """

    path: str
    budget_bytes: int | None
    passes: int
    presmooth_steps: int
    roughness: float | None
    relax_steps: int
    unused_vertices: int
    policy: DenoisePolicy
    patch_size: int | None = None
    patches: int | None = None
    largest_padded_vertices: int | None = None
    halo_rings: int | None = None
    devices: int | None = None
    flipped_faces: int = 0
    exact_vertices: int = 0
    scale_groups: int = 1
    still_vertices: int = 0
    unchanged: str | None = None
    controller: str | None = None

    def __repr__(self) -> str:
        parts = (
            f"{f.name}={_summary(getattr(self, f.name))}"
            for f in dataclasses.fields(self)
            if getattr(self, f.name) is not None
        )
        text = f"{type(self).__name__}({', '.join(parts)})"
        return text if len(text) <= INFO_REPR_MAX else text[: INFO_REPR_MAX - 5] + " ...)"


def whole_mesh_graph(
    faces: np.ndarray, n_vertex: int, aggregation: str, *, groups=None, face_pairs=None
):
    """The padded graph the whole-mesh path runs on, as NumPy: padded to its rung of the
    shape ladder, with the tables `aggregation` asks for at fixed widths
    (`shape_ladder.with_tables`), so that a compiled program serves every mesh of its
    rung (`dmd-jax warmup` compiles them in advance). `groups` and `face_pairs`: the
    faces' edge sort, if known (`graph.build_mesh_graph`)."""
    graph = build_mesh_graph(faces, n_vertex, groups=groups, face_pairs=face_pairs)
    graph = pad_mesh_graph(graph, shape_ladder.padded_sizes(graph))
    return shape_ladder.with_tables(graph, aggregation)


def _whole_mesh_pass(v, f, bundle, aggregation: str, topology: list | None = None):
    """`(frame, one_pass)`: the network's frame of the whole mesh `v` and one network
    pass over it (frame positions -> frame positions, float64 on the host).

    `topology`: a list `[groups, face_pairs]`, the edge sort of `f` if known
    (`whole_mesh_graph`), handed over: it is emptied here, so that no frame holds the
    arrays through the passes (about 100 MB at 1M faces).
    """
    groups, pairs = topology if topology else (None, None)
    if topology:
        topology.clear()
    # The padded graph does not change between passes: build it (edge lists, ELL
    # tables) and move it to the device once, not once per pass.
    graph = whole_mesh_graph(f, v.shape[0], aggregation, groups=groups, face_pairs=pairs)
    del groups, pairs
    edges = undirected_vertex_edges(graph)
    frame = mesh_frame(bundle.config.model.encoding, v, f, edges=edges)
    # `device_put`, not `jnp.asarray`: the same transfer without a copy program per
    # array shape, each traced and compiled in a fresh process (docs/cold-start.md).
    graph = jax.tree.map(jax.device_put, graph)
    predict = predictor(bundle.config)
    n, n_padded = v.shape[0], graph.n_vertex

    def one_pass(x):
        # As training pads the noisy positions: float32, zeros on padding rows. The
        # padding is cut on the host (a device slice is a program per padded shape).
        noisy = pad_vertex_array(x.astype(np.float32), n_padded)
        return np.asarray(predict(bundle.params, jax.device_put(noisy), graph))[:n].astype(
            np.float64
        )

    return frame, one_pass


def _preload_whole(bundle, n_vertex: int, f, aggregation: str, max_memory, patch_size) -> None:
    """Starts loading the whole-mesh program of this mesh from the compile cache in the
    background (`forward.Program.preload`), when the memory plan will surely run it
    whole, so that the load overlaps the host work before the first pass (orientation,
    the exact and still vertices, the pre-smoothing, the graph: docs/cold-start.md).

    The rung is guessed from the counts (`shape_ladder.rung_estimate`, exact for a
    closed manifold mesh) and the table layout from the faces around each vertex; a
    wrong guess costs a load in the background, and the pass loads or compiles its own
    program as it would have.
    """
    model = bundle.config.model
    if not whole_without_measuring(model, n_vertex, f.shape[0], max_memory, patch_size):
        return
    if aggregation == "segment_sum":
        widths = (None, None)
    elif int(np.bincount(f.ravel()).max()) < shape_ladder.MAX_ELL_WIDTH - 1:
        widths = shape_ladder.STANDARD_WIDTHS  # every valence fits its table
    elif aggregation == "auto":
        widths = (None, shape_ladder.STANDARD_WIDTHS[1])  # the vertex table left out
    else:
        return
    rung = shape_ladder.rung_estimate(n_vertex, f.shape[0])
    noisy = jax.ShapeDtypeStruct((rung, 3), np.float32)  # as `one_pass` pads it
    graph = shape_ladder.abstract_graph(rung, widths)
    predictor(bundle.config).preload(bundle.params, noisy, graph)


def _denoise_whole(v, f, bundle, policy: DenoisePolicy, aggregation: str, held=None, topology=None):
    """The whole mesh at once; float64 positions in the input frame and the passes run
    (`held`: vertices kept where they are, `policy.run_passes`; `topology`: as
    `_whole_mesh_pass`'s)."""
    frame, one_pass = _whole_mesh_pass(v, f, bundle, aggregation, topology)
    x, done = run_passes(one_pass, frame.apply(v), policy, held)
    return frame.invert(x), done


def network_passes(vertices, faces, bundle, passes: int, aggregation: str = "auto", *, held=None):
    """Yields the mesh after each of `passes` network passes, as `denoise` chains them
    in one frame (no pre-smoothing, no relaxation): the search over pass counts of
    `dmd_jax.data.smoothing_set` reads every count from one run.

    Args:
      vertices: `[n_vertex, 3]` float64, every vertex referenced.
      faces: `[n_face, 3]` consistently wound.
      bundle: a `ModelBundle`.
      passes: how many.
      aggregation: as `denoise`'s.
      held: optional `[n_vertex]` bool, the vertices `denoise` holds where they are
        (`consistency.exact_vertices`, `still_vertices`): put back after every pass,
        as `policy.run_passes` does.

    Yields:
      `[n_vertex, 3]` float64 positions in the input frame, after pass 1, 2, ...
    """
    v = np.asarray(vertices, np.float64)
    frame, one_pass = _whole_mesh_pass(v, np.asarray(faces), bundle, aggregation)
    x = frame.apply(v)
    start = x.copy()
    hold = held is not None and bool(np.any(held))
    for _ in range(passes):
        x = one_pass(x)
        if hold:
            x[held] = start[held]
        if not np.all(np.isfinite(x)):
            raise ValueError("the network produced non-finite vertices (broken weights?)")
        yield frame.invert(x)


def _referenced(v: np.ndarray, f: np.ndarray):
    """The vertices faces reference and the faces renumbered onto them, or None when
    every vertex is referenced. Unused vertices (stray scan points) must not enter the
    frame or any statistic: one far away costs the mesh its float32 precision."""
    used = np.zeros(v.shape[0], bool)
    used[f.ravel()] = True
    if used.all():
        return None
    index = np.cumsum(used, dtype=np.int64) - 1
    return used, v[used], index[f].astype(np.int32)


def _prenormalised(v: np.ndarray):
    """`v` centred on its bounding box and divided by a power of two near its extent.

    Dividing by a power of two is exact, so the result is the same function of the
    mesh at any scale float64 holds: normals and squared lengths of a mesh at 1e-150
    would otherwise underflow, and at 1e150 overflow.

    Returns:
      The positions, the centre and the scale (`v ≈ x * scale + centre`).
    """
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * lo + 0.5 * hi  # halves first: no overflow near the float64 limit
    half = float(np.max(0.5 * hi - 0.5 * lo))
    if not half > 0:
        raise ValueError("the mesh has zero extent: every referenced vertex is at one point")
    scale = float(2.0 ** min(int(np.round(np.log2(half))) + 1, 1023))
    return (v - centre) / scale, centre, scale


def denoise(
    vertices,
    faces=None,
    params=None,
    *,
    policy: DenoisePolicy | None = None,
    iterations: int | None = None,
    presmooth: int | str | None = None,
    relax: int | None = None,
    aggregation: str = "auto",
    max_memory=None,
    patch_size: int | None = None,
    progress: bool | None = None,
    devices=None,
    config=None,
    controller: bool | None = None,
    return_info: bool = False,
):
    """Denoises a triangle mesh with a trained DMD-Net, in bounded memory.

    The mesh is mapped to the frame of the model's encoding (`encoding.mesh_frame`:
    bounding box centred, and longest side 1 or mean edge length 1), denoised, and
    mapped back, so the result is translation- and scale-equivariant. Only vertices some
    face references enter the frame and the network; unused ones come back exactly as
    given.

    A mesh whose whole-mesh run fits `max_memory` runs at once. A larger one runs patch
    by patch (`dmd_jax.patch_runner`): compact owned vertex sets, each grown by a halo
    as deep as the network's receptive field, the per-mesh pools computed first over all
    patches. The result equals the whole-mesh run up to float32 summation order
    (`tests/test_patches.py`).

    Args:
      vertices: `[n_vertex, 3]` in any frame; float16/32/64 or integer. A
        `trimesh.Trimesh` (or anything with `.vertices` and `.faces`) may stand for both
        `vertices` and `faces`.
      faces: `[n_face, 3]` integer indices.
      params: a `ModelBundle` (from `load_pretrained()`, `load_weights()` or a training
        checkpoint via `load_model`), a path for `load_model`, raw params with
        `config`, or None (default): the bundled weights.
      policy: how to run the network (`dmd_jax.policy.DenoisePolicy`); default: the
        policy stored with the weights (`bundle.policy`).
      iterations: a fixed number of network passes, each starting from the last,
        instead of the policy's pass rule.
      presmooth: a fixed number of uniform Laplacian steps before the network
        (`dmd_jax.presmooth`) instead of the policy's rule; 0 gives the network the
        mesh as it is; `"rule"` (`policy.PRESMOOTH_RULE`), like None, runs the rule.
      relax: steps of feature-preserving tangential relaxation of the result
        (`dmd_jax.relax.relax_tangential`) instead of the policy's; for noise with a
        tangential part (per-coordinate noise): the network moves vertices along normals
        only. About 300 bytes per vertex, on the whole mesh.
      aggregation: how the GCN aggregations run (`graph.AGGREGATIONS`; the same operator
        either way, equal up to float summation order): `"ell"` through padded
        neighbour tables (faster on CPU, no scatter), `"segment_sum"` over the edge
        lists, as in training, or `"auto"`: the tables unless one is padded to more than
        `graph.AUTO_MAX_FILL` slots per edge. Attention models use the edge lists.
      max_memory: the memory this call may use beyond what the process holds when it
        starts, in bytes or as a string (`"6GiB"`, `"8GB"`); default
        `memory_plan.DEFAULT_MEMORY_FRACTION` of the memory available.
      patch_size: owned vertices per patch; forces the patch path (tests, tuning).
        Default: the largest patches the budget allows.
      progress: a tqdm progress bar over the patches on stderr (default: when stderr is a
        terminal and there are several patches).
      devices: the devices patches run on (default `jax.local_devices()`).
      config: the experiment config, only with raw params.
      controller: whether the learned smoothing controller stored with the weights
        (`dmd_jax.controller`) chooses the pre-smoothing steps, the passes and the
        vertex update from the mesh's statistics. None (default): as the weights'
        policy says (`DenoisePolicy.controller`), unless the caller fixed `policy`,
        `iterations` or `presmooth`; True: always (a `ValueError` when the weights hold
        none); False: never.
      return_info: also return a `DenoiseInfo` saying how the call ran.

    Returns:
      `[n_vertex, 3]` denoised vertices in the input frame and order (float32 for
      float32 input, float64 otherwise); with `return_info`, `(vertices, DenoiseInfo)`.

    Raises:
      ValueError: bad mesh (see `dmd_jax.mesh.validate_mesh`), bad params or policy, a
        count out of range, an unknown `aggregation`, a bad `max_memory` or
        `patch_size`, or a budget too small for a single patch (the message names the
        budget and what one patch needs).
      TypeError: `faces` missing for plain arrays.
    """
    if faces is None and hasattr(vertices, "vertices") and hasattr(vertices, "faces"):
        vertices, faces = vertices.vertices, vertices.faces
    if faces is None:
        raise TypeError(
            "denoise needs faces: pass denoise(vertices, faces) or a mesh object with "
            ".vertices and .faces (e.g. a trimesh.Trimesh)"
        )
    from dmd_jax.presmooth import MAX_STEPS

    # Every count is checked before any work.
    if iterations is not None:
        check_count("iterations", iterations, minimum=1, most=MAX_PASSES_LIMIT)
    if relax is not None:
        check_count("relax", relax, most=MAX_RELAX_STEPS)
    if presmooth is not None and not (isinstance(presmooth, str) and presmooth == PRESMOOTH_RULE):
        check_count("presmooth", presmooth, most=MAX_STEPS)
    check_aggregation(aggregation)
    if patch_size is not None:
        check_count("patch_size", patch_size, minimum=1, most=MAX_PATCH_SIZE)
    if policy is not None and not isinstance(policy, DenoisePolicy):
        raise ValueError(f"policy must be a DenoisePolicy, got {type(policy).__name__}")
    v, f = validate_mesh(vertices, faces)
    in_dtype = np.asarray(vertices).dtype
    bundle = as_bundle(params, config)
    run = (bundle.policy if policy is None else policy).overridden(
        iterations=iterations, relax=relax
    )

    referenced = _referenced(v, f)
    if referenced is not None:
        used, v, f = referenced
    chooser = _controller_for(bundle, controller, policy, iterations, presmooth)
    args = (bundle, run, presmooth, aggregation, max_memory, patch_size, devices, progress, chooser)
    groups = scale_groups(v, f)
    if groups is None:
        out, fields = _denoise_referenced(v, f, in_dtype, *args)
    else:
        # Parts of very different sizes: one run each, in its own frame.
        out, runs = np.empty_like(v), []
        for group in groups:
            index = np.cumsum(group) - 1
            faces_of = f[group[f[:, 0]]]
            out[group], part = _denoise_referenced(v[group], index[faces_of], in_dtype, *args)
            runs.append(part)
        fields = {
            **runs[0],
            "flipped_faces": sum(r["flipped_faces"] for r in runs),
            "exact_vertices": sum(r["exact_vertices"] for r in runs),
            "still_vertices": sum(r["still_vertices"] for r in runs),
            "scale_groups": len(runs),
        }
    out_dtype = np.float32 if in_dtype == np.float32 else np.float64
    if referenced is not None:
        full = np.array(vertices, dtype=out_dtype, copy=True)
        full[used] = out
        out = full
    out = out.astype(out_dtype, copy=False)
    if not return_info:
        return out
    unused = 0 if referenced is None else int((~used).sum())
    relax_steps = fields.pop("relax_steps", run.relax_steps)
    return out, DenoiseInfo(**fields, relax_steps=relax_steps, unused_vertices=unused, policy=run)


def _controller_for(bundle, controller, policy, iterations, presmooth):
    """The `ControllerParams` that choose the amount of smoothing of this call, or None
    (`denoise`'s `controller` argument).

    Raises:
      ValueError: `controller=True` with weights that hold none, or not a bool/None.
    """
    if controller is not None and not isinstance(controller, bool):
        raise ValueError(f"controller must be True, False or None, got {controller!r}")
    if controller is False:
        return None
    if bundle.controller is None:
        if controller:
            raise ValueError(
                "controller=True, but these weights hold no smoothing controller "
                "(dmd-jax export-weights --controller adds one)"
            )
        return None
    if controller:
        return bundle.controller
    fixed = policy is not None or iterations is not None or presmooth is not None
    return bundle.controller if bundle.policy.controller and not fixed else None


def _denoise_referenced(
    v,
    f,
    in_dtype,
    bundle,
    run,
    presmooth,
    aggregation,
    max_memory,
    patch_size,
    devices,
    progress,
    chooser=None,
):
    """`denoise` of a mesh whose every vertex is referenced, in one frame: its winding
    made consistent and its exact vertices (to the precision of `in_dtype`, the caller's
    number format) held (`dmd_jax.consistency`).

    Returns:
      `[n_vertex, 3]` float64 positions in the input frame, and the `DenoiseInfo` fields
      of the run (but `relax_steps`, `unused_vertices` and `policy`).
    """
    from dmd_jax.presmooth import laplacian_steps
    from dmd_jax.relax import relax_tangential

    if chooser is None:  # the controller may change the program's config: after it
        _preload_whole(bundle, v.shape[0], f, aggregation, max_memory, patch_size)
    f, flipped = oriented_faces(f, v.shape[0])
    x, centre, scale = _prenormalised(v)  # refuses a mesh of one point first
    # One sort of the faces' edges serves every test and the graph: the edge-adjacent
    # pairs (both tests), the unique edges (the tolerance's mean edge length).
    groups = edge_groups(f, v.shape[0])
    pairs = adjacent_faces(groups, f.shape[0])
    still = still_vertices(v, f, pairs=pairs)
    if still.all():
        # Nothing to denoise (all creases, or no area): the mesh as given, no work.
        fields = dict(
            path="unchanged",
            budget_bytes=None,
            passes=0,
            presmooth_steps=0,
            roughness=None,
            relax_steps=0,
            flipped_faces=flipped,
            still_vertices=int(still.sum()),
            unchanged=STILL_REASON,
        )
        return v.copy(), fields
    edges = groups.edges(v.shape[0])
    # The face normals of `x`, read by the exact-vertex test and the roughness.
    normals = face_normals_np(x, f)
    tolerance = exact_tolerance(in_dtype, v, f, edges=edges)
    held = exact_vertices(x, f, tolerance, pairs=pairs, normals=normals) | still
    if not held.any():
        held = None  # a noisy mesh: every path exactly as without the test
    decision = None
    if chooser is not None:
        from dmd_jax.controller import decide

        decision = decide(chooser, x, f)
        presmooth = decision.option.presmooth
        if decision.option.passes:
            bundle = bundle.with_vertex_update(decision.option.update)
            run = run.replace(max_passes=decision.option.passes, pass_tolerance=0.0)
    network = decision is None or decision.option.passes > 0
    if decision is not None and network:
        _preload_whole(bundle, v.shape[0], f, aggregation, max_memory, patch_size)
    pre = presmooth_plan(
        run, x, f, presmooth, free=None if held is None else ~held, normals=normals
    )
    # What the checks computed is not needed through the passes: the edge sort goes to
    # the whole-mesh graph (`_whole_mesh_pass` empties the list), the rest is dropped.
    topology = [groups, pairs]
    del groups, pairs, edges, normals
    if pre.steps:
        start, x = x, laplacian_steps(x, f, pre.steps)
        if held is not None:
            x[held] = start[held]
        del start
    memory = plan(bundle.config.model, x.shape[0], f.shape[0], max_memory, patch_size)
    extra = {}
    if not network:
        passes = 0
    elif memory.whole:
        x, passes = _denoise_whole(x, f, bundle, run, aggregation, held, topology)
    else:
        topology.clear()
        x, stats = denoise_patches(
            x, f, bundle, run, aggregation, memory.budget, patch_size, devices, progress, held
        )
        passes = stats.passes
        extra = stats._asdict()
        del extra["passes"]
    if run.relax_steps:
        start, x = x, relax_tangential(x, f, run.relax_steps)
        if held is not None:
            x[held] = start[held]
    fields = dict(
        path="no network" if not network else "whole" if memory.whole else "patches",
        budget_bytes=memory.budget,
        passes=passes,
        presmooth_steps=pre.steps,
        roughness=pre.roughness,
        flipped_faces=flipped,
        exact_vertices=0 if held is None else int((held & ~still).sum()),
        still_vertices=int(still.sum()),
        controller=None if decision is None else decision.describe(),
        **extra,
    )
    out = x * scale + centre
    if not network and not pre.steps and not run.relax_steps:
        out = v.copy()  # the controller chose nothing: the mesh exactly as given
    out[still] = v[still]  # exactly as given, not through the frame's rounding
    return out, fields
