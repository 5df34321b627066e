"""Classic mesh denoisers written with the project's segment-sum ops, for comparison.

Every method has the signature `fn(vertices, faces, **params) -> vertices` (NumPy in,
float64 NumPy out, same vertex order). Methods run in the mesh's canonical frame and
derive every length from the mesh (mean edge length, mean distance between adjacent
face centroids, shortest edge at a vertex), so results are translation and scale
equivariant. Neighbourhoods are index arrays built once on the host; the filters are
`jax.jit`-compiled gathers and `jax.ops.segment_*` reductions iterated with
`jax.lax.fori_loop` (L0 solves its linear systems on the host with SciPy).

=========  =================================================================
name       method
=========  =================================================================
laplacian  uniform umbrella smoothing
taubin     Taubin 1995 λ|μ smoothing (pymeshlab's weights and defaults)
bmd        Fleishman, Drori & Cohen-Or 2003, bilateral mesh denoising
nifp       Jones, Durand & Desbrun 2003, non-iterative feature-preserving
fefp       Sun, Rosin, Martin & Langbein 2007, fast and effective (two-step)
bnf        Zheng, Fu, Au, Tai & Wang 2011, bilateral normal filtering
gnf        Zhang, Deng, Zhang, Bouaziz & Liu 2015, guided normal filtering
l0         He & Schaefer 2013, L0 minimization (area-based edge operator)
=========  =================================================================

Learned baselines live in `LEARNED` (same signature; `run_baseline` and `DEFAULTS`
cover them too): `cnr`, Wang, Liu & Tong 2016, cascaded normal regression, with the
bundled weights `dmd_jax/weights/cnr_small.msgpack` (see `dmd_jax.baselines.cascaded_regression`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dmd_jax.baselines._common import MAX_COUNT, MAX_PASSES, default_params
from dmd_jax.baselines.bilateral_mesh import bmd
from dmd_jax.baselines.cascaded_regression import cnr
from dmd_jax.baselines.l0_minimization import l0
from dmd_jax.baselines.normal_filtering import bnf, fefp, gnf
from dmd_jax.baselines.robust_projection import nifp
from dmd_jax.baselines.smoothing import laplacian, taubin

REGISTRY: dict[str, Callable[..., np.ndarray]] = {
    "laplacian": laplacian,
    "taubin": taubin,
    "bmd": bmd,
    "nifp": nifp,
    "fefp": fefp,
    "bnf": bnf,
    "gnf": gnf,
    "l0": l0,
}

# Kept apart from the classic filters: a learned method needs weights, and its
# data-dependent local frames make it rotation equivariant only up to rounding.
LEARNED: dict[str, Callable[..., np.ndarray]] = {"cnr": cnr}

_ALL = {**REGISTRY, **LEARNED}

DEFAULTS: dict[str, dict] = {name: default_params(fn) for name, fn in _ALL.items()}


def run_baseline(name: str, vertices, faces, **params) -> np.ndarray:
    """Runs the denoiser `name` with its defaults overridden by `params`.

    Args:
      name: a key of `REGISTRY` or `LEARNED`.
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      **params: parameters of that method (see `DEFAULTS[name]`).

    Returns:
      `[n_vertex, 3]` float64 denoised positions.

    Raises:
      ValueError: unknown method or parameter name, or an invalid value.
    """
    if name not in _ALL:
        raise ValueError(f"unknown denoiser {name!r}; choose one of: " + ", ".join(sorted(_ALL)))
    unknown = sorted(set(params) - set(DEFAULTS[name]))
    if unknown:
        raise ValueError(
            f"{name}: unknown parameter(s) {', '.join(unknown)}; "
            f"valid: {', '.join(sorted(DEFAULTS[name]))}"
        )
    return _ALL[name](vertices, faces, **params)


__all__ = [
    "DEFAULTS",
    "LEARNED",
    "MAX_COUNT",
    "MAX_PASSES",
    "REGISTRY",
    "bmd",
    "bnf",
    "cnr",
    "run_baseline",
    "fefp",
    "gnf",
    "l0",
    "laplacian",
    "nifp",
    "taubin",
]


def __getattr__(name: str):
    # `baselines.denoise_with` was `run_baseline`'s name until it clashed with the root
    # `dmd_jax.denoise_with` (which also runs DMD-Net); old code keeps working, warned.
    if name == "denoise_with":
        import warnings

        warnings.warn(
            "dmd_jax.baselines.denoise_with is deprecated: use dmd_jax.baselines.run_baseline "
            "(or dmd_jax.denoise_with, which also runs DMD-Net)",
            DeprecationWarning,
            stacklevel=2,
        )
        return run_baseline
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
