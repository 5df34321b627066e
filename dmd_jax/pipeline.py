"""Input pipeline: shuffling, rotation augmentation, mixed noise and bucketed padding.

Every batch is a pure function of `(seed, step)` and the dataset, so any step of any run
can be rebuilt exactly (that is what makes resume bit-identical). Batches are padded
disjoint unions of meshes; all padded sizes derive from one vertex bucket, so an epoch
compiles one program per bucket it touches.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from dmd_jax import noise as noise_lib
from dmd_jax.encoding import mesh_frame
from dmd_jax.graph import (
    MeshGraph,
    PaddedSizes,
    batch_mesh_graphs,
    bucket_size,
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
)
from dmd_jax.mesh import canonical_frame

# Upper bounds of padded sizes per padded vertex: a closed triangle mesh has f ≈ 2v,
# 2e + v ≈ 7v primal edges with self loops and 4f dual edges with self loops.
_FACE_RATIO = 2.25
_VERTEX_EDGE_RATIO = 7.5
_FACE_EDGE_RATIO = 4.0 * _FACE_RATIO


class MeshExample(NamedTuple):
    """One clean mesh and its graph, built once on the host."""

    vertices: np.ndarray  # [n_vertex, 3] float
    faces: np.ndarray  # [n_face, 3] int32
    graph: MeshGraph


class Batch(NamedTuple):
    """A padded batch: noisy input, clean target and the graph, all in canonical frames."""

    noisy: np.ndarray  # [n_vertex, 3] float32
    clean: np.ndarray  # [n_vertex, 3] float32
    graph: MeshGraph


class NoiseSettings(NamedTuple):
    """What the mixed-noise sampler may draw (see `dmd_jax.noise.sample_noise_spec`)."""

    kinds: tuple[str, ...] = noise_lib.NOISE_KINDS
    canonical_levels: dict | None = None  # kind -> levels; None: the paper's levels
    edge_levels: tuple[float, ...] = noise_lib.EDGE_LEVELS
    p_edge: float = 0.5
    p_normal: float = 0.0
    p_clean: float = 0.0


# The mesh-denoising benchmark protocol: Gaussian noise along the vertex normals of
# 0.1, 0.2 or 0.3 mean edge lengths (CNR, GCN-Denoiser). Used to evaluate and to pick
# checkpoints.
BENCHMARK_NOISE = NoiseSettings(
    kinds=("gaussian",), edge_levels=(0.1, 0.2, 0.3), p_edge=1.0, p_normal=1.0
)


def make_examples(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[MeshExample]:
    """Builds the host-side graph of every `(vertices, faces)` pair once."""
    out = []
    for vertices, faces in meshes:
        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int32)
        out.append(MeshExample(v, f, build_mesh_graph(f, v.shape[0])))
    return out


def sizes_for_vertices(
    n_vertex: int, n_face: int, n_vertex_edge: int, n_face_edge: int, n_graph: int
) -> PaddedSizes:
    """Padded sizes from a single vertex bucket (one compiled program per bucket)."""
    nv = bucket_size(n_vertex + 1)
    while (
        int(_FACE_RATIO * nv) < n_face
        or int(_VERTEX_EDGE_RATIO * nv) < n_vertex_edge
        or int(_FACE_EDGE_RATIO * nv) < n_face_edge
    ):
        nv = bucket_size(nv + 1)
    return PaddedSizes(
        n_vertex=nv,
        n_face=int(_FACE_RATIO * nv),
        n_vertex_edge=int(_VERTEX_EDGE_RATIO * nv),
        n_face_edge=int(_FACE_EDGE_RATIO * nv),
        n_graph=n_graph + 1,
    )


def collate(
    noisy: Sequence[np.ndarray], clean: Sequence[np.ndarray], graphs: Sequence[MeshGraph]
) -> Batch:
    """Joins meshes into one padded disjoint union (sizes bucketed)."""
    graph = batch_mesh_graphs(list(graphs))
    sizes = sizes_for_vertices(
        graph.n_vertex,
        graph.n_face,
        graph.vertex_senders.shape[0],
        graph.face_senders.shape[0],
        len(graphs),
    )
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
    noise: NoiseSettings,
    encoding: str = "xyz",
) -> tuple[np.ndarray, np.ndarray, noise_lib.NoiseSpec]:
    """Rotates (optionally) and noises one clean mesh.

    Both outputs are expressed in the frame of the *noisy* mesh that the model's
    `encoding` works in (`dmd_jax.encoding.mesh_frame`), the frame that `denoise` will
    use at inference time, so training sees what inference sees.

    Returns:
      `(noisy [n, 3], clean [n, 3], spec)`.
    """
    k_rot, k_noise = jax.random.split(key)
    v = np.asarray(vertices, np.float64)
    if rotate:
        v = v @ random_rotation(k_rot).T
    v = canonical_frame(v).apply(v)
    noisy, spec = noise_lib.add_mixed_noise(
        k_noise,
        v,
        faces,
        kinds=noise.kinds,
        canonical_levels=noise.canonical_levels,
        edge_levels=noise.edge_levels,
        p_edge=noise.p_edge,
        p_normal=noise.p_normal,
        p_clean=noise.p_clean,
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


def training_batch(
    examples: Sequence[MeshExample],
    step: int,
    *,
    batch_size: int,
    seed: int,
    noise: NoiseSettings,
    rotate: bool = True,
    encoding: str = "xyz",
) -> Batch:
    """The batch of `step`: a pure function of `(seed, step)` and the examples."""
    idx = batch_indices(step, len(examples), batch_size, seed)
    key = step_key(seed, step)
    noisy, clean, graphs = [], [], []
    for slot, i in enumerate(idx):
        ex = examples[int(i)]
        n, c, _ = corrupt(
            jax.random.fold_in(key, slot),
            ex.vertices,
            ex.faces,
            rotate=rotate,
            noise=noise,
            encoding=encoding,
        )
        noisy.append(n)
        clean.append(c)
        graphs.append(ex.graph)
    return collate(noisy, clean, graphs)


def evaluation_batches(
    examples: Sequence[MeshExample],
    *,
    seed: int,
    noise: NoiseSettings,
    rotate: bool = True,
    encoding: str = "xyz",
) -> list[tuple[Batch, noise_lib.NoiseSpec]]:
    """One single-mesh batch per example with fixed noise (the same for every evaluation)."""
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
        )
        out.append((collate([n], [c], [ex.graph]), spec))
    return out
