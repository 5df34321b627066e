"""Non-iterative, feature-preserving mesh smoothing: Jones, Durand & Desbrun, SIGGRAPH 2003.

Every face q predicts a position for vertex p by projecting p onto q's plane,
`Π_q(p) = p − ((p − c_q)·n_q) n_q`, and p moves to the robust weighted mean

    p' = Σ_q Π_q(p) a_q f(‖c_q − p‖) g(‖Π_q(p) − p‖) / Σ_q a_q f(‖c_q − p‖) g(‖Π_q(p) − p‖),

with Gaussian spatial weight f (σ_f), influence weight g (σ_g), face areas a_q and
centroids c_q. The normals n_q are mollified: they are the face normals of a copy of
the mesh whose vertices were smoothed by the non-robust average
`Σ a_q f_m(‖c_q − p‖) c_q / Σ a_q f_m(‖c_q − p‖)` with σ_m = σ_f / 2. Faces enter when
their centroid lies within 2σ_f of p (the paper's cut-off); the pairs come from a
KD-tree on the host and are not limited by connectivity, as in the paper.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from dmd_jax.baselines._common import (
    check_positive,
    count_trace,
    face_centroids,
    float_dtype,
    gaussian,
    run_in_canonical_frame,
)
from dmd_jax.geometry import face_areas, face_normals
from dmd_jax.graph import bucket_size
from dmd_jax.mesh import mean_edge_length


def _weighted_mean(weights, values, receivers, n, fallback):
    acc = jax.ops.segment_sum(
        weights[:, None] * values, receivers, num_segments=n, indices_are_sorted=True
    )
    total = jax.ops.segment_sum(weights, receivers, num_segments=n, indices_are_sorted=True)
    ok = total > 0
    return jnp.where(ok[:, None], acc / jnp.where(ok, total, 1.0)[:, None], fallback)


@jax.jit
def _nifp_core(x, faces, pair_v, pair_f, valid, sigma_f, sigma_g, sigma_m):
    """Mollification and robust projection over `(vertex, face)` pairs.

    Pairs are sorted by vertex; padding pairs carry `valid = 0`.
    """
    count_trace("nifp")
    n_vertex = x.shape[0]
    c = face_centroids(x, faces)
    area = face_areas(x, faces)[pair_f] * valid
    p = x[pair_v]
    cq = c[pair_f]
    d2 = jnp.sum((cq - p) ** 2, axis=-1)
    mollified = _weighted_mean(area * gaussian(d2, sigma_m), cq, pair_v, n_vertex, x)
    nq = face_normals(mollified, faces)[pair_f]
    proj = p - jnp.sum((p - cq) * nq, axis=-1, keepdims=True) * nq
    w = area * gaussian(d2, sigma_f) * gaussian(jnp.sum((proj - p) ** 2, -1), sigma_g)
    return _weighted_mean(w, proj, pair_v, n_vertex, x)


def _vertex_face_pairs(vertices, centroids, radius):
    """`(vertex, face)` index pairs with `‖c_face − v‖ ≤ radius`, sorted by vertex."""
    found = cKDTree(vertices).sparse_distance_matrix(
        cKDTree(centroids), radius, output_type="ndarray"
    )
    v, f = found["i"].astype(np.int64), found["j"].astype(np.int64)
    order = np.lexsort((f, v))
    return v[order].astype(np.int32), f[order].astype(np.int32)


def nifp(
    vertices,
    faces,
    *,
    sigma_f: float = 1.0,
    sigma_g: float = 1.0,
    mollify: float = 0.5,
) -> np.ndarray:
    """Jones et al. (2003) one-pass robust smoothing with mollified normals.

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      sigma_f: spatial σ as a multiple of the mean edge length.
      sigma_g: influence σ as a multiple of the mean edge length.
      mollify: σ_m / σ_f for the mollification pass (the paper's 1/2).

    Returns:
      `[n_vertex, 3]` float64 denoised positions.
    """
    check_positive("nifp", sigma_f=sigma_f, sigma_g=sigma_g, mollify=mollify)

    def core(v, f):
        dt = float_dtype()
        edge = mean_edge_length(v, f)
        sf, sg = sigma_f * edge, sigma_g * edge
        pv, pf = _vertex_face_pairs(v, v[f].mean(axis=1), 2.0 * sf)
        # Pad the pair list to a bucket size (padding on the last vertex keeps the
        # receivers sorted) so meshes of similar size share one compiled program.
        pad = bucket_size(pv.size) - pv.size
        valid = np.concatenate([np.ones(pv.size), np.zeros(pad)])
        pv = np.concatenate([pv, np.full(pad, v.shape[0] - 1, np.int32)])
        pf = np.concatenate([pf, np.zeros(pad, np.int32)])
        return _nifp_core(
            jnp.asarray(v, dt),
            jnp.asarray(f),
            pv,
            pf,
            jnp.asarray(valid, dt),
            jnp.asarray(sf, dt),
            jnp.asarray(sg, dt),
            jnp.asarray(mollify * sf, dt),
        )

    return run_in_canonical_frame(vertices, faces, core, name="nifp")
