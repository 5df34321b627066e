"""Differentiable discrete geometry of triangle meshes, in pure JAX.

All functions take `vertices [n_vertex, 3]` and `faces [n_face, 3]` and accumulate per
vertex with `jax.ops.segment_sum` (sizes from static shapes). Degenerate (zero-area)
faces give finite values and finite gradients: every norm and division is guarded.

Curvature follows Meyer, Desbrun, Schröder & Barr (2003), "Discrete
Differential-Geometry Operators for Triangulated 2-Manifolds", as the paper's appendix
C writes it:

* mean curvature  `κ_H(v) = |Σ_u (cot α + cot β)(p_v − p_u)| / (4 A_mixed(v))`
  (unsigned; `signed_mean_curvature` gives the sign from the vertex normal),
* Gaussian curvature `κ_G(v) = (2π − Σ_f θ_f(v)) / A_mixed(v)`.

Boundary convention: the same formulas are used on boundary vertices (as libigl's
`gaussian_curvature` does), so there they measure the boundary's turning, not a
surface curvature; vertices with no incident face get 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Below this a length is treated as zero; keeps gradients finite on degenerate faces.
_TINY = 1e-20


def dot3(a, b):
    """`Σ_c a[..., c] b[..., c]` over a last axis of 3, written out: `[...]`.

    XLA's CPU backend runs a reduction (or `einsum`) over such a tiny axis as a separate,
    slow kernel; written out, the products join the surrounding elementwise fusion.
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def corner_sum(values, faces):
    """Each face's sum of `values` over its three corners, `values[faces].sum(1)`: `[n_face, ...]`.

    One gather per corner, added in one fusion (on CPU the reduction over a gathered
    `[n_face, 3, ...]` block is a separate, slower kernel).
    """
    values = jnp.asarray(values)  # NumPy values cannot be indexed by traced faces
    return values[faces[:, 0]] + values[faces[:, 1]] + values[faces[:, 2]]


def _last_axis_of_3(x, axis) -> bool:
    """Whether `axis` is the last axis of `x` and has length 3 (`dot3` applies)."""
    return x.shape[axis] == 3 and axis in (-1, x.ndim - 1)


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm with a finite gradient at zero (the 'double where' trick)."""
    if _last_axis_of_3(x, axis):
        sq = dot3(x, x)
        sq = sq[..., None] if keepdims else sq
    else:
        sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    nonzero = sq > _TINY
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


def safe_normalize(x, axis=-1):
    """`x / |x|`, and 0 where `|x| = 0` (finite gradient)."""
    if _last_axis_of_3(x, axis):
        # One multiply by a guarded rsqrt: on CPU it fuses with its producer, where the
        # general form below runs as three separate kernels.
        sq = dot3(x, x)
        nonzero = sq > _TINY
        inverse = jnp.where(nonzero, jax.lax.rsqrt(jnp.where(nonzero, sq, 1.0)), 0.0)
        return x * inverse[..., None]
    norm = safe_norm(x, axis=axis, keepdims=True)
    return jnp.where(norm > 0, x / jnp.where(norm > 0, norm, 1.0), 0.0)


def _segment_sum_corners(values, faces, n_vertex):
    """Sums per-corner values `[n_face, 3, ...]` onto vertices `[n_vertex, ...]`."""
    flat = values.reshape((-1,) + values.shape[2:])
    return jax.ops.segment_sum(flat, faces.reshape(-1), num_segments=n_vertex)


def face_cross(vertices, faces):
    """Unnormalised face normals `(p1 − p0) × (p2 − p0)`: `[n_face, 3]`, length 2·area."""
    p = vertices[faces]
    return jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def face_normals(vertices, faces):
    """Unit face normals `[n_face, 3]` (right-hand rule); zero on degenerate faces."""
    return safe_normalize(face_cross(vertices, faces))


def face_areas(vertices, faces):
    """Face areas `[n_face]`."""
    return 0.5 * safe_norm(face_cross(vertices, faces))


def vertex_normals(vertices, faces):
    """Area-weighted unit vertex normals `[n_vertex, 3]`; zero on isolated vertices."""
    cross = face_cross(vertices, faces)
    corners = jnp.broadcast_to(cross[:, None, :], (faces.shape[0], 3, 3))
    return safe_normalize(_segment_sum_corners(corners, faces, vertices.shape[0]))


def _corner_vectors(vertices, faces):
    """For each corner i, the edge vectors to the next and previous corner: `[f, 3, 3]`."""
    p = vertices[faces]
    nxt = jnp.roll(p, -1, axis=1) - p
    prv = jnp.roll(p, 1, axis=1) - p
    return nxt, prv


def interior_angles(vertices, faces):
    """Interior angle of each face at each corner, `[n_face, 3]` in radians.

    Computed as `atan2(|a × b|, a · b)`, accurate for angles near 0 and π. A collinear
    face gets `(0, 0, π)`. A corner that coincides with a neighbour has no angle: such
    corners share what the others leave of π (the limit of a shrinking edge, `π/2` each
    for two coincident corners, `π/3` for three), so every face sums to π and
    Gauss–Bonnet survives collapsed edges; the gradient there is finite.
    """
    a, b = _corner_vectors(vertices, faces)
    ok = (safe_norm(a) > 0) & (safe_norm(b) > 0)
    # atan2(0, 0) has a NaN gradient: feed the undefined corners atan2(0, 1) instead.
    angle = jnp.where(
        ok,
        jnp.arctan2(safe_norm(jnp.cross(a, b)), jnp.where(ok, jnp.sum(a * b, axis=-1), 1.0)),
        0.0,
    )
    n_undefined = jnp.sum(~ok, axis=1, keepdims=True)
    rest = (jnp.pi - jnp.sum(angle, axis=1, keepdims=True)) / jnp.maximum(n_undefined, 1)
    return jnp.where(ok, angle, rest)


def cotangents(vertices, faces):
    """Cotangent of the interior angle at each corner, `[n_face, 3]`.

    The cotangent at corner i weights the opposite edge (corners i+1, i+2). On a
    degenerate face the sine is clamped at 1e-12, so values are large (up to 1e12) but
    finite; a corner that coincides with a neighbour gets 0.
    """
    # Unit edge vectors: an absolute floor on the sine then bounds the gradient, where a
    # floor scaled by |a||b| vanishes (and overflows float32) as an edge collapses.
    a, b = (safe_normalize(e) for e in _corner_vectors(vertices, faces))
    cos = jnp.sum(a * b, axis=-1)
    sin = safe_norm(jnp.cross(a, b))
    return cos / jnp.maximum(sin, 1e-12)


def cotangent_laplacian(vertices, faces, values=None):
    """`Σ_u w_vu (x_v − x_u)` with cotangent weights `w_vu = Σ_f cot α_vu^f`.

    Args:
      vertices: `[n_vertex, 3]` positions (they define the weights).
      faces: `[n_face, 3]`.
      values: `[n_vertex, d]` to apply the Laplacian to; the positions if omitted.

    Returns:
      `[n_vertex, d]`.
    """
    x = vertices if values is None else values
    cot = cotangents(vertices, faces)  # [f, 3], corner i weights edge (i+1, i+2)
    xi = x[faces]  # [f, 3, d]
    x_next = jnp.roll(xi, -1, axis=1)
    x_prev = jnp.roll(xi, 1, axis=1)
    # Vertex at corner i is an end of the edges opposite corners i+1 and i+2.
    w_to_next = jnp.roll(cot, 1, axis=1)  # cot at corner i-1 weights edge (i, i+1)
    w_to_prev = jnp.roll(cot, -1, axis=1)  # cot at corner i+1 weights edge (i-1, i)
    contrib = w_to_next[..., None] * (xi - x_next) + w_to_prev[..., None] * (xi - x_prev)
    return _segment_sum_corners(contrib, faces, x.shape[0])


def mixed_voronoi_area(vertices, faces):
    """Meyer et al.'s mixed area `A_mixed` per vertex, `[n_vertex]`.

    Voronoi area on non-obtuse triangles; on an obtuse triangle half its area goes to the
    obtuse corner and a quarter to each other corner. Sums to the total surface area.
    """
    a, b = _corner_vectors(vertices, faces)
    cot = cotangents(vertices, faces)
    area = face_areas(vertices, faces)
    # Voronoi part at corner i: (|e_i,i+1|^2 cot(i+2) + |e_i,i-1|^2 cot(i+1)) / 8.
    len_next = jnp.sum(a * a, axis=-1)
    len_prev = jnp.sum(b * b, axis=-1)
    voronoi = (len_next * jnp.roll(cot, -2, axis=1) + len_prev * jnp.roll(cot, -1, axis=1)) / 8.0
    dots = jnp.sum(a * b, axis=-1)  # < 0 where the corner is obtuse
    obtuse_here = dots < 0
    obtuse_face = jnp.any(obtuse_here, axis=1, keepdims=True)
    per_corner = jnp.where(
        obtuse_face,
        jnp.where(obtuse_here, area[:, None] / 2.0, area[:, None] / 4.0),
        voronoi,
    )
    return _segment_sum_corners(per_corner, faces, vertices.shape[0])


def _safe_divide(num, den):
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def mean_curvature_normal(vertices, faces):
    """Meyer's mean-curvature normal `K(v) = Σ w (p_v − p_u) / (2 A_mixed)`: `[n, 3]`.

    `K = 2 H n`, pointing along the outward normal on convex parts.
    """
    lap = cotangent_laplacian(vertices, faces)
    return _safe_divide(lap, 2.0 * mixed_voronoi_area(vertices, faces)[:, None])


def mean_curvature(vertices, faces):
    """Unsigned mean curvature per vertex, `|Σ w (p_v − p_u)| / (4 A_mixed)`: `[n]`."""
    lap = cotangent_laplacian(vertices, faces)
    return _safe_divide(safe_norm(lap), 4.0 * mixed_voronoi_area(vertices, faces))


def signed_mean_curvature(vertices, faces):
    """Mean curvature with sign: positive where the surface bends away from its normal
    (a sphere with outward normals has `H = +1/r`)."""
    k = mean_curvature_normal(vertices, faces)
    sign = jnp.sign(jnp.sum(k * vertex_normals(vertices, faces), axis=-1))
    return 0.5 * safe_norm(k) * jnp.where(sign == 0, 1.0, sign)


def angle_defect(vertices, faces):
    """`2π − Σ_f θ_f(v)` per vertex `[n]`; 0 for vertices with no incident face."""
    angles = interior_angles(vertices, faces)
    total = _segment_sum_corners(angles, faces, vertices.shape[0])
    has_face = _segment_sum_corners(jnp.ones_like(angles), faces, vertices.shape[0]) > 0
    return jnp.where(has_face, 2.0 * jnp.pi - total, 0.0)


def gaussian_curvature(vertices, faces):
    """Gaussian curvature per vertex, `(2π − Σ θ) / A_mixed`: `[n_vertex]`."""
    return _safe_divide(angle_defect(vertices, faces), mixed_voronoi_area(vertices, faces))


def vertex_features(vertices, faces):
    """The feature extractor's targets: `[n_vertex, 5]` = unit normal, κ_H, κ_G."""
    return jnp.concatenate(
        [
            vertex_normals(vertices, faces),
            mean_curvature(vertices, faces)[:, None],
            gaussian_curvature(vertices, faces)[:, None],
        ],
        axis=-1,
    )


def face_centroids(vertices, faces):
    """Face centroids `[n_face, 3]`."""
    return corner_sum(vertices, faces) / 3.0


def fit_vertices_to_normals(vertices, faces, normals, corner_vertex, corner_face, free, iterations):
    """Sun et al. (2007) vertex update, repeated: moves vertices onto the face planes.

    `x_i ← x_i + (1/|F_i|) Σ_{j∈F_i} n_j (n_j · (c_j − x_i))` with the current face
    centroids `c_j` and fixed target normals `n_j` (Jacobi: all vertices at once). Zheng
    et al. (2011) and Zhang et al. (2015) use the same update, and so does DMD-Net's
    normal-first head (`ModelConfig.head="normal"`), which differentiates through it.

    Args:
      vertices: `[n_vertex, 3]`.
      faces: `[n_face, 3]` int32.
      normals: `[n_face, 3]` unit target normals.
      corner_vertex, corner_face: `[3 n_face]` int32 corner arrays (`faces.ravel()` and
        each corner's face).
      free: `[n_vertex]` float, 1 where a vertex may move, 0 where it is held fixed.
      iterations: int (may be traced).

    Returns:
      `[n_vertex, 3]` updated positions.
    """
    n_vertex = vertices.shape[0]
    degree = jax.ops.segment_sum(
        jnp.ones(corner_vertex.shape[0], vertices.dtype), corner_vertex, num_segments=n_vertex
    )
    scale = (free / jnp.maximum(degree, 1.0)).astype(vertices.dtype)
    nc = normals[corner_face].astype(vertices.dtype)

    def body(_, x):
        c = face_centroids(x, faces)
        d = c[corner_face] - x[corner_vertex]
        move = nc * dot3(nc, d)[:, None]
        step = jax.ops.segment_sum(move, corner_vertex, num_segments=n_vertex)
        return x + scale[:, None] * step

    return jax.lax.fori_loop(0, iterations, body, vertices)
