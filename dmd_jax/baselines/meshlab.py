"""MeshLab's own smoothing filters through pymeshlab, as reference points for the baselines.

`taubin` and `two_step` run pymeshlab's implementations of Taubin 1995 and Sun et al.
2007 (the method `dmd_jax.baselines.fefp` re-implements), so a comparison table can show
what the reference library gives next to this package's versions. They are not in
`dmd_jax.baselines.REGISTRY`: they need the optional `pymeshlab` package, run on the CPU
in MeshLab's own frame, and are never counted as a competing method.
"""

from __future__ import annotations

import numpy as np

PYMESHLAB_FILTERS = {
    # Taubin 1995 with pymeshlab's defaults (λ = 0.5, μ = −0.53, 10 steps).
    "taubin": ("apply_coord_taubin_smoothing", {}),
    # Sun et al. 2007 (FEFP) with the settings DESIGN.md lists: T = 0.5, 20 normal and
    # 50 vertex iterations. pymeshlab's normalthr is an angle in degrees: acos(0.5) = 60°.
    "two_step": (
        "apply_coord_two_steps_smoothing",
        {"stepsmoothnum": 1, "normalthr": 60.0, "stepnormalnum": 20, "stepfitnum": 50},
    ),
}


def pymeshlab_filter(vertices, faces, name: str, **params) -> np.ndarray:
    """Runs a pymeshlab smoothing filter and returns vertices in the input order.

    Args:
      vertices: `[n, 3]` positions.
      faces: `[f, 3]` vertex indices.
      name: `taubin` or `two_step` (keys of `PYMESHLAB_FILTERS`).
      **params: override the filter's parameters (pymeshlab's names).

    Returns:
      `[n, 3]` float64 filtered positions.

    Raises:
      ValueError: an unknown filter name.
      RuntimeError: pymeshlab changed the vertex count.
      ImportError: pymeshlab is not installed.
    """
    import pymeshlab

    if name not in PYMESHLAB_FILTERS:
        raise ValueError(
            f"unknown pymeshlab filter {name!r}; use one of {sorted(PYMESHLAB_FILTERS)}"
        )
    filter_name, defaults = PYMESHLAB_FILTERS[name]
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int32)))
    getattr(ms, filter_name)(**{**defaults, **params})
    out = ms.current_mesh().vertex_matrix()
    if out.shape != np.shape(vertices):
        raise RuntimeError(f"pymeshlab {filter_name} changed the vertex count")
    return np.asarray(out, np.float64)
