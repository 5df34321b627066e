"""Input pipeline: shuffling, rotation augmentation, mixed noise and bucketed padding.

Every batch is a pure function of `(seed, step)` and the dataset, so any step of any run
can be rebuilt exactly (that is what makes resume bit-identical). A training batch is
one group of meshes per device, each group a padded disjoint union, all padded to the
same sizes and stacked on a leading axis (one group on one device); the sizes come from
one vertex bucket (`graph.sizes_for_vertices`), so an epoch compiles one program per
bucket it touches.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import numpy as np

from dmd_jax import noise as noise_lib
from dmd_jax.config import NoiseConfig
from dmd_jax.encoding import LocalInputs, local_inputs, mesh_frame, rotate_local_inputs
from dmd_jax.graph import (
    MAX_ELL_WIDTH,
    MeshGraph,
    PaddedSizes,
    batch_mesh_graphs,
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    sizes_for_vertices,
    with_ell_layout,
    with_fixed_ell,
)
from dmd_jax.mesh import canonical_frame


class MeshExample(NamedTuple):
    """One clean mesh and its graph, built once on the host.

    `view`: for a range-image mesh (`dmd_jax.scan.simulate_scan`) or a mesh meant to be
    seen by one sensor, the direction it was scanned along `[3]`: its noise is then always
    the scanner kind along that view (rotated with the mesh). None: `NoiseConfig` decides.
    """

    vertices: np.ndarray  # [n_vertex, 3] float
    faces: np.ndarray  # [n_face, 3] int32
    graph: MeshGraph
    view: np.ndarray | None = None


class Batch(NamedTuple):
    """A padded batch: noisy input, clean target and the graph, in the model's frames.

    One padded disjoint union (`collate`: `noisy [n_vertex, 3]`), or in training the
    groups of a step stacked on a leading axis (`training_batch`: `noisy [n_group,
    n_vertex, 3]`, every `graph` array `[n_group, ...]`). `local`: the `"local"`
    encoding's inputs of `noisy`, computed beforehand (`CandidatePool`: vertex
    `[(n_group,) n_vertex, V]`, candidates `[(n_group,) n_face, K, 3]`), or None (an
    empty pytree): the model computes them in the step.
    """

    noisy: np.ndarray  # [(n_group,) n_vertex, 3] float32
    clean: np.ndarray  # [(n_group,) n_vertex, 3] float32
    graph: MeshGraph
    local: LocalInputs | None = None


def make_examples(meshes: Sequence[tuple]) -> list[MeshExample]:
    """Builds the host-side graph of every `(vertices, faces)` pair once; a triple
    `(vertices, faces, view)` also gives the example a view (`MeshExample.view`)."""
    out = []
    for mesh in meshes:
        vertices, faces = mesh[0], mesh[1]
        view = None if len(mesh) < 3 or mesh[2] is None else np.asarray(mesh[2], np.float64)
        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int32)
        out.append(MeshExample(v, f, build_mesh_graph(f, v.shape[0]), view))
    return out


def collate(
    noisy: Sequence[np.ndarray],
    clean: Sequence[np.ndarray],
    graphs: Sequence[MeshGraph],
    sizes: PaddedSizes | None = None,
) -> Batch:
    """Joins meshes into one padded disjoint union.

    Args:
      noisy, clean: per mesh, `[n_i, 3]` positions.
      graphs: per mesh, its `MeshGraph`.
      sizes: the padded sizes (default: the group's own bucket, `graph.padded_sizes_for`).
    """
    graph = batch_mesh_graphs(list(graphs))
    if sizes is None:
        sizes = padded_sizes_for(graph)
    padded = pad_mesh_graph(graph, sizes)
    return Batch(
        noisy=pad_vertex_array(np.concatenate(noisy).astype(np.float32), sizes.n_vertex),
        clean=pad_vertex_array(np.concatenate(clean).astype(np.float32), sizes.n_vertex),
        graph=padded,
    )


def random_rotation(key) -> np.ndarray:
    """A uniformly distributed rotation matrix `[3, 3]` (QR of a Gaussian, sign-fixed)."""
    g = np.asarray(jax.random.normal(key, (3, 3), dtype=np.float32), np.float64)
    q, r = np.linalg.qr(g)
    q = q * np.sign(np.diag(r))[None, :]
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def corrupt(
    key,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    rotate: bool,
    noise: NoiseConfig,
    encoding: str = "xyz",
    view: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, noise_lib.NoiseSpec]:
    """Rotates (optionally) and noises one clean mesh.

    Both outputs are expressed in the frame of the *noisy* mesh that the model's
    `encoding` works in (`dmd_jax.encoding.mesh_frame`), the frame that `denoise` will
    use at inference time, so training sees what inference sees. With a `view` (a scan's
    `[3]` sensor direction) the noise is the scanner kind along the rotated view, at one
    of `noise.scanner_levels`.

    Returns:
      `(noisy [n, 3], clean [n, 3], spec)`.
    """
    k_rot, k_noise = jax.random.split(key)
    v = np.asarray(vertices, np.float64)
    if rotate:
        rotation = random_rotation(k_rot)
        v = v @ rotation.T
        view = None if view is None else rotation @ np.asarray(view, np.float64)
    v = canonical_frame(v).apply(v)
    scanner_levels = (
        noise_lib.SCANNER_LEVELS if noise.scanner_levels is None else noise.scanner_levels
    )
    noisy, spec = noise_lib.add_mixed_noise(
        k_noise,
        v,
        faces,
        kinds=noise.kinds if view is None else (noise_lib.SCANNER_KIND,),
        # Unset levels (None) are the sampler's defaults: the paper's.
        canonical_levels=None if noise.canonical_levels is None else dict(noise.canonical_levels),
        edge_levels=noise_lib.EDGE_LEVELS if noise.edge_levels is None else noise.edge_levels,
        p_edge=noise.p_edge,
        p_normal=noise.p_normal,
        p_clean=noise.p_clean,
        p_scanner=noise.p_scanner,
        scanner_levels=scanner_levels,
        view=view,
    )
    noisy = np.asarray(noisy, np.float64)
    frame = mesh_frame(encoding, noisy, faces)
    return frame.apply(noisy), frame.apply(v), spec


def step_key(seed: int, step: int):
    """The PRNG key of one training step: fold the step into the run's seed."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), step)


def batch_indices(step: int, n_examples: int, batch_size: int, seed: int) -> np.ndarray:
    """Indices of the meshes of `step`: consecutive slices of a per-epoch permutation."""
    if n_examples <= 0:
        raise ValueError("the training set is empty")
    positions = step * batch_size + np.arange(batch_size)
    epochs, offsets = np.divmod(positions, n_examples)
    out = np.empty(batch_size, np.int64)
    for epoch in np.unique(epochs):
        perm = np.random.default_rng([seed, int(epoch)]).permutation(n_examples)
        sel = epochs == epoch
        out[sel] = perm[offsets[sel]]
    return out


def split_slots(batch_size: int, n_group: int) -> list[np.ndarray]:
    """Slots `0..batch_size-1` of a global batch, cut into `n_group` contiguous groups
    whose sizes differ by at most one."""
    if n_group < 1 or batch_size < n_group:
        raise ValueError(
            f"a global batch of {batch_size} meshes cannot feed {n_group} devices "
            "(every device needs at least one mesh)"
        )
    return np.array_split(np.arange(batch_size), n_group)


def common_sizes(groups: Sequence[Sequence[MeshGraph]]) -> PaddedSizes:
    """Padded sizes that hold the disjoint union of every group (one vertex bucket).

    They depend only on which meshes a step draws, not on the noise, so every process
    of a multi-host run computes them alike without building the others' groups.

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


def largest_sizes(examples: Sequence[MeshExample], per_group: int) -> PaddedSizes:
    """Padded sizes that hold any `per_group` of the examples: one bucket for every batch.

    Each count (vertices, faces, edges) is `per_group` times the largest mesh's, an
    upper bound of any group's (a batch may draw one mesh twice across an epoch
    boundary), so `training_batch(..., sizes=largest_sizes(...))` never outgrows it and
    the step compiles once.

    Args:
      examples: the meshes a batch may draw.
      per_group: meshes per group (`ceil(batch_size / n_group)`).
    """
    if not examples or per_group < 1:
        raise ValueError("largest_sizes needs examples and per_group >= 1")

    def top(fn):
        return per_group * max(int(fn(ex.graph)) for ex in examples)

    return sizes_for_vertices(
        top(lambda g: g.n_vertex),
        top(lambda g: g.n_face),
        top(lambda g: g.vertex_senders.shape[0]),
        top(lambda g: g.face_senders.shape[0]),
        per_group,
    )


def size_classes(
    examples: Sequence[MeshExample], per_group: int, n_classes: int, *, samples: int = 4096
) -> list[PaddedSizes]:
    """A few padded sizes, increasing, that every batch of the examples fits in one of.

    The last is `largest_sizes` (any group fits); the others are the vertex buckets
    (`common_sizes`) at the quantiles `k / n_classes` of `samples` random groups (a
    fixed draw: the classes are a function of the examples). A step padded to the
    smallest class that holds it (`fit_class`) wastes less than one padded to the
    largest, and a run compiles `n_classes` programs, all known before its first step.

    Args:
      examples: the meshes a batch may draw.
      per_group: meshes per group.
      n_classes: how many sizes (>= 1); fewer come back where quantiles coincide.
    """
    top = largest_sizes(examples, per_group)
    if n_classes <= 1:
        return [top]
    picks = np.random.default_rng(0).integers(0, len(examples), (samples, per_group))
    found = sorted(
        (common_sizes([[examples[int(i)].graph for i in row]]) for row in picks),
        key=lambda s: s.n_vertex,
    )
    cut = [found[int(k / n_classes * (samples - 1))] for k in range(1, n_classes)]
    return sorted({*cut, top}, key=lambda s: s.n_vertex)


def fit_class(classes: Sequence[PaddedSizes], need: PaddedSizes) -> PaddedSizes:
    """The smallest of `classes` (increasing) that holds `need` in every count."""
    for c in classes:
        if all(have >= want for have, want in zip(c, need, strict=True)):
            return c
    raise ValueError(f"no padded size class holds {need}")


def step_sizes(
    examples: Sequence[MeshExample],
    step: int,
    classes: Sequence[PaddedSizes],
    *,
    batch_size: int,
    seed: int,
    n_group: int = 1,
) -> PaddedSizes:
    """The class (`size_classes`) the batch of `step` is padded to: the smallest that
    holds every group of it (`common_sizes`)."""
    idx = batch_indices(step, len(examples), batch_size, seed)
    slots = split_slots(batch_size, n_group)
    need = common_sizes([[examples[int(idx[j])].graph for j in s] for s in slots])
    return fit_class(classes, need)


def stack(batches: Sequence[Batch]) -> Batch:
    """Batches of equal padded sizes stacked on a new leading axis."""
    return jax.tree.map(lambda *xs: np.stack(xs), *batches)


def training_batch(
    examples: Sequence[MeshExample],
    step: int,
    *,
    batch_size: int,
    seed: int,
    noise: NoiseConfig,
    rotate: bool = True,
    encoding: str = "xyz",
    n_group: int = 1,
    groups: Sequence[int] | None = None,
    sizes: PaddedSizes | None = None,
) -> Batch:
    """The batch of `step`: a pure function of `(seed, step)` and the examples.

    Slot `j` of the global batch always gets the same mesh and noise, however the batch
    is split, so one device and several train on the same meshes.

    Args:
      examples: the training meshes.
      step: the step number.
      batch_size: meshes per step (the global batch, at least `n_group`).
      seed: the run's seed (shuffling, rotation, noise).
      noise: what the noise sampler may draw.
      rotate: random rotation augmentation.
      encoding: the model's encoding, which decides the frame (`encoding.mesh_frame`).
      n_group: groups the batch is split into (devices along the batch axis).
      groups: the groups to build (default all; pass `parallel.local_groups(mesh)` on
        several hosts). The padded sizes always account for every group.
      sizes: padded sizes to use instead of the step's own bucket (they must hold every
        group): runs trained side by side (`experiments.multiseed`) pad their batches
        to one common bucket so the batches stack.

    Returns:
      A `Batch` of the requested groups stacked on a leading axis, in order.
    """
    idx = batch_indices(step, len(examples), batch_size, seed)
    slots = split_slots(batch_size, n_group)
    if sizes is None:
        sizes = common_sizes([[examples[int(idx[j])].graph for j in s] for s in slots])
    key = step_key(seed, step)
    out = []
    for g in range(n_group) if groups is None else groups:
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
                view=ex.view,
            )
            noisy.append(n)
            clean.append(c)
            graphs.append(ex.graph)
        out.append(collate(noisy, clean, graphs, sizes))
    return stack(out)


def evaluation_batches(
    examples: Sequence[MeshExample],
    *,
    seed: int,
    noise: NoiseConfig,
    rotate: bool = True,
    encoding: str = "xyz",
    sizes: PaddedSizes | None = None,
) -> list[tuple[Batch, noise_lib.NoiseSpec]]:
    """One single-mesh batch per example with fixed noise (the same for every evaluation).

    `sizes`: pad every batch to these sizes (e.g. `largest_sizes(examples, 1)`: one
    compiled evaluation program) instead of each mesh's own bucket.
    """
    out = []
    base = jax.random.PRNGKey(seed)
    for i, ex in enumerate(examples):
        n, c, spec = corrupt(
            jax.random.fold_in(base, i),
            ex.vertices,
            ex.faces,
            rotate=rotate,
            noise=noise,
            encoding=encoding,
            view=ex.view,
        )
        out.append((collate([n], [c], [ex.graph], sizes), spec))
    return out


def unpadded_mesh(batch: Batch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The one mesh of a single-mesh batch without its padding.

    Returns:
      `(noisy [n_vertex, 3] float64, clean [n_vertex, 3] float64, faces [n_face, 3])`.
    """
    n = int(batch.graph.n_vertex_per_graph[0])
    nf = int(batch.graph.n_face_per_graph[0])
    faces = np.asarray(batch.graph.faces[:nf])
    return np.asarray(batch.noisy[:n], np.float64), np.asarray(batch.clean[:n], np.float64), faces


# ---------------------------------------------------------------- candidate pool
# Folded into the run's seed for the pool's draws, so that they are a stream of their
# own, apart from the per-step keys of `training_batch` and of the rotations.
_POOL_STREAM = 0x706F6F6C


def ell_widths(examples: Sequence[MeshExample]) -> tuple[int | None, int | None]:
    """The `(vertex, face)` ELL widths that hold any batch of `examples`, None where the
    widest exceeds `MAX_ELL_WIDTH`."""
    tables = [with_ell_layout(ex.graph) for ex in examples]
    vertex = max(t.vertex_ell.neighbours.shape[1] for t in tables)
    face = max(t.face_ell.neighbours.shape[1] for t in tables)
    return tuple(w if w <= MAX_ELL_WIDTH else None for w in (vertex, face))


# One jitted `encoding.local_inputs` per model config of the process, shared by its
# pools (a resumed or restarted run in one process compiles it once).
_ENCODE_PROGRAMS: dict = {}


def _encode_program(model) -> Callable:
    if model not in _ENCODE_PROGRAMS:
        _ENCODE_PROGRAMS[model] = jax.jit(lambda x, g: local_inputs(x, g, model))
    return _ENCODE_PROGRAMS[model]


class PoolEntry(NamedTuple):
    """One cached noisy draw of a training mesh, unpadded, in its model frame.

    `noisy`, `clean`: `[n_vertex, 3]` float32; `local`: its `LocalInputs` (vertex
    `[n_vertex, V]`, candidates `[n_face, K, 3]`, float32); `generation`: which draw of
    its pool slot it is.
    """

    noisy: np.ndarray
    clean: np.ndarray
    local: LocalInputs
    generation: int


class CandidatePool:
    """Training batches whose candidate fields are computed once per noisy draw.

    The `"local"` encoding's inputs (the bilateral and Taubin candidate normal fields and
    the vertex columns, `encoding.LocalInputs`) have no parameters: computing them in
    every step (`training_batch`) costs 40 % of a `small` step at the long run's 120
    filter passes. The pool keeps `draws` noisy draws per training mesh with those
    inputs computed once (outside the differentiated step) and trains on each draw
    `uses` times before replacing it:

    * step `s` trains on the meshes of `batch_indices(s, ...)`, as `training_batch`;
      position `q = s * batch_size + j` of the run visits its mesh in epoch
      `e = q // n_examples`, and takes slot `e % draws` of that mesh's pool, in its
      generation `(e // draws) // uses`. So each draw serves `uses` visits, and the
      pool is refreshed as the run goes, one mesh at a time;
    * the draw of (mesh, slot, generation) is `corrupt` with a key folded from the
      run's seed and those three numbers: a pure function of them. Draws are computed
      when first needed and kept (the latest generation of each slot), so the pool's
      state at any step is a function of the step, and a resumed run, whose pool starts
      empty, gets bit-identical batches;
    * each use is rotated afresh (a rotation from `(seed, step, slot)`), the noisy and
      clean positions and every 3-vector of the encoding together (the filters are
      rotation equivariant, `tests/test_candidate_pool.py`), so repeated draws are not
      repeated inputs. Without `rotate` neither the draws nor the uses are rotated.

    Batches carry ELL tables of fixed widths (`with_fixed_ell`, `ell_widths`: the
    widest of the training set, unless wider than `MAX_ELL_WIDTH`), the model's gather
    form of the same aggregations (8x faster pre-filters, 1.2x the network). With fixed padded
    `sizes` (`largest_sizes`) every batch has one shape: the step compiles once.

    Args:
      examples: the training meshes.
      model: the `ModelConfig` (its `"local"` encoding and filters).
      noise: what the noise sampler may draw.
      batch_size: meshes per step (the global batch).
      seed: the run's seed.
      draws: noisy draws kept per mesh (`TrainConfig.candidate_pool`, >= 1).
      uses: visits each draw serves (`TrainConfig.candidate_uses`).
      rotate: random rotation augmentation.
      n_group, groups, sizes: as in `training_batch`.
    """

    @classmethod
    def from_config(cls, examples: Sequence[MeshExample], cfg, **kw) -> CandidatePool:
        """The pool of an `ExperimentConfig`'s run: its model, noise, batch size, seed,
        rotation and `train.candidate_pool` / `candidate_uses`; `kw`: `n_group`,
        `groups`, `sizes`."""
        t = cfg.train
        return cls(
            examples,
            cfg.model,
            noise=cfg.noise,
            batch_size=t.batch_size,
            seed=t.seed,
            draws=t.candidate_pool,
            uses=t.candidate_uses,
            rotate=t.rotate,
            **kw,
        )

    def __init__(
        self,
        examples: Sequence[MeshExample],
        model,
        *,
        noise: NoiseConfig,
        batch_size: int,
        seed: int,
        draws: int = 1,
        uses: int = 4,
        rotate: bool = True,
        n_group: int = 1,
        groups: Sequence[int] | None = None,
        sizes: PaddedSizes | None = None,
    ):
        if model.encoding != "local":
            raise ValueError(
                "the candidate pool caches the 'local' encoding's inputs; this model's "
                f"encoding is {model.encoding!r} (set train.candidate_pool=0)"
            )
        if draws < 1 or uses < 1:
            raise ValueError(f"draws and uses must be >= 1, got {draws} and {uses}")
        if not examples:
            raise ValueError("the training set is empty")
        self.examples = list(examples)
        self.model, self.noise = model, noise
        self.batch_size, self.seed = batch_size, seed
        self.draws, self.uses, self.rotate = draws, uses, rotate
        self.n_group, self.groups, self.sizes = n_group, groups, sizes
        self.ell_widths = ell_widths(self.examples)
        # Every draw is encoded on its mesh padded to one size: one program.
        self._draw_sizes = largest_sizes(self.examples, 1)
        self._encode = _encode_program(model)
        self._entries: dict[tuple[int, int], PoolEntry] = {}
        self.encoded = 0  # draws encoded so far (`encoding.local_inputs` calls)

    def slot_of(self, step: int) -> list[tuple[int, int, int]]:
        """`(mesh, slot, generation)` of every position of the global batch of `step`."""
        n = len(self.examples)
        idx = batch_indices(step, n, self.batch_size, self.seed)
        epochs = (step * self.batch_size + np.arange(self.batch_size)) // n
        return [
            (int(i), int(e % self.draws), int(e // self.draws // self.uses))
            for i, e in zip(idx, epochs, strict=True)
        ]

    def entry(self, mesh: int, slot: int, generation: int) -> PoolEntry:
        """The draw `generation` of `slot` of `mesh`, encoded (cached: computed once)."""
        have = self._entries.get((mesh, slot))
        if have is not None and have.generation == generation:
            return have
        ex = self.examples[mesh]
        key = jax.random.fold_in(jax.random.PRNGKey(self.seed), _POOL_STREAM)
        key = jax.random.fold_in(jax.random.fold_in(key, mesh), slot)
        noisy, clean, _ = corrupt(
            jax.random.fold_in(key, generation),
            ex.vertices,
            ex.faces,
            rotate=self.rotate,
            noise=self.noise,
            encoding=self.model.encoding,
            view=ex.view,
        )
        noisy = noisy.astype(np.float32)
        graph = with_fixed_ell(pad_mesh_graph(ex.graph, self._draw_sizes), self.ell_widths)
        x = pad_vertex_array(noisy, self._draw_sizes.n_vertex)
        enc = jax.device_get(self._encode(x, graph))
        nv, nf = ex.graph.n_vertex, ex.graph.n_face
        local = LocalInputs(np.asarray(enc.vertex[:nv]), np.asarray(enc.candidates[:nf]))
        out = PoolEntry(noisy, clean.astype(np.float32), local, generation)
        self.encoded += 1
        # Only a later generation replaces a slot's draw: an older one asked for (the
        # two sides of an epoch boundary in one batch) is served without evicting it.
        if have is None or have.generation < generation:
            self._entries[(mesh, slot)] = out
        return out

    def batch(self, step: int, sizes: PaddedSizes | None = None) -> Batch:
        """The batch of `step` (a pure function of `(seed, step)` and the examples),
        padded to `sizes` (default: the pool's `sizes`, else the step's bucket)."""
        slots = split_slots(self.batch_size, self.n_group)
        picks = self.slot_of(step)
        sizes = self.sizes if sizes is None else sizes
        if sizes is None:
            sizes = common_sizes([[self.examples[picks[j][0]].graph for j in s] for s in slots])
        key = step_key(self.seed, step)
        out = []
        for g in range(self.n_group) if self.groups is None else self.groups:
            noisy, clean, vertex, cands, graphs = [], [], [], [], []
            for j in slots[g]:
                mesh, slot, generation = picks[j]
                e = self.entry(mesh, slot, generation)
                n, c, local = e.noisy, e.clean, e.local
                if self.rotate:
                    r = random_rotation(jax.random.fold_in(key, int(j)))
                    n = (n.astype(np.float64) @ r.T).astype(np.float32)
                    c = (c.astype(np.float64) @ r.T).astype(np.float32)
                    local = rotate_local_inputs(local, r.astype(np.float32))
                noisy.append(n)
                clean.append(c)
                vertex.append(local.vertex)
                cands.append(local.candidates)
                graphs.append(self.examples[mesh].graph)
            b = collate(noisy, clean, graphs, sizes)
            local = LocalInputs(
                pad_vertex_array(np.concatenate(vertex), sizes.n_vertex),
                pad_vertex_array(np.concatenate(cands), sizes.n_face),
            )
            out.append(b._replace(graph=with_fixed_ell(b.graph, self.ell_widths), local=local))
        return stack(out)


class Prefetcher:
    """Builds the batches of consecutive steps in a background thread, `depth` ahead.

    `get(step)` returns `make(step)`; the steps must be asked for in order from `start`.
    The thread runs the host pipeline (and the pool's encodings) while the device runs
    the step, so the step never waits for its batch unless the pipeline is the slower.
    An exception in `make` is raised by the `get` of its step. `close()` stops it.
    """

    def __init__(self, make: Callable[[int], Batch], start: int, *, depth: int = 2):
        self._make = make
        self._next = start
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(start,), daemon=True)
        self._thread.start()

    def _run(self, step: int) -> None:
        while not self._stop.is_set():
            try:
                item = (step, self._make(step), None)
            except BaseException as exc:  # handed to the consumer, who raises it
                item = (step, None, exc)
            while not self._stop.is_set():
                try:
                    self._queue.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if item[2] is not None:
                return
            step += 1

    def get(self, step: int) -> Batch:
        if step != self._next:
            raise ValueError(f"the prefetcher is at step {self._next}, not {step}")
        got, batch, exc = self._queue.get()
        if exc is not None:
            raise exc
        assert got == step
        self._next += 1
        return batch

    def close(self) -> None:
        self._stop.set()
        while self._thread.is_alive():
            try:
                self._queue.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(timeout=0.1)
