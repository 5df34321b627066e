"""Tangential relaxation: evens out a mesh's sampling without moving its surface.

DMD-Net's normal-first head moves each vertex along the face normals only
(`geometry.fit_vertices_to_normals`), as the classic normal-filtering pipelines do. Noise
with a tangential part (per-coordinate noise, as in the paper's Table II, rather than the
benchmark's noise along the normals) then stays in the result as uneven, sometimes folded
triangles whose normals are wrong although the surface is smooth. A few steps of the
umbrella operator restricted to the directions in which the surface does not bend fix
that: on a flat region the tangent plane, along a crease its line, at a corner nothing.

The directions come from the area-weighted normal tensor of each vertex's faces
(`T_i = Σ_f a_f n_f n_fᵀ`, as in feature-preserving remeshing): an eigenvector whose
eigenvalue is at least `feature_ratio` times the largest is a normal direction of the
surface at that vertex, and the step is projected off it.
"""

from __future__ import annotations

import numpy as np

from dmd_jax.topology import boundary_vertex_mask, one_ring_mean

# An eigenvalue of the normal tensor counts as a second (third) normal direction from this
# fraction of the largest. Two planes meeting at a dihedral angle θ give a ratio of
# (1 − cos θ)/(1 + cos θ): 0.2 keeps creases sharper than about 48° and lets the
# residual noise of denoised normals (3–5°, ratio ≈ 0.003) count as flat. Chosen on the
# validation split of shared/meshes/train (docs/studies.md, relax_validation): 0.2
# beat 0.05 at every noise level tried (0.05 left clean meshes 0.1° closer) and kept
# clean meshes closer than 1.0 (no creases kept).
FEATURE_RATIO = 0.2


def _blocked_directions(x: np.ndarray, faces: np.ndarray, feature_ratio: float) -> np.ndarray:
    """`[n_vertex, 3, 3]` projectors onto the directions a vertex must not move along."""
    n_vertex = x.shape[0]
    cross = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    # |cross| n nᵀ = cross crossᵀ / |cross|: the area-weighted outer product, no division
    # by zero on degenerate faces.
    norm = np.linalg.norm(cross, axis=1)
    outer = np.einsum("fi,fj->fij", cross, cross) / np.maximum(norm, 1e-300)[:, None, None]
    tensor = np.zeros((n_vertex, 3, 3))
    for k in range(3):
        np.add.at(tensor, faces[:, k], outer)
    eigval, eigvec = np.linalg.eigh(tensor)  # ascending
    top = eigval[:, 2:3]
    blocked = (eigval >= feature_ratio * top) & (top > 0)
    # Σ_k [blocked_k] e_k e_kᵀ; a vertex without faces blocks nothing and is not moved
    # anyway (it has no neighbours).
    return np.einsum("vk,vik,vjk->vij", blocked.astype(x.dtype), eigvec, eigvec)


def relax_tangential(
    vertices,
    faces,
    iterations: int = 3,
    *,
    step: float = 0.5,
    feature_ratio: float = FEATURE_RATIO,
) -> np.ndarray:
    """Moves vertices towards their one-ring mean within the surface (see module doc).

    Args:
      vertices: `[n_vertex, 3]` positions (e.g. a denoised mesh).
      faces: `[n_face, 3]` vertex indices.
      iterations: relaxation steps (0 returns a copy of `vertices`).
      step: fraction of the projected umbrella vector moved per step, in `(0, 1]`.
      feature_ratio: eigenvalue ratio from which a direction of the normal tensor is
        treated as a normal of the surface (`FEATURE_RATIO`); larger keeps fewer creases.

    Returns:
      `[n_vertex, 3]` float64 positions, a new array (the input is not modified).
      Boundary vertices and vertices of no face are not moved.

    Raises:
      ValueError: bad shapes, indices out of range, `iterations < 0`, or `step` or
        `feature_ratio` outside `(0, 1]`.
    """
    x = np.array(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"vertices must have shape [n_vertex, 3], got {x.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape [n_face, 3], got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= x.shape[0]):
        raise ValueError(f"faces index vertices outside 0..{x.shape[0] - 1}")
    if int(iterations) != iterations or iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations}")
    if not 0.0 < step <= 1.0:
        raise ValueError(f"step must lie in (0, 1], got {step}")
    if not 0.0 < feature_ratio <= 1.0:
        raise ValueError(f"feature_ratio must lie in (0, 1], got {feature_ratio}")
    if iterations == 0 or f.size == 0:
        return x
    mean = one_ring_mean(f.astype(np.int64), x.shape[0])
    # Vertices no face uses have an empty ring, and a boundary vertex's ring is one-sided
    # (its umbrella points into the mesh, so open scans would shrink): both stay put.
    free = np.zeros(x.shape[0], bool)
    free[f.ravel()] = True
    free &= ~boundary_vertex_mask(f, x.shape[0])
    for _ in range(int(iterations)):
        umbrella = np.where(free[:, None], mean @ x - x, 0.0)
        blocked = _blocked_directions(x, f, feature_ratio)
        umbrella -= np.einsum("vij,vj->vi", blocked, umbrella)
        x = x + step * umbrella
    return x
