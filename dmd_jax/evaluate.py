"""Evaluation helpers: pymeshlab reference filters and markdown result tables."""

from __future__ import annotations

from collections.abc import Sequence

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
      vertices: `[n, 3]`.
      faces: `[f, 3]`.
      name: `taubin` or `two_step` (keys of `PYMESHLAB_FILTERS`).
      **params: override the filter's parameters.
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


def markdown_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A GitHub markdown table; floats printed with 3 decimals (4 significant if small)."""

    def fmt(x):
        if isinstance(x, float):
            return f"{x:.4g}" if abs(x) < 0.01 and x != 0 else f"{x:.3f}"
        return str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(x) for x in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
