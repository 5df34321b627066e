"""Uniform Laplacian (umbrella) smoothing and Taubin's λ|μ smoothing.

Taubin, "A signal processing approach to fair surface design", SIGGRAPH 1995 (and
"Curve and surface smoothing without shrinkage", ICCV 1995): alternate a shrinking
step `x ← x + λ L x` and an inflating step `x ← x + μ L x` with `μ < −λ < 0`, where
`L x_v` is the umbrella vector from `v` to the average of its neighbours.

Weights and boundary handling follow MeshLab (`vcg::tri::Smooth::VertexCoordTaubin`,
which pymeshlab's `apply_coord_taubin_smoothing` calls): uniform weights; a vertex on
an open boundary averages itself with its boundary neighbours only. One "step" of
`iterations` is one λ pass followed by one μ pass, as in pymeshlab's `stepsmoothnum`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.baselines._common import (
    check_count,
    count_trace,
    float_dtype,
    run_in_canonical_frame,
)
from dmd_jax.topology import umbrella_weights


def _umbrella_average(x, senders, receivers, weight, self_weight):
    """Weighted neighbour average per vertex, `[n_vertex, 3]` (itself when isolated)."""
    n = x.shape[0]
    acc = jax.ops.segment_sum(
        weight[:, None] * x[senders], receivers, num_segments=n, indices_are_sorted=True
    )
    total = jax.ops.segment_sum(weight, receivers, num_segments=n, indices_are_sorted=True)
    acc = acc + self_weight[:, None] * x
    total = total + self_weight
    return jnp.where(total[:, None] > 0, acc / jnp.where(total > 0, total, 1.0)[:, None], x)


@jax.jit
def _lambda_mu_core(x, senders, receivers, weight, self_weight, factors, iterations):
    """`iterations` times, one umbrella step per entry of `factors` (traced)."""
    count_trace("lambda_mu")

    def step(_, y):
        for k in range(factors.shape[0]):
            avg = _umbrella_average(y, senders, receivers, weight, self_weight)
            y = y + factors[k] * (avg - y)
        return y

    return jax.lax.fori_loop(0, iterations, step, x)


def _lambda_mu(vertices, faces, factors, iterations, name):
    def core(v, f):
        s, r, w, sw = umbrella_weights(f, v.shape[0])
        dt = float_dtype()
        return _lambda_mu_core(
            jnp.asarray(v, dt),
            jnp.asarray(s),
            jnp.asarray(r),
            jnp.asarray(w, dt),
            jnp.asarray(sw, dt),
            jnp.asarray(np.asarray(factors, np.float64), dt),
            jnp.asarray(iterations, jnp.int32),
        )

    return run_in_canonical_frame(vertices, faces, core, name=name)


def laplacian(vertices, faces, *, lam: float = 0.5, iterations: int = 10) -> np.ndarray:
    """Uniform Laplacian smoothing, `x ← x + λ (mean of neighbours − x)`, repeated.

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      lam: step size λ in (0, 1].
      iterations: number of smoothing steps.

    Returns:
      `[n_vertex, 3]` float64 smoothed positions.
    """
    check_count("laplacian", iterations=iterations)
    if not (0.0 < lam <= 1.0):
        raise ValueError(f"laplacian: lam must lie in (0, 1], got {lam!r}")
    return _lambda_mu(vertices, faces, [lam], iterations, "laplacian")


def taubin(
    vertices, faces, *, lam: float = 0.5, mu: float = -0.53, iterations: int = 10
) -> np.ndarray:
    """Taubin λ|μ smoothing with pymeshlab's defaults (λ = 0.5, μ = −0.53, 10 steps).

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      lam: shrinking factor λ > 0.
      mu: inflating factor μ < 0 (Taubin requires μ < −λ for a positive pass band).
      iterations: number of λ|μ pairs (pymeshlab's `stepsmoothnum`).

    Returns:
      `[n_vertex, 3]` float64 smoothed positions.
    """
    check_count("taubin", iterations=iterations)
    if not lam > 0:
        raise ValueError(f"taubin: lam must be > 0, got {lam!r}")
    if not mu < 0:
        raise ValueError(f"taubin: mu must be < 0, got {mu!r}")
    return _lambda_mu(vertices, faces, [lam, mu], iterations, "taubin")
