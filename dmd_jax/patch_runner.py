"""The patch path of `denoise`: a mesh too large for its memory budget, patch by patch.

First the per-mesh pools (the transformer's `W_tf`, the STN's), summed over the patches,
then every patch with those pools, keeping its owned vertices (`dmd_jax.patches` grows
the patches). The result equals the whole-mesh run up to float32 summation order.
Patches are dispatched to every local device (`jax.local_devices()`), one in flight per
accelerator, while the host prepares the next.
"""

from __future__ import annotations

import math
import sys
from collections import deque
from typing import NamedTuple

import jax
import numpy as np

from dmd_jax import patches as patch_lib
from dmd_jax.forward import patch_predictor, pool_predictor
from dmd_jax.graph import (
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    sizes_for_vertices,
    widen_ell_layout,
    with_aggregation_layout,
)
from dmd_jax.memory_plan import (
    HOST_BYTES_PER_PADDED_VERTEX,
    format_bytes,
    mesh_bytes,
    network_bytes_per_vertex,
)
from dmd_jax.mesh import CanonicalFrame, canonical_frame
from dmd_jax.policy import DenoisePolicy, run_passes

# Owned sets are graph Voronoi cells of a target size (`patches.compact_partition`); on
# noisy grids of 5M faces, cells of 100k-200k vertices spanned 0.65-1.5 times the target
# with a median of 0.95. The patch size is chosen so that a cell this many times the
# target still fits the budget; larger ones are split.
CELL_SLACK = 1.25


class PatchStats(NamedTuple):
    """How a patch-wise run went (for `inference.DenoiseInfo`)."""

    passes: int
    patch_size: int
    patches: int
    largest_padded_vertices: int
    halo_rings: int
    devices: int


def denoise_patches(
    v: np.ndarray,
    f: np.ndarray,
    bundle,
    policy: DenoisePolicy,
    aggregation: str,
    budget: int | None,
    patch_size: int | None = None,
    devices=None,
    progress: bool | None = None,
    held: np.ndarray | None = None,
) -> tuple[np.ndarray, PatchStats]:
    """Denoises `v` (float64, input frame) patch by patch; returns float64 positions in
    the input frame and how it ran.

    Args:
      v: `[n_vertex, 3]` float64 positions.
      f: `[n_face, 3]` int32 faces.
      bundle: the `ModelBundle`.
      policy: the passes to run (`policy.run_passes`).
      aggregation: one of `graph.AGGREGATIONS`.
      budget: bytes for the call (patches sized to fit), or None with `patch_size`.
      patch_size: owned vertices per patch, forced; None sizes them from `budget`.
      devices: devices to spread the patches over (default `jax.local_devices()`).
      progress: a tqdm bar over the patches (None: when stderr is a terminal).
      held: `[n_vertex]` bool, vertices kept where they are (`policy.run_passes`).
    """
    cfg = bundle.config.model
    frame = lean_mesh_frame(cfg.encoding, v, f)
    x = frame.apply(v)
    runner = PatchRunner(bundle, f, v.shape[0], aggregation, devices, progress)
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

    x, done = run_passes(one_pass, x, policy, held)
    stats = PatchStats(
        passes=done,
        patch_size=runner.patch_size,
        patches=patches_run,
        largest_padded_vertices=runner.largest_patch,
        halo_rings=runner.halo.output,
        devices=len(runner.devices),
    )
    return frame.invert(x), stats


def _ell_widths(graph) -> tuple:
    return tuple(
        None if e is None else e.neighbours.shape[1] for e in (graph.vertex_ell, graph.face_ell)
    )


def _widen_ell(graph, widths):
    """`graph` with its ELL tables widened to `widths` (`graph.widen_ell_layout`: unused
    slots that change nothing); a table that is None on either side, or already as wide,
    stays as it is."""
    out = [
        ell
        if ell is None or width is None or ell.neighbours.shape[1] >= width
        else widen_ell_layout(ell, width)
        for ell, width in zip((graph.vertex_ell, graph.face_ell), widths, strict=True)
    ]
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


class PatchRunner:
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
        room = budget - mesh_bytes(self.n_vertex, self.faces.shape[0])
        self.max_padded_vertices = room // per_vertex
        if self.max_padded_vertices < 256:
            raise ValueError(
                f"the memory budget of {format_bytes(budget)} leaves "
                f"{format_bytes(max(room, 0))} for patches after the mesh's own arrays "
                f"({format_bytes(mesh_bytes(self.n_vertex, self.faces.shape[0]))}); a "
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
            graph = with_aggregation_layout(graph, self.aggregation)
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
                        f"the memory budget of {format_bytes(self.budget)} cannot hold a "
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
            predict = pool_predictor(self.cfg, names)
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
        predict = patch_predictor(self.cfg)
        result = np.empty_like(x)

        def run_fn(device, patch, graph):
            args = self._inputs(device, x, patch, graph, pooled, owned_mask=False)
            return predict(self._device_params(device), *args)

        desc = f"patches {n_pass}/{n_pass}" if n_pass > 1 else "patches"
        for patch, out in self._sweep(x, self.halo.output, run_fn, desc):
            keep = patch.owned
            result[patch.vertices[keep]] = out[: patch.vertices.size][keep]
        return result
