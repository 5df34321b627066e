"""Vertices fitted to target face normals, converged: the normal-first head's solve.

Sun et al.'s vertex update (`geometry.fit_vertices_to_normals`) is a Jacobi iteration
on the quadratic

    E(x) = Σ_faces j Σ_edges (i,k) of j (n_j · (x_i − x_k))²,

whose gradient is `∇_i E = 6 Σ_{j∋i} n_j n_jᵀ (x_i − c_j)` (`c_j` the centroid of face
`j`): one update is `x ← x − D⁻¹ ∇E / 6` with `D = diag(|F_i|)`, the number of faces at
each vertex. Ten such steps (DMD-Net's `vertex_iterations`) stop far from the fit: the
smooth part of the noise, the part of a real scan's displacement that spans several
rings, decays by about `1 − λ` per step for the small eigenvalues `λ` of `D⁻¹ ∇²E`.

Iterated to the end, `E` alone is ill-posed. It is homogeneous, so shrinking the mesh
lowers it whenever the target normals are not exactly integrable (always, for predicted
normals), and it does not see a vertex sliding within the planes of its faces, so
vertices drift tangentially and triangles fold. Measured on the meshes of
`tests/test_vertex_update.py` with target normals perturbed by 8° per face
(`benchmarks/results/vertex_update_sweep.md`), 300 Jacobi steps end at 14.5-22° mean
normal error and an isotropic Tikhonov solve of weight 1e-4 at 43-51°, where 10 steps
give 5-10°. Here the fit keeps each vertex near its start *in the tangent plane* and
lets it move freely along its normal:

    x* = argmin_x  E(x) / 6 + ½ Σ_i |F_i| (x_i − x⁰_i)ᵀ T_i (x_i − x⁰_i),
    T_i = μ_n m_i m_iᵀ + μ_t (I − m_i m_iᵀ),

with `m_i` the unit mean of the target normals at vertex `i`, `μ_n = normal_weight`
(default 1e-3: smooth normal displacements up to about `1 / sqrt(μ_n)` ≈ 30 rings long
are undone; the shrinking mode is held) and `μ_t = tangent_weight` (default 0.03: holds
the vertex in its tangent plane, where `E` is blind). The weights are relative to the
per-face stiffness of `E / 6` (`2/3` per face along its normal), so they are free of the
mesh's scale and resolution. In that sweep, with noise along the normals the solve ends
near the exact shape with exact normals (0.06-0.47° against 0.94-8.13° for 10 Jacobi
steps) and near or below 10 Jacobi steps with perturbed ones (5.3-5.9° against
5.1-10.1°), turning no face against its target; with tangential noise (scanner,
isotropic) and perturbed normals it ends at 8.4-11.8° against 8.6-13.7° (worse in one
case of six: the CAD part under scanner noise, 9.1° against 8.7°). A tangent
weight of 0.1 holds tangential noise in place (9.4-13.9° there), 0.01 starts to fold
faces under noise along the normals (5-6 faces).

The normal equations `(M + W) d = −M x⁰` for the displacement `d = x − x⁰` (`M = ∇E/6`
as a linear map, `W` the block diagonal `|F_i| T_i`) are symmetric positive definite.
They are solved by conjugate gradients from `d = 0`, preconditioned by the exact 3 × 3
diagonal blocks of `M + W` (which captures the anisotropy: along a face's normal it is
stiff, in its plane only `μ_t` holds it), stopped when the preconditioned residual has
fallen by `tolerance` or after `max_iterations`. Held vertices (`free = 0`, e.g. a
boundary) and vertices of no face do not move.

Differentiation is implicit (`jax.lax.custom_linear_solve`, symmetric): the gradient
of a loss through the solve is one more solve with the same matrix, whatever the number
of iterations the forward solve took, so training memory does not grow with the
iterations (the unrolled Jacobi update stores every step). The derivative is that of
the exact solution; with the default tolerance the forward result is within a few 1e-4
of it (relative residual), so the two agree to that accuracy.

Cost per iteration: one matrix product (one gather of the faces' corners, one segment
sum onto the vertices, as in one Jacobi step) and two inner products; 23-78
iterations at the default tolerance on the test meshes, 56 on a 100k-face grid with the
bundled network's normals (`benchmarks/results/vertex_update.md`: 0.175 of the default
`denoise` call there).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from dmd_jax.geometry import dot3, safe_normalize

# Defaults (see the module docstring; `ModelConfig.vertex_*` carries them for the model).
NORMAL_WEIGHT = 1e-3
TANGENT_WEIGHT = 0.03
TOLERANCE = 1e-4
MAX_ITERATIONS = 200


class SolveInfo(NamedTuple):
    """How one solve ran.

    Attributes:
      iterations: conjugate-gradient iterations taken (scalar int32).
      residual: preconditioned residual norm relative to the start's (scalar).
    """

    iterations: jax.Array
    residual: jax.Array


class _Operator(NamedTuple):
    """What the matrix products need, computed once per solve."""

    faces: jax.Array  # [n_face, 3]
    corner_vertex: jax.Array  # [3 n_face], faces.ravel()
    normal: jax.Array  # [n_face, 3] target normals
    weight: jax.Array  # [n_vertex] |F_i| on moving vertices, 0 elsewhere
    direction: jax.Array  # [n_vertex, 3] m_i
    moving: jax.Array  # [n_vertex] 1 where the vertex may move
    normal_weight: float
    tangent_weight: float


def _fit_term(op: _Operator, d):
    """`M d = Σ_{j∋i} n_j n_jᵀ (d_i − c_j(d))` per vertex, `[n_vertex, 3]`."""
    # n_j · (d_i − c_j) is a corner's projection less its face's mean projection: one
    # gather of the faces' corners, then per-face arithmetic and one segment sum.
    n = op.normal[:, None, :]  # [n_face, 1, 3]
    s = dot3(n, d[op.faces])  # [n_face, 3]
    u = s - (s[:, 0] + s[:, 1] + s[:, 2])[:, None] / 3.0
    return jax.ops.segment_sum(
        (n * u[:, :, None]).reshape(-1, 3), op.corner_vertex, num_segments=d.shape[0]
    )


def _matvec(op: _Operator, d):
    """`(P (M + W) P + I − P) d` with `P = diag(moving)`: symmetric, positive definite."""
    p = op.moving[:, None]
    pd = p * d
    along = dot3(op.direction, pd)[:, None] * op.direction
    hold = op.weight[:, None] * (
        op.tangent_weight * pd + (op.normal_weight - op.tangent_weight) * along
    )
    return p * (_fit_term(op, pd) + hold) + (1.0 - p) * d


def _block_inverse(op: _Operator, dtype):
    """Inverses of the 3 × 3 diagonal blocks of the operator, `[n_vertex, 3, 3]`."""
    n = op.normal
    outer = (2.0 / 3.0) * n[:, :, None] * n[:, None, :]  # [n_face, 3, 3]
    outer = jnp.broadcast_to(outer[:, None], (n.shape[0], 3, 3, 3)).reshape(-1, 3, 3)
    block = jax.ops.segment_sum(outer, op.corner_vertex, num_segments=op.weight.shape[0])
    m = op.direction
    mm = m[:, :, None] * m[:, None, :]
    eye = jnp.eye(3, dtype=dtype)
    hold = op.weight[:, None, None] * (
        op.tangent_weight * eye + (op.normal_weight - op.tangent_weight) * mm
    )
    p = op.moving[:, None, None]
    block = p * (block + hold) + (1.0 - p) * eye
    # Adjugate over determinant, written out: a batched 3 × 3 inverse in one fusion.
    a, b, c = block[:, 0, 0], block[:, 0, 1], block[:, 0, 2]
    d, e, f = block[:, 1, 0], block[:, 1, 1], block[:, 1, 2]
    g, h, i = block[:, 2, 0], block[:, 2, 1], block[:, 2, 2]
    co = jnp.stack(
        [
            jnp.stack([e * i - f * h, c * h - b * i, b * f - c * e], -1),
            jnp.stack([f * g - d * i, a * i - c * g, c * d - a * f], -1),
            jnp.stack([d * h - e * g, b * g - a * h, a * e - b * d], -1),
        ],
        -2,
    )
    det = a * co[:, 0, 0] + b * co[:, 1, 0] + c * co[:, 2, 0]
    return co / det[:, None, None]


def _pcg(matvec, b, inverse, tolerance: float, max_iterations: int):
    """Preconditioned conjugate gradients from 0; returns `(x, SolveInfo)`."""

    def precondition(r):
        # Written out, not einsum: on CPU it fuses with the update around it.
        return (
            inverse[:, :, 0] * r[:, 0:1]
            + inverse[:, :, 1] * r[:, 1:2]
            + inverse[:, :, 2] * r[:, 2:3]
        )

    def vdot(u, v):
        return jnp.sum(u * v)

    z = precondition(b)
    rz0 = vdot(b, z)
    # A zero right-hand side (the start already fits) needs no iteration.
    stop = (tolerance**2) * rz0

    def cond(state):
        _, _, _, rz, k = state
        return (k < max_iterations) & (rz > stop) & (rz > 0)

    def body(state):
        x, r, p, rz, k = state
        ap = matvec(p)
        alpha = rz / vdot(p, ap)
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        rz_new = vdot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, p, rz_new, k + 1

    x, _, _, rz, k = jax.lax.while_loop(
        cond, body, (jnp.zeros_like(b), b, z, rz0, jnp.asarray(0, jnp.int32))
    )
    relative = jnp.sqrt(jnp.where(rz0 > 0, rz / jnp.where(rz0 > 0, rz0, 1.0), 0.0))
    return x, SolveInfo(k, relative)


def _check_weight(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def solve_vertices_to_normals(
    vertices,
    faces,
    normals,
    free=None,
    *,
    tolerance: float = TOLERANCE,
    max_iterations: int = MAX_ITERATIONS,
    normal_weight: float = NORMAL_WEIGHT,
    tangent_weight: float = TANGENT_WEIGHT,
    return_info: bool = False,
):
    """Moves vertices to fit target face normals: the regularised least-squares solve.

    Minimises `E(x) / 6 + ½ Σ_i |F_i| (x_i − x⁰_i)ᵀ T_i (x_i − x⁰_i)` (module
    docstring) by preconditioned conjugate gradients from the start `x⁰ = vertices`;
    differentiable in `vertices` and `normals` by implicit differentiation.

    Args:
      vertices: `[n_vertex, 3]` start positions `x⁰`.
      faces: `[n_face, 3]` int vertex indices (degenerate padding faces `(p, p, p)` are
        inert).
      normals: `[n_face, 3]` target unit normals (a zero normal adds nothing).
      free: `[n_vertex]` float, 1 where a vertex may move, 0 where it is held; default
        every vertex.
      tolerance: stop when the preconditioned residual norm has fallen by this factor.
      max_iterations: at most this many conjugate-gradient iterations (static).
      normal_weight: `μ_n`, the hold toward the start along the vertex normal.
      tangent_weight: `μ_t`, the hold toward the start in the tangent plane.
      return_info: also return a `SolveInfo`.

    Returns:
      `[n_vertex, 3]` positions (with `return_info`, `(positions, SolveInfo)`).

    Raises:
      ValueError: bad shapes, a weight or tolerance that is not a positive number, or a
        `max_iterations` that is not a positive integer.
    """
    vertices = jnp.asarray(vertices)
    faces = jnp.asarray(faces)
    normals = jnp.asarray(normals)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape [n_vertex, 3], got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape [n_face, 3], got {faces.shape}")
    if normals.shape != faces.shape:
        raise ValueError(f"normals must have shape {faces.shape} like faces, got {normals.shape}")
    tolerance = _check_weight("tolerance", tolerance)
    normal_weight = _check_weight("normal_weight", normal_weight)
    tangent_weight = _check_weight("tangent_weight", tangent_weight)
    if isinstance(max_iterations, bool) or int(max_iterations) != max_iterations:
        raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
    dtype = vertices.dtype
    n_vertex = vertices.shape[0]
    if free is None:
        free = jnp.ones(n_vertex, dtype)
    free = jnp.asarray(free).astype(dtype)
    if free.shape != (n_vertex,):
        raise ValueError(f"free must have shape [{n_vertex}], got {free.shape}")

    corner_vertex = faces.reshape(-1)
    normals = normals.astype(dtype)
    degree = jax.ops.segment_sum(
        jnp.ones(corner_vertex.shape[0], dtype), corner_vertex, num_segments=n_vertex
    )
    moving = free * (degree > 0).astype(dtype)  # a vertex of no face has nothing to fit
    direction = safe_normalize(
        jax.ops.segment_sum(jnp.repeat(normals, 3, axis=0), corner_vertex, num_segments=n_vertex)
    )
    op = _Operator(
        faces=faces,
        corner_vertex=corner_vertex,
        normal=normals,
        weight=degree * moving,
        direction=direction,
        moving=moving,
        normal_weight=normal_weight,
        tangent_weight=tangent_weight,
    )
    # The preconditioner only steers the iteration: no derivative flows through it.
    inverse = jax.lax.stop_gradient(_block_inverse(op, dtype))
    rhs = -moving[:, None] * _fit_term(op, vertices)

    def solve(matvec, b):
        return _pcg(matvec, b, inverse, tolerance, int(max_iterations))

    d, info = jax.lax.custom_linear_solve(
        lambda v: _matvec(op, v), rhs, solve, symmetric=True, has_aux=True
    )
    out = vertices + d
    return (out, info) if return_info else out
