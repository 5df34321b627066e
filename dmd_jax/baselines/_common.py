"""Shared pieces of the classic denoisers: host-side neighbourhoods and JAX kernels.

Neighbourhoods are index arrays built once per mesh by `dmd_jax.topology` (NumPy/SciPy,
no Python loops over elements); the filters themselves are gathers plus
`jax.ops.segment_*` reductions inside `jax.jit`. Every public filter runs in the
mesh's canonical frame (centre and longest bounding-box side 1) and maps the result
back, so it is translation and scale equivariant and keeps float32 accurate when
64-bit JAX is off.
"""

from __future__ import annotations

import collections
import inspect
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.geometry import (  # noqa: F401  (re-exported for the baselines)
    face_centroids,
    fit_vertices_to_normals,
    safe_norm,
)
from dmd_jax.mesh import canonical_frame, validate_mesh

# How many times each jitted core has been traced; tests read it to check that a
# second call on a mesh of the same size reuses the compiled program.
TRACE_COUNTS: collections.Counter = collections.Counter()


def count_trace(name: str) -> None:
    """Records one trace of the jitted core `name` (runs at trace time only)."""
    TRACE_COUNTS[name] += 1


# --------------------------------------------------------------------------------------
# Calling convention
# --------------------------------------------------------------------------------------


def run_in_canonical_frame(vertices, faces, core: Callable, *, name: str) -> np.ndarray:
    """Validates a mesh, runs `core(v, f)` in its canonical frame and maps back.

    Args:
      vertices: `[n_vertex, 3]` array-like.
      faces: `[n_face, 3]` array-like of vertex indices.
      core: `core(vertices [n, 3] float64 canonical, faces [f, 3] int32) -> [n, 3]`.
      name: the method's name, for error messages.

    Parts with nothing to denoise (`consistency.still_faces`: all creases, a lone
    triangle, no area) come back exactly as given, as from DMD-Net; a mesh of nothing
    else is not filtered at all.

    Returns:
      `[n_vertex, 3]` float64 NumPy array in the input's frame.
    """
    from dmd_jax.consistency import still_vertices

    v, f = validate_mesh(vertices, faces, name=name)
    frame = canonical_frame(v)  # refuses a mesh of one point first
    still = still_vertices(v, f)
    if still[np.unique(f)].all():
        return v
    out = np.asarray(core(frame.apply(v), f), dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise FloatingPointError(f"{name}: the filter produced non-finite vertices")
    out = frame.invert(out)
    out[still] = v[still]
    return out


def default_params(fn: Callable) -> dict:
    """The keyword-only parameters of a filter and their defaults."""
    return {
        p.name: p.default
        for p in inspect.signature(fn).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }


def check_positive(name: str, **values) -> None:
    """Raises `ValueError` unless every value is a finite number > 0."""
    for key, val in values.items():
        if not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name}: {key} must be a finite number > 0, got {val!r}")


# The most iterations any count parameter of a classic filter takes. The papers' settings
# stay below 100; 10,000 passes over a million-face mesh already take hours, and a count
# past it is a typo, refused before any work rather than run for days.
MAX_COUNT = 10_000
# The most whole-filter passes `dmd_jax.denoise_with(method, iterations=...)` (and
# `dmd-jax denoise --iterations`) runs of a classic filter, each with its own inner
# iterations: a thousand repeats of any filter have long converged.
MAX_PASSES = 1_000


def check_count(name: str, **values) -> None:
    """Raises `ValueError` unless every value is an integer from 0 to `MAX_COUNT`."""
    for key, val in values.items():
        try:
            ok = not isinstance(val, bool) and int(val) == val and 0 <= val <= MAX_COUNT
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ValueError(
                f"{name}: {key} must be an integer from 0 to {MAX_COUNT:,}, got {val!r}"
            )


def float_dtype():
    """float64 when 64-bit JAX is enabled, else float32."""
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


# --------------------------------------------------------------------------------------
# JAX kernels shared by the normal-filtering methods
# --------------------------------------------------------------------------------------


def gaussian(dist_sq, sigma):
    """`exp(-d² / (2σ²))` from squared distances."""
    return jnp.exp(-0.5 * dist_sq / (sigma * sigma))


def mean_adjacent_centroid_distance(vertices, faces, dual_a, dual_b):
    """Mean distance between the centroids of faces sharing an edge (a scalar).

    A mesh without two edge-adjacent faces gets 1 (any positive value: its filters
    then only see each face itself).
    """
    if dual_a.shape[0] == 0:
        return jnp.asarray(1.0, vertices.dtype)
    c = face_centroids(vertices, faces)
    return jnp.mean(safe_norm(c[dual_a] - c[dual_b]))


def weighted_normal_average(weights, normals, receivers, senders, n_face):
    """`normalize(Σ_j w_ij n_j)` per receiving face; zero-sum faces keep their normal.

    Only an exactly zero sum counts as zero: products of small areas and range weights
    are legitimately tiny (`safe_normalize`'s 1e-10 floor would freeze such faces).
    """
    acc = jax.ops.segment_sum(
        weights[:, None] * normals[senders],
        receivers,
        num_segments=n_face,
        indices_are_sorted=True,
    )
    norm = jnp.sqrt(jnp.sum(acc * acc, axis=-1, keepdims=True))
    ok = norm > 0
    return jnp.where(ok, acc / jnp.where(ok, norm, 1.0), normals)
