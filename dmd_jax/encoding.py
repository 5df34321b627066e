"""How DMD-Net sees a mesh: the frame it works in and the features it is given.

Two encodings, chosen by `ModelConfig.encoding`:

* `"xyz"`, the paper's reading: the canonical frame (bounding box centred, longest side
  1) and the absolute canonical coordinates as the only input. An offset the network
  learnt on 2k-vertex meshes is then the same length in bounding-box units on a
  40k-vertex scan, i.e. several times too long in edge lengths (`shared/model-audit.md`,
  item A), and ReLUs on absolute coordinates make it orientation dependent (item C).
* `"local"`, resolution-free: the frame is centred on the bounding box and scaled by
  the mean edge length, so one unit is one mean edge whatever the resolution: noise
  levels, offsets, the vertex and chamfer losses and the curvature targets are all in
  edge units. The inputs are translation-invariant and oriented:

  - per vertex (`LOCAL_VERTEX_DIM` columns): the uniform Laplacian coordinate
    `x_i − mean_{j∈N(i)} x_j` (3), the area-weighted vertex normal (3), and the vertex
    average of every pre-filtered face normal field below (3 each);
  - per face (`LOCAL_FACE_DIM` columns, concatenated to the dual stream's input): the
    face normal (3) and the pre-filtered face normals (3 each), which also makes the
    winding of every face visible to the network (P2D alone is blind to it, audit D).

  With `ModelConfig.taubin_iterations > 0` the mesh is also Taubin-smoothed (λ|μ
  umbrella steps, pymeshlab's factors) and kept after each of `taubin_snapshots`: every
  smoothed mesh adds its face normals as one more candidate (3 face columns, and their
  vertex average, 3 vertex columns) and its displacement `x − x_smooth` (3 vertex
  columns), a per-vertex measure of how rough the surface is. The bilateral filters move
  normals across the dual graph only (3 neighbours a face); on coarse organic meshes at
  0.3 edges of noise none of their fields is as smooth as Taubin's result
  (`docs/design-decisions.md`).

The pre-filters are bilateral normal filters (Zheng et al. 2011) over the dual graph
(faces sharing an edge) with a spatial σ of one edge and the range σs of
`ModelConfig.filter_sigmas` (default `FILTER_RANGE_SIGMAS`), each kept after several
numbers of passes (`snapshot_passes` of `ModelConfig.filter_iterations`): the same kind
of multi-scale filtered-normal
descriptor CNR regresses from, and, among them, fields as smooth as BNF's. They have no
parameters, so the model stays one function of the noisy mesh, the same in training and
inference.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import geometry, ops
from dmd_jax.constants import (  # noqa: F401  (the layout is re-exported from here)
    ENCODINGS,
    FILTER_RANGE_SIGMAS,
    FILTER_SNAPSHOTS,
    FILTER_SPATIAL_SIGMA,
    TAUBIN_SNAPSHOTS,
    candidate_labels,
    local_dims,
    n_candidates,
    snapshot_passes,
    taubin_snapshots,
)
from dmd_jax.mesh import CanonicalFrame, canonical_frame, edge_unit_frame

# Taubin smoothing of the optional smoothed-mesh candidates: pymeshlab's λ and μ (kept
# after `TAUBIN_SNAPSHOTS` of `ModelConfig.taubin_iterations` λ|μ pairs).
TAUBIN_LAMBDA_MU = (0.5, -0.53)


def mesh_frame(encoding: str, vertices, faces, *, edges=None) -> CanonicalFrame:
    """The frame the network of `encoding` works in, for one (noisy) mesh.

    Args:
      encoding: one of `ENCODINGS`.
      vertices: `[n_vertex, 3]` positions in any frame.
      faces: `[n_face, 3]` vertex indices (used by `"local"`).
      edges: the mesh's unique undirected edges, if already known (see
        `mesh.mean_edge_length`).

    Returns:
      A `CanonicalFrame`: `"xyz"` the bounding-box frame, `"local"` centred on the
      bounding box with the mean edge length as unit.

    Raises:
      ValueError: an unknown encoding, non-finite coordinates, or a mesh whose edges
        all have zero length.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown encoding {encoding!r}; choose one of {ENCODINGS}")
    if encoding == "xyz":
        return canonical_frame(vertices)  # validates finiteness and extent
    return edge_unit_frame(vertices, faces, edges=edges)


def laplacian_coordinates(x, graph):
    """`x_i − mean_{j∈N(i)} x_j` over the primal edges of `graph` (self loops excluded).

    Args:
      x: `[n_vertex, d]`.
      graph: a `MeshGraph`; padding edges (weight 0) are ignored.

    Returns:
      `[n_vertex, d]`; 0 on isolated (and padding) vertices.
    """
    n = x.shape[0]
    if graph.vertex_ell is not None:
        # Inference's padded neighbour table: gathers instead of a scatter (the Taubin
        # candidates call this 20 times a pass).
        # Slot 0 is the vertex itself (`graph.ell_layout`): left out with the self loops.
        nbr = graph.vertex_ell.neighbours[:, 1:]
        rows = jnp.arange(n, dtype=nbr.dtype)[:, None]
        keep = ((nbr != rows) & (graph.vertex_ell.weights[:, 1:] > 0)).astype(x.dtype)
        total = jnp.einsum("vk,vkc->vc", keep, x[nbr])
        count = jnp.sum(keep, axis=1)
    else:
        s, r = graph.vertex_senders, graph.vertex_receivers
        keep = ((s != r) & (graph.vertex_edge_weight > 0)).astype(x.dtype)
        total = jax.ops.segment_sum(
            x[s] * keep[:, None], r, num_segments=n, indices_are_sorted=True
        )
        count = jax.ops.segment_sum(keep, r, num_segments=n, indices_are_sorted=True)
    mean = total / jnp.maximum(count, 1.0)[:, None]
    return jnp.where(count[:, None] > 0, x - mean, 0.0)


# Candidates and columns of `local_features` with the default filters and without
# Taubin candidates.
N_CANDIDATES = n_candidates(0)
LOCAL_VERTEX_DIM, LOCAL_FACE_DIM = local_dims(0)


def _kept_after(step, x, counts):
    """Runs `x ← step(i, x)` up to `max(counts)` times; the states after each count."""
    out, done = [], 0
    for count in counts:
        x = jax.lax.fori_loop(done, count, step, x)
        out.append(x)
        done = count
    return out


def taubin_smooth(x, graph, iterations):
    """Taubin λ|μ smoothing (`TAUBIN_LAMBDA_MU`, uniform umbrella over `graph`'s edges).

    Args:
      x: `[n_vertex, 3]` positions.
      graph: a `MeshGraph` (padding edges are ignored; isolated vertices stay put).
      iterations: an increasing tuple of λ|μ pair counts (static).

    Returns:
      A list of `[n_vertex, 3]` positions, one per entry of `iterations`.
    """
    lam, mu = TAUBIN_LAMBDA_MU

    def pair(_, y):
        y = y - lam * laplacian_coordinates(y, graph)
        return y - mu * laplacian_coordinates(y, graph)

    return _kept_after(pair, x, iterations)


def bilateral_face_normals(x, graph, normals, *, sigma_r: float, iterations):
    """Bilateral normal filtering over the dual graph (faces sharing an edge, and self).

    `n_i ← normalize(Σ_j A_j W_c(|c_i − c_j|) W_r(|n_i − n_j|) n_j)` with Gaussian
    weights, `W_c`'s σ `FILTER_SPATIAL_SIGMA` (frame units) and `W_r`'s `sigma_r`.
    The range weight is computed as `exp((n_i · n_j − 1) / σ_r²)`, equal to
    `exp(−|n_i − n_j|² / 2σ_r²)` for unit normals and 1.6x faster than forming the
    differences (at 100k faces on 2 CPU cores: 3.6 → 2.3 ms a pass). The normals are
    unit after every pass; only a zero start normal (a degenerate face) sees other
    weights, all its neighbours' scaled alike, so its normalised result is the same.

    Args:
      x: `[n_vertex, 3]` positions in the frame of `mesh_frame`.
      graph: a `MeshGraph` (padding edges, weight 0, are left out).
      normals: `[n_face, 3]` the unit face normals to start from.
      sigma_r: range σ.
      iterations: filtering passes (static), or an increasing tuple of pass counts to
        return the normals after each.

    Returns:
      `[n_face, 3]` unit normals (0 where the start normal is 0, e.g. padding faces), or
      a list of them, one per entry of a tuple `iterations`.
    """
    n_face = normals.shape[0]
    c = geometry.face_centroids(x, graph.faces)
    area = geometry.face_areas(x, graph.faces)
    inv_sr2 = 1.0 / (sigma_r * sigma_r)
    inv_2sc2 = 0.5 / (FILTER_SPATIAL_SIGMA * FILTER_SPATIAL_SIGMA)
    if graph.face_ell is not None:
        # Inference's padded neighbour table (`graph.with_ell_layout`): the same sums as
        # gathers over `[n_face, slots]`, no scatter (about 3x faster on CPU).
        nbr, ell_w = graph.face_ell.neighbours, graph.face_ell.weights
        d2 = jnp.sum((c[nbr] - c[:, None, :]) ** 2, axis=-1)
        spatial = (ell_w > 0) * area[nbr] * jnp.exp(-d2 * inv_2sc2)

        def step(_, n):
            # One gather per slot and the sums written out: XLA's CPU backend runs the
            # `einsum` form's tiny contractions as batched dots, 3x slower a pass. Slot 0
            # is the face itself (`graph.ell_layout`): its range weight is exp(0) = 1 for
            # a unit normal, and its term is 0 for a zero one either way; no gather.
            acc = spatial[:, 0, None] * n
            for k in range(1, nbr.shape[1]):
                nk = n[nbr[:, k]]
                w = spatial[:, k] * jnp.exp((geometry.dot3(nk, n) - 1.0) * inv_sr2)
                acc = acc + w[:, None] * nk
            return geometry.safe_normalize(acc)

    else:
        s, r = graph.face_senders, graph.face_receivers
        d2 = jnp.sum((c[s] - c[r]) ** 2, axis=-1)
        spatial = (graph.face_edge_weight > 0) * area[s] * jnp.exp(-d2 * inv_2sc2)

        def step(_, n):
            w = spatial * jnp.exp((jnp.sum(n[s] * n[r], axis=-1) - 1.0) * inv_sr2)
            acc = jax.ops.segment_sum(
                w[:, None] * n[s], r, num_segments=n_face, indices_are_sorted=True
            )
            return geometry.safe_normalize(acc)

    if isinstance(iterations, int):
        return jax.lax.fori_loop(0, iterations, step, normals)
    return _kept_after(step, normals, iterations)


def candidate_consistency(candidates, graph):
    """Per candidate normal of every face: its roughness and its distance from the noisy one.

    The quantities classic filters trade off when they pick a normal: roughness
    `mean_g (1 - n_k(f) · n_k(g))` over the faces `g` sharing an edge with `f`, and
    fidelity `1 - n_k(f) · n_0(f)` to the noisy normal `n_0 = candidates[:, 0]`. Both are
    dimensionless, in [0, 2], and invariant to rotations, translations and scale.

    Args:
      candidates: `[n_face, K, 3]` unit normals (`local_features`), noisy one first.
      graph: the `MeshGraph` (its dual edge lists; weight-0 padding edges and self loops
        are left out).

    Returns:
      `[n_face, 2 K]`: the K roughness values, then the K fidelity values.
    """
    s, r = graph.face_senders, graph.face_receivers
    real = ((graph.face_edge_weight > 0) & (s != r)).astype(candidates.dtype)
    agree = jnp.sum(candidates[s] * candidates[r], axis=-1)  # [n_face_edge, K]
    n_face = candidates.shape[0]
    rough = jax.ops.segment_sum(real[:, None] * (1.0 - agree), r, num_segments=n_face)
    count = jax.ops.segment_sum(real, r, num_segments=n_face)
    rough = rough / jnp.maximum(count, 1.0)[:, None]
    fidelity = 1.0 - jnp.sum(candidates * candidates[:, :1], axis=-1)
    return jnp.concatenate([rough, fidelity], axis=-1)


class LocalInputs(NamedTuple):
    """The parameter-free part of the `"local"` encoding, computed once outside a model call.

    `local_features` of one noisy mesh (or one padded group), minus its face columns,
    which are `candidates.reshape(n_face, -1)`. `DMDNet(...)(..., local=LocalInputs(...))`
    uses them instead of computing them from the positions: the same network inputs, so
    the same outputs (`tests/test_candidate_pool.py`). The filters are rotation
    equivariant and translation invariant, so the inputs of a rotated mesh are these with
    every 3-column block rotated (`rotate_local_inputs`).

    Attributes:
      vertex: `[n_vertex, V]` the vertex columns (`local_dims`).
      candidates: `[n_face, K, 3]` the candidate normals (`n_candidates`).
    """

    vertex: Any
    candidates: Any


def local_inputs(x, graph, config) -> LocalInputs:
    """`local_features` of `x` with the filters of a `ModelConfig` (what `DMDNet` computes).

    Args:
      x: `[n_vertex, 3]` noisy positions in the edge-unit frame (`mesh_frame`).
      graph: the (padded) `MeshGraph` of `x`.
      config: the model's `ModelConfig` (`filter_iterations`, `taubin_iterations`,
        `filter_sigmas`).

    Returns:
      `LocalInputs(vertex [n_vertex, V], candidates [n_face, K, 3])`.
    """
    vertex, _, candidates = local_features(
        x,
        graph,
        filter_iterations=config.filter_iterations,
        taubin_iterations=config.taubin_iterations,
        filter_sigmas=config.filter_sigmas,
    )
    return LocalInputs(vertex, candidates)


def rotate_local_inputs(local: LocalInputs, rotation) -> LocalInputs:
    """The local inputs of the mesh rotated by `rotation` `[3, 3]` (`x @ rotation.T`).

    Every vertex column block (Laplacian coordinate, normals, Taubin displacements) and
    every candidate normal is a 3-vector that rotates with the mesh; the rest of the
    encoding is invariant. Works on NumPy or JAX arrays, `[..., n, V]` and `[..., n, K, 3]`.
    """
    xp = np if isinstance(local.vertex, np.ndarray) else jnp
    r = xp.asarray(rotation, local.vertex.dtype)
    v = local.vertex
    blocks = v.reshape(*v.shape[:-1], v.shape[-1] // 3, 3) @ r.T
    return LocalInputs(
        blocks.reshape(v.shape), local.candidates @ r.T.astype(local.candidates.dtype)
    )


def local_features(
    x,
    graph,
    *,
    filter_iterations: int,
    taubin_iterations: int = 0,
    filter_sigmas: tuple[float, ...] = FILTER_RANGE_SIGMAS,
):
    """The `"local"` encoding's inputs (see the module docstring).

    Args:
      x: `[n_vertex, 3]` noisy positions in the edge-unit frame.
      graph: the `MeshGraph`.
      filter_iterations: passes of each bilateral pre-filter.
      taubin_iterations: λ|μ pairs of the Taubin-smoothed candidates (0: none).
      filter_sigmas: the range σ of each bilateral pre-filter (static).

    Returns:
      `(vertex [n_vertex, V], face [n_face, F], candidates [n_face, K, 3])` with
      `(V, F) = local_dims(taubin_iterations, filter_sigmas)` and
      `K = n_candidates(...)`: the last holds
      the noisy face normal, every pre-filtered one (each σ after each of
      `snapshot_passes`) and the Taubin-smoothed ones, the normals the normal-first head
      mixes.
    """
    faces = graph.faces
    n0 = geometry.face_normals(x, faces)
    passes = snapshot_passes(filter_iterations)
    fields = [n0]
    for sr in filter_sigmas:
        fields += bilateral_face_normals(x, graph, n0, sigma_r=sr, iterations=passes)
    smoothed = taubin_smooth(x, graph, taubin_snapshots(taubin_iterations))
    fields += [geometry.face_normals(y, faces) for y in smoothed]
    candidates = jnp.stack(fields, axis=1)
    face = candidates.reshape(candidates.shape[0], -1)
    vertex = [laplacian_coordinates(x, graph), geometry.vertex_normals(x, faces)]
    vertex += [
        geometry.safe_normalize(ops.dual_to_primal(n, faces, graph.vertex_face_degree))
        for n in fields[1:]
    ]
    vertex += [x - y for y in smoothed]
    return jnp.concatenate(vertex, axis=-1), face, candidates
