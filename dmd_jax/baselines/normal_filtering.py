"""Two-step denoisers: filter the face normals, then fit the vertices to them.

* `fefp`: Sun, Rosin, Martin & Langbein, "Fast and effective feature-preserving mesh
  denoising", IEEE TVCG 2007.
* `bnf`: Zheng, Fu, Au, Tai & Wang, "Bilateral normal filtering for mesh denoising",
  IEEE TVCG 2011 (local, iterative scheme).
* `gnf`: Zhang, Deng, Zhang, Bouaziz & Liu, "Guided mesh normal filtering", Pacific
  Graphics 2015 (local scheme with geometric neighbourhoods).

All three move the vertices with Sun et al.'s update (`fit_vertices_to_normals`), for the
papers' iteration counts (`vertex_iterations`), or with `vertex_update="solve"` with the
converged fit of the normal-first head (`dmd_jax.vertex_update`, default settings; the
count is then not used).
Face neighbourhoods are the vertex-based 1-ring (faces sharing a vertex) unless said
otherwise; GNF's filtering neighbourhood is geometric (face centroids within a radius,
found with a KD-tree on the input mesh).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from dmd_jax.baselines._common import (
    check_count,
    check_positive,
    count_trace,
    face_centroids,
    fit_vertices_to_normals,
    float_dtype,
    gaussian,
    mean_adjacent_centroid_distance,
    run_in_canonical_frame,
    weighted_normal_average,
)
from dmd_jax.geometry import face_areas, face_normals, safe_norm, safe_normalize
from dmd_jax.topology import (
    boundary_vertex_mask,
    dual_edges,
    face_ring_pairs,
    vertex_corner_arrays,
)
from dmd_jax.vertex_update import solve_vertices_to_normals

# How the vertices follow the filtered normals: the papers' Jacobi iterations, or the
# converged fit (`dmd_jax.vertex_update`).
VERTEX_UPDATES = ("jacobi", "solve")


def _check_update(name: str, vertex_update) -> bool:
    """Whether `vertex_update` asks for the converged fit; ValueError on another value."""
    if vertex_update not in VERTEX_UPDATES:
        raise ValueError(
            f"{name}: vertex_update must be one of {VERTEX_UPDATES}, got {vertex_update!r}"
        )
    return vertex_update == "solve"


def _fit(x, faces, n, cv, cf, free, n_vert, solve: bool):
    """The vertex step: `n_vert` Jacobi iterations, or the converged fit (`solve`)."""
    if solve:
        return solve_vertices_to_normals(x, faces, n, free)
    return fit_vertices_to_normals(x, faces, n, cv, cf, free, n_vert)


def _i32(x) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.int32)


def _sq(x):
    return jnp.sum(x * x, axis=-1)


def _free_mask(faces, n_vertex, fix_boundary: bool, dtype):
    free = np.ones(n_vertex)
    if fix_boundary:
        free[boundary_vertex_mask(faces, n_vertex)] = 0.0
    return jnp.asarray(free, dtype)


# --------------------------------------------------------------------------------------
# FEFP (Sun et al. 2007)
# --------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("solve",))
def _fefp_core(x, faces, ring_r, ring_s, cv, cf, free, threshold, n_normal, n_vertex_it, solve):
    count_trace("fefp")
    n_face = faces.shape[0]

    def normal_step(_, n):
        d = jnp.sum(n[ring_r] * n[ring_s], axis=-1)
        w = jnp.where(d > threshold, (d - threshold) ** 2, 0.0)
        return weighted_normal_average(w, n, ring_r, ring_s, n_face)

    n = jax.lax.fori_loop(0, n_normal, normal_step, face_normals(x, faces))
    return _fit(x, faces, n, cv, cf, free, n_vertex_it, solve)


def _fefp_pairs(faces, n_vertex: int, neighbourhood: str):
    """`(receivers, senders)` of FEFP's face neighbourhood, self included, sorted."""
    if neighbourhood == "edge":
        da, db = dual_edges(faces, n_vertex)
        loops = np.arange(faces.shape[0])
        r = np.concatenate([da, db, loops])
        s = np.concatenate([db, da, loops])
        order = np.lexsort((s, r))
        return _i32(r[order]), _i32(s[order])
    rr, rs = face_ring_pairs(faces, n_vertex)
    if neighbourhood == "meshlab":
        keep = rs <= rr
        return rr[keep], rs[keep]
    return rr, rs


def fefp(
    vertices,
    faces,
    *,
    threshold: float = 0.5,
    normal_iterations: int = 20,
    vertex_iterations: int = 50,
    fix_boundary: bool = False,
    neighbourhood: str = "vertex",
    vertex_update: str = "jacobi",
) -> np.ndarray:
    """Sun et al. (2007): thresholded normal averaging, then vertex fitting.

    Normal step over the faces N(i) around face i (i included):
    `n_i ← normalize(Σ_{j∈N(i)} w_ij n_j)`, `w_ij = (n_i·n_j − T)²` if `n_i·n_j > T`,
    else 0. Vertex step: `fit_vertices_to_normals`.

    pymeshlab's `apply_coord_two_steps_smoothing(stepsmoothnum=1, normalthr=60,
    stepnormalnum=20, stepfitnum=50)` implements the same two steps, but its face
    neighbourhood is not the paper's: vcglib's `FaceNormalAngleThreshold` walks each
    vertex's face list starting from face i itself rather than from the list head, so
    face i only sees the faces with index ≤ i that share a vertex with it (the lists
    are in decreasing face order). `neighbourhood="meshlab"` reproduces that to
    machine precision, for cross-checking; the default follows the paper.

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      threshold: T in [0, 1); 0.5 keeps neighbours within 60° of the face normal.
      normal_iterations: normal filtering passes.
      vertex_iterations: vertex fitting passes.
      fix_boundary: hold vertices on open boundaries in place.
      neighbourhood: `"vertex"` (faces sharing a vertex, the paper's), `"edge"`
        (faces sharing an edge) or `"meshlab"` (see above).
      vertex_update: `"jacobi"` (the paper's `vertex_iterations` passes) or `"solve"`
        (the converged fit, `dmd_jax.vertex_update`).

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.

    Returns:
      `[n_vertex, 3]` float64 denoised positions.
    """
    if neighbourhood not in ("vertex", "edge", "meshlab"):
        raise ValueError(
            f"fefp: neighbourhood must be 'vertex', 'edge' or 'meshlab', got {neighbourhood!r}"
        )
    check_count("fefp", normal_iterations=normal_iterations, vertex_iterations=vertex_iterations)
    solve = _check_update("fefp", vertex_update)
    if not (0.0 <= threshold < 1.0):
        raise ValueError(f"fefp: threshold must lie in [0, 1), got {threshold!r}")

    def core(v, f):
        dt = float_dtype()
        rr, rs = _fefp_pairs(f, v.shape[0], neighbourhood)
        cv, cf = vertex_corner_arrays(f)
        return _fefp_core(
            jnp.asarray(v, dt),
            jnp.asarray(f),
            rr,
            rs,
            cv,
            cf,
            _free_mask(f, v.shape[0], fix_boundary, dt),
            jnp.asarray(threshold, dt),
            jnp.asarray(normal_iterations, jnp.int32),
            jnp.asarray(vertex_iterations, jnp.int32),
            solve=solve,
        )

    return run_in_canonical_frame(vertices, faces, core, name="fefp")


# --------------------------------------------------------------------------------------
# BNF (Zheng et al. 2011)
# --------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("solve",))
def _bnf_core(
    x,
    faces,
    ring_r,
    ring_s,
    dual_a,
    dual_b,
    cv,
    cf,
    free,
    sigma_c,
    sigma_r,
    n_normal,
    n_vert,
    solve,
):
    count_trace("bnf")
    n_face = faces.shape[0]
    c = face_centroids(x, faces)
    # Areas relative to their mean: the normalised average is unchanged and the sums
    # stay far from underflow on meshes with many small faces.
    area = face_areas(x, faces)
    area = area / jnp.maximum(jnp.mean(area), jnp.finfo(x.dtype).tiny)
    sc = sigma_c * mean_adjacent_centroid_distance(x, faces, dual_a, dual_b)
    # Centroids and areas do not change while only the normals are filtered.
    spatial = area[ring_s] * gaussian(_sq(c[ring_r] - c[ring_s]), sc)

    def normal_step(_, n):
        w = spatial * gaussian(_sq(n[ring_r] - n[ring_s]), sigma_r)
        return weighted_normal_average(w, n, ring_r, ring_s, n_face)

    n = jax.lax.fori_loop(0, n_normal, normal_step, face_normals(x, faces))
    return _fit(x, faces, n, cv, cf, free, n_vert, solve)


def bnf(
    vertices,
    faces,
    *,
    sigma_c: float = 1.0,
    sigma_r: float = 0.35,
    normal_iterations: int = 20,
    vertex_iterations: int = 10,
    fix_boundary: bool = False,
    vertex_update: str = "jacobi",
) -> np.ndarray:
    """Zheng et al. (2011), local scheme: bilateral filtering of face normals.

    `n_i ← normalize(Σ_{j∈N(i)} A_j W_c(‖c_i − c_j‖) W_r(‖n_i − n_j‖) n_j)` over the
    faces sharing a vertex with face i (i excluded), Gaussian `W_c`, `W_r`; then
    `fit_vertices_to_normals`.

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      sigma_c: spatial σ as a multiple of the mean distance between the centroids of
        edge-adjacent faces (so it scales with the mesh).
      sigma_r: range σ on `‖n_i − n_j‖` (unit normals: dimensionless).
      normal_iterations: normal filtering passes.
      vertex_iterations: vertex fitting passes.
      fix_boundary: hold vertices on open boundaries in place.
      vertex_update: `"jacobi"` (the paper's `vertex_iterations` passes) or `"solve"`
        (the converged fit, `dmd_jax.vertex_update`).

    Returns:
      `[n_vertex, 3]` float64 denoised positions.
    """
    check_count("bnf", normal_iterations=normal_iterations, vertex_iterations=vertex_iterations)
    solve = _check_update("bnf", vertex_update)
    check_positive("bnf", sigma_c=sigma_c, sigma_r=sigma_r)

    def core(v, f):
        dt = float_dtype()
        rr, rs = face_ring_pairs(f, v.shape[0], include_self=False)
        da, db = dual_edges(f, v.shape[0])
        cv, cf = vertex_corner_arrays(f)
        return _bnf_core(
            jnp.asarray(v, dt),
            jnp.asarray(f),
            rr,
            rs,
            da,
            db,
            cv,
            cf,
            _free_mask(f, v.shape[0], fix_boundary, dt),
            jnp.asarray(sigma_c, dt),
            jnp.asarray(sigma_r, dt),
            jnp.asarray(normal_iterations, jnp.int32),
            jnp.asarray(vertex_iterations, jnp.int32),
            solve=solve,
        )

    return run_in_canonical_frame(vertices, faces, core, name="bnf")


# --------------------------------------------------------------------------------------
# GNF (Zhang et al. 2015)
# --------------------------------------------------------------------------------------


def _patch_pairs(ring_r: np.ndarray, ring_s: np.ndarray, n_face: int):
    """Pairs of faces inside each patch, as indices into a list of distinct pairs.

    The ring must be sorted by patch. A pair `(k, l)` lies in every patch holding
    both faces, so normal differences are computed once per distinct pair.

    Returns:
      `(patch [m], pair [m], first [p], second [p])`: entry i says that patch
      `patch[i]` holds the faces `first[pair[i]] < second[pair[i]]`.
    """
    indptr = np.concatenate([[0], np.cumsum(np.bincount(ring_r, minlength=n_face))])
    nnz = ring_r.size
    later = indptr[ring_r.astype(np.int64) + 1] - np.arange(nnz) - 1
    first = np.repeat(np.arange(nnz), later)
    offset = np.arange(first.size) - np.repeat(np.cumsum(later) - later, later)
    second = first + 1 + offset
    k, l = ring_s[first].astype(np.int64), ring_s[second].astype(np.int64)
    key, pair = np.unique(np.minimum(k, l) * n_face + np.maximum(k, l), return_inverse=True)
    uk, ul = np.divmod(key, n_face)
    return _i32(ring_r[first]), _i32(pair), _i32(uk), _i32(ul)


def _patch_inner_edges(ring_r, ring_s, dual_a, dual_b, n_face: int):
    """Inner edges of each patch: `(patch [m], edge [m])`, indices into the dual edges.

    An inner edge of patch j is a dual edge `(dual_a[e], dual_b[e])` whose two faces
    both lie in patch j. The ring must be sorted by patch.
    """
    ends = np.concatenate([dual_a, dual_b]).astype(np.int64)
    other = np.concatenate([dual_b, dual_a]).astype(np.int64)
    edge_id = np.tile(np.arange(dual_a.size), 2)
    keep = ends < other
    ends, other, edge_id = ends[keep], other[keep], edge_id[keep]
    order = np.argsort(ends, kind="stable")
    other, edge_id = other[order], edge_id[order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(ends, minlength=n_face))])
    # For every ring entry (j, a), every edge (a, b) with b > a ...
    a = ring_s.astype(np.int64)
    deg = indptr[a + 1] - indptr[a]
    entry = np.repeat(np.arange(ring_r.size), deg)
    offset = np.arange(entry.size) - np.repeat(np.cumsum(deg) - deg, deg)
    slot = np.repeat(indptr[a], deg) + offset
    j = ring_r[entry].astype(np.int64)
    b = other[slot]
    # ... kept when b is in patch j too (ring keys are sorted because the ring is).
    keys = ring_r.astype(np.int64) * n_face + ring_s
    query = j * n_face + b
    pos = np.clip(np.searchsorted(keys, query), 0, keys.size - 1)
    inside = keys[pos] == query
    return _i32(j[inside]), _i32(edge_id[slot][inside])


def _radius_pairs(points: np.ndarray, radius: float):
    """Pairs `(i, j)` with `‖p_i − p_j‖ ≤ radius`, self included, sorted by `i`."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray").astype(np.int64)
    n = points.shape[0]
    loops = np.arange(n)
    i = np.concatenate([pairs[:, 0], pairs[:, 1], loops])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], loops])
    order = np.lexsort((j, i))
    return _i32(i[order]), _i32(j[order])


def _guidance_normals(n, area, ring, patch, inner, dual):
    """Zhang et al.'s guidance: mean normal of the most consistent patch containing i.

    A patch `P_j` is the faces sharing a vertex with face j (j included). Its
    consistency is `H(P) = D(P) · R(P)`: `D` the largest normal difference between two
    of its faces, `R = max φ / (Σ φ + ε)` over its inner edges with `φ = ‖n_a − n_b‖`
    (small for patches without a feature). Each face takes the area-weighted mean
    normal of the patch with the smallest H among those that contain it.

    Args:
      n: `[n_face, 3]` unit normals.
      area: `[n_face]` face areas.
      ring: `(receivers, senders)` of the vertex-ring neighbourhood, self included.
      patch: `_patch_pairs` output.
      inner: `_patch_inner_edges` output.
      dual: `(a, b)` faces of every dual edge.

    Returns:
      `[n_face, 3]` guidance normals.
    """
    ring_r, ring_s = ring
    pp_patch, pp_pair, pair_k, pair_l = patch
    ie_patch, ie_edge = inner
    n_face = n.shape[0]

    def seg(op, values, ids):
        return op(values, ids, num_segments=n_face, indices_are_sorted=True)

    mean = safe_normalize(seg(jax.ops.segment_sum, area[ring_s, None] * n[ring_s], ring_r))
    pair_diff = safe_norm(n[pair_k] - n[pair_l])
    diff = seg(jax.ops.segment_max, pair_diff[pp_pair], pp_patch)
    phi = safe_norm(n[dual[0]] - n[dual[1]])[ie_edge]
    max_tv = seg(jax.ops.segment_max, phi, ie_patch)
    sum_tv = seg(jax.ops.segment_sum, phi, ie_patch)
    # Empty segments (a one-face patch; a patch without inner edge) reduce to -inf.
    diff = jnp.maximum(diff, 0.0)
    max_tv = jnp.maximum(max_tv, 0.0)
    h = diff * max_tv / (sum_tv + 1e-9)
    hc = h[ring_s]
    h_min = seg(jax.ops.segment_min, hc, ring_r)
    best = jnp.where(hc <= h_min[ring_r], ring_s, n_face)
    chosen = seg(jax.ops.segment_min, best, ring_r)
    return mean[chosen]


@partial(jax.jit, static_argnames=("solve",))
def _gnf_core(x, faces, ring, patch, inner, omega, dual, cv, cf, free, params, iters, solve):
    count_trace("gnf")
    om_r, om_s = omega
    sigma_s_factor, sigma_r = params
    n_normal, n_vert = iters
    n_face = faces.shape[0]

    def outer(_, y):
        n = face_normals(y, faces)
        area = face_areas(y, faces)
        area = area / jnp.maximum(jnp.mean(area), jnp.finfo(y.dtype).tiny)
        c = face_centroids(y, faces)
        sigma_s = sigma_s_factor * mean_adjacent_centroid_distance(y, faces, *dual)
        g = _guidance_normals(n, area, ring, patch, inner, dual)
        w = (
            area[om_s]
            * gaussian(_sq(c[om_r] - c[om_s]), sigma_s)
            * gaussian(_sq(g[om_r] - g[om_s]), sigma_r)
        )
        filtered = weighted_normal_average(w, n, om_r, om_s, n_face)
        return _fit(y, faces, filtered, cv, cf, free, n_vert, solve)

    return jax.lax.fori_loop(0, n_normal, outer, x)


def gnf(
    vertices,
    faces,
    *,
    radius: float = 2.0,
    sigma_s: float = 1.0,
    sigma_r: float = 0.35,
    normal_iterations: int = 20,
    vertex_iterations: int = 10,
    fix_boundary: bool = False,
    vertex_update: str = "jacobi",
) -> np.ndarray:
    """Zhang et al. (2015), local scheme: joint bilateral filter guided by patch normals.

    Each of the `normal_iterations` passes recomputes the face normals of the current
    mesh, builds the guidance normals g (`_guidance_normals`), filters
    `n_i ← normalize(Σ_{j∈Ω_i} A_j K_s(‖c_i − c_j‖) K_r(‖g_i − g_j‖) n_j)` and then runs
    `vertex_iterations` vertex updates, as the authors' code alternates them. Ω_i holds
    the faces whose input centroids lie within `radius` of face i's (i included).

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      radius: Ω radius as a multiple of the mean distance between the centroids of
        edge-adjacent faces of the input.
      sigma_s: spatial σ as a multiple of that mean distance (re-measured each pass).
      sigma_r: range σ on `‖g_i − g_j‖`.
      normal_iterations: normal filtering passes (each followed by vertex updates).
      vertex_iterations: vertex updates per pass.
      fix_boundary: hold vertices on open boundaries in place.
      vertex_update: `"jacobi"` (the paper's `vertex_iterations` per pass) or `"solve"`
        (the converged fit after each pass, `dmd_jax.vertex_update`).

    Returns:
      `[n_vertex, 3]` float64 denoised positions.
    """
    check_count("gnf", normal_iterations=normal_iterations, vertex_iterations=vertex_iterations)
    solve = _check_update("gnf", vertex_update)
    check_positive("gnf", radius=radius, sigma_s=sigma_s, sigma_r=sigma_r)

    def core(v, f):
        dt = float_dtype()
        n_face = f.shape[0]
        rr, rs = face_ring_pairs(f, v.shape[0])
        da, db = dual_edges(f, v.shape[0])
        c = v[f].mean(axis=1)
        mean_dist = float(np.linalg.norm(c[da] - c[db], axis=1).mean()) if da.size else 1.0
        om = _radius_pairs(c, radius * mean_dist)
        return _gnf_core(
            jnp.asarray(v, dt),
            jnp.asarray(f),
            (rr, rs),
            _patch_pairs(rr, rs, n_face),
            _patch_inner_edges(rr, rs, da, db, n_face),
            om,
            (da, db),
            *vertex_corner_arrays(f),
            _free_mask(f, v.shape[0], fix_boundary, dt),
            (jnp.asarray(sigma_s, dt), jnp.asarray(sigma_r, dt)),
            (jnp.asarray(normal_iterations, jnp.int32), jnp.asarray(vertex_iterations, jnp.int32)),
            solve=solve,
        )

    return run_in_canonical_frame(vertices, faces, core, name="gnf")
