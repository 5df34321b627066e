"""Input pipeline: shuffling, rotation augmentation, mixed noise and bucketed padding.

Every batch is a pure function of `(seed, step)` and the dataset, so any step of any run
can be rebuilt exactly (that is what makes resume bit-identical). A training batch is
one group of meshes per device, each group a padded disjoint union, all padded to the
same sizes and stacked on a leading axis (one group on one device); the sizes come from
one vertex bucket (`graph.sizes_for_vertices`), so an epoch compiles one program per
bucket it touches.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from dmd_jax import noise as noise_lib
from dmd_jax.config import NoiseConfig
from dmd_jax.encoding import mesh_frame
from dmd_jax.graph import (
    MeshGraph,
    PaddedSizes,
    batch_mesh_graphs,
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    sizes_for_vertices,
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
    n_vertex, 3]`, every `graph` array `[n_group, ...]`).
    """

    noisy: np.ndarray  # [(n_group,) n_vertex, 3] float32
    clean: np.ndarray  # [(n_group,) n_vertex, 3] float32
    graph: MeshGraph


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
