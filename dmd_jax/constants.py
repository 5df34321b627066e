"""Names and sizes the configs check against, kept apart from the model code.

`dmd_jax.config` validates a `ModelConfig` or `NoiseConfig` against the encodings, the
noise kinds and the width of the local features without importing JAX-side modules:
they live here, plain Python, and `encoding` and `noise` import them from this module
(and re-export them, so `encoding.local_dims` and `noise.NOISE_KINDS` keep working).
Nothing here imports another `dmd_jax` module.
"""

from __future__ import annotations

# --------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------

# The paper's four distributions, drawn independently per coordinate (or per vertex along
# its normal); the default of `NoiseConfig.kinds`.
PAPER_NOISE_KINDS = ("gaussian", "uniform", "gamma", "impulse")
# Depth-sensor noise (`noise.scanner_displacement`): along one view direction, spatially
# correlated, growing at grazing angles, quantised in depth. Not a per-coordinate law.
SCANNER_KIND = "scanner"
# Every kind `noise.add_noise_jax` and `dmd_jax.add_noise` take (`NoiseConfig.kinds` too).
NOISE_KINDS = (*PAPER_NOISE_KINDS, SCANNER_KIND)

# --------------------------------------------------------------------------------------
# Surface regions
# --------------------------------------------------------------------------------------

# A crease: an edge whose faces' normals differ by at least this (degrees). The paper's
# CAD parts have creases of 60-90°; 30° keeps the gentle chamfers of fandisk as well.
# `comparison.crease_faces` splits benchmark errors by it, `LossConfig.crease_weight`
# weights training faces by it.
CREASE_ANGLE = 30.0

# --------------------------------------------------------------------------------------
# Encodings and the layout of the local features (`encoding.local_features`)
# --------------------------------------------------------------------------------------

ENCODINGS = ("xyz", "local")
# Default range σs of the bilateral pre-filters on |n_i − n_j| (unit normals), one filter
# each (`ModelConfig.filter_sigmas`): from edge preserving (0.2: neighbours more than ~25°
# apart barely mix) to smoothing.
FILTER_RANGE_SIGMAS = (0.2, 0.35, 0.6)
# Spatial σ of the pre-filters, in mean edge lengths (the `"local"` frame's unit).
FILTER_SPATIAL_SIGMA = 1.0
# Each filter's normals are kept after these fractions of `filter_iterations` passes.
# The dual graph gives a face only 3 neighbours (BNF's vertex ring ~12), so it takes
# ~60 passes to smooth a flat region as much as BNF's 20; measured on fandisk and block
# at 0.3 mean edges of noise along normals, σ 0.35 after 8 / 30 / 60 passes, followed by
# the vertex update, gives 12.8° / 3.8° / 3.1° (BNF 3.2°) and 14.0° / 6.3° / 4.5° (BNF
# 3.7°), while on bunny at 0.1 the 8-pass field is the best (8.5°; BNF 14.0°).
FILTER_SNAPSHOTS = (2 / 15, 1 / 2, 1.0)
# The optional Taubin-smoothed candidates are kept after these fractions of
# `ModelConfig.taubin_iterations` λ|μ pairs (`encoding.TAUBIN_LAMBDA_MU`).
TAUBIN_SNAPSHOTS = (3 / 10, 1.0)


def _snapshots(fractions, iterations: int) -> tuple[int, ...]:
    """`round(fraction × iterations)` per fraction, made strictly increasing from 1."""
    out = []
    for frac in fractions:
        out.append(max(round(frac * iterations), out[-1] + 1 if out else 1))
    return tuple(out)


def snapshot_passes(filter_iterations: int) -> tuple[int, ...]:
    """The pass counts after which each pre-filter's normals are kept (increasing)."""
    return _snapshots(FILTER_SNAPSHOTS, filter_iterations)


def taubin_snapshots(taubin_iterations: int) -> tuple[int, ...]:
    """The λ|μ pair counts after which the Taubin-smoothed mesh is kept; `()` for 0."""
    return _snapshots(TAUBIN_SNAPSHOTS, taubin_iterations) if taubin_iterations else ()


def n_candidates(taubin_iterations: int = 0, filter_sigmas=FILTER_RANGE_SIGMAS) -> int:
    """Candidate normals of the normal-first head: noisy, pre-filtered, Taubin-smoothed."""
    filtered = len(filter_sigmas) * len(FILTER_SNAPSHOTS)
    return 1 + filtered + len(taubin_snapshots(taubin_iterations))


def candidate_labels(
    filter_iterations: int, taubin_iterations: int = 0, filter_sigmas=FILTER_RANGE_SIGMAS
) -> list[str]:
    """Names of the `n_candidates(...)` candidate normals in `local_features`' order:
    `"noisy"`, then `"σ{range σ} ×{passes}"` per pre-filter and snapshot, then
    `"Taubin ×{pairs}"` per Taubin snapshot."""
    passes = snapshot_passes(filter_iterations)
    labels = ["noisy"] + [f"σ{s} ×{p}" for s in filter_sigmas for p in passes]
    return labels + [f"Taubin ×{p}" for p in taubin_snapshots(taubin_iterations)]


def local_dims(taubin_iterations: int = 0, filter_sigmas=FILTER_RANGE_SIGMAS) -> tuple[int, int]:
    """`(vertex columns, face columns)` of `encoding.local_features`: 6 (Laplacian
    coordinate, vertex normal) + 3 per candidate other than the noisy normal + 3 per
    Taubin displacement, and 3 per candidate."""
    k = n_candidates(taubin_iterations, filter_sigmas)
    return 6 + 3 * (k - 1) + 3 * len(taubin_snapshots(taubin_iterations)), 3 * k
