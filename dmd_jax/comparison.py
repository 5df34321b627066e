"""Per-shape comparison of denoisers: ratios to the best other method, crease and flat faces.

A mean in degrees over meshes is carried by the few hard meshes whose errors are large;
a method can lead on average and still lose on most shapes. These measures weigh every
mesh alike:

* `ratios_to_best_other`: per case (mesh, noise condition), a method's error divided by
  the lowest error of every *other* method compared (below 1: it wins the case).
* `geometric_mean`: the mean of those ratios in log space, so 0.5 and 2 cancel.
* `share_within`: the fraction of cases where a method is best or within 5 %.
* `summarise_ratios`: all of these for one group of cases, with the worst ratio and the
  case (mesh) it comes from, so one large loss (a 7x error on one pyramid) shows beside
  the mean instead of hiding in it.

and split the normal error by region of the clean mesh (`crease_faces`): faces along a
sharp crease and the rest (flats and smooth parts), where filters and networks fail in
different ways (over-smoothed creases, wavy flats). `is_cad` names the meshes whose clean
geometry is mostly flat with sharp creases (machined parts), from the geometry alone, so
a new mesh is classified the same way without a hand-made list.

Host side, NumPy; the error values come from `dmd_jax.metrics`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from dmd_jax.constants import CREASE_ANGLE
from dmd_jax.mesh import edge_dihedral_angles

# A flat edge: its faces' normals differ by at most this (degrees).
FLAT_ANGLE = 1.0
# `is_cad`: a mesh is a CAD part when at least this share of its interior edges is flat
# and at least `CAD_MIN_CREASE_SHARE` lies on creases. A scan or a smooth organic shape has
# few exactly flat edges (its faces meet at a few degrees everywhere); a machined part is
# made of planes (and cylinders, whose edges along the axis are flat) meeting at creases.
CAD_MIN_FLAT_SHARE = 0.3
CAD_MIN_CREASE_SHARE = 0.005
# `share_within`: best or within this factor of the best other method.
WITHIN = 1.05
# Ratios of normal errors count errors below this many degrees as this (`floor` of
# `ratios_to_best_other`): on a clean mesh a filter that leaves every face alone scores
# ~0°, and a ratio against ~0 would be unbounded noise. A tenth of a degree is far below
# what a rendering shows, and far below every noisy condition's errors (≥ 1°), whose
# ratios it leaves unchanged.
RATIO_FLOOR_DEG = 0.1


def crease_faces(vertices, faces, angle: float = CREASE_ANGLE) -> np.ndarray:
    """`[n_face]` bool: faces with an edge of dihedral angle at least `angle` degrees."""
    a, b, dihedral = edge_dihedral_angles(vertices, faces)
    out = np.zeros(np.asarray(faces).shape[0], bool)
    sharp = dihedral >= angle
    out[a[sharp]] = True
    out[b[sharp]] = True
    return out


def surface_shares(vertices, faces) -> tuple[float, float]:
    """`(flat, crease)`: shares of the interior edges that are flat (`FLAT_ANGLE`) and on
    creases (`CREASE_ANGLE`)."""
    _, _, dihedral = edge_dihedral_angles(vertices, faces)
    if dihedral.size == 0:
        return 0.0, 0.0
    return float(np.mean(dihedral <= FLAT_ANGLE)), float(np.mean(dihedral >= CREASE_ANGLE))


def is_cad(vertices, faces) -> bool:
    """Whether a clean mesh is a CAD part: mostly flat edges, and creases (see the
    module doc and `CAD_MIN_FLAT_SHARE`, `CAD_MIN_CREASE_SHARE`)."""
    flat, crease = surface_shares(vertices, faces)
    return flat >= CAD_MIN_FLAT_SHARE and crease >= CAD_MIN_CREASE_SHARE


def region_errors(face_errors, crease) -> tuple[float, float]:
    """Mean of per-face errors on crease faces and on the other faces.

    Args:
      face_errors: `[n_face]` errors (e.g. `metrics.face_normal_errors_deg`); NaN marks a
        face whose error is undefined, left out.
      crease: `[n_face]` bool, `crease_faces` of the clean mesh.

    Returns:
      `(crease, flat)` means; NaN for a region with no face.

    Raises:
      ValueError: the two arrays differ in shape.
    """
    e = np.asarray(face_errors, np.float64)
    c = np.asarray(crease, bool)
    if e.shape != c.shape or e.ndim != 1:
        raise ValueError(f"face_errors {e.shape} and crease {c.shape} must be equal [n_face]")
    ok = np.isfinite(e)

    def mean(mask):
        m = mask & ok
        return float(e[m].mean()) if m.any() else math.nan

    return mean(c), mean(~c)


def ratios_to_best_other(
    errors: Mapping[object, Mapping[str, float]],
    method: str,
    others: Sequence[str],
    *,
    floor: float = 0.0,
) -> dict[object, float]:
    """`method`'s error over the lowest error of `others`, per case.

    Args:
      errors: `{case: {method: error}}` (a case is any key, e.g. `(set, mesh, level)`).
      method: the method to rate.
      others: the methods it is compared with (`method` itself is skipped if listed).
      floor: errors below it count as it (e.g. `RATIO_FLOOR_DEG` for normal errors, so
        a clean mesh left alone by every method rates 1, not 0/0).

    Returns:
      `{case: ratio}` for every case holding `method` and at least one other; a case where
      the best other error is 0 gives `inf` (or 1 when `method`'s is 0 too).

    Raises:
      ValueError: no other method to compare with.
    """
    rivals = [m for m in others if m != method]
    if not rivals:
        raise ValueError(f"no method other than {method!r} to compare with")
    out = {}
    for case, errs in errors.items():
        present = [errs[m] for m in rivals if m in errs]
        if method not in errs or not present:
            continue
        best = max(min(present), floor)
        mine = max(errs[method], floor)
        out[case] = (1.0 if mine == 0 else math.inf) if best == 0 else mine / best
    return out


def geometric_mean(values) -> float:
    """The geometric mean of positive numbers (NaN for none).

    Raises:
      ValueError: a value that is not positive or not finite.
    """
    x = np.asarray(list(values), np.float64)
    if x.size == 0:
        return math.nan
    if not np.all(np.isfinite(x) & (x > 0)):
        raise ValueError("geometric_mean needs finite positive values")
    return float(np.exp(np.mean(np.log(x))))


def share_within(ratios, factor: float = WITHIN) -> float:
    """The share of ratios at most `factor` (best, or within `factor - 1` of the best)."""
    x = np.asarray(list(ratios), np.float64)
    return float(np.mean(x <= factor)) if x.size else math.nan


class RatioSummary(NamedTuple):
    """One group of per-case ratios (`summarise_ratios`).

    Attributes:
      n: cases.
      geometric_mean: their geometric mean (`geometric_mean`).
      worst: the largest ratio.
      worst_case: the case (key) it belongs to.
      within: cases at most `WITHIN` (best or within 5 %).
      best: cases at most 1.
    """

    n: int
    geometric_mean: float
    worst: float
    worst_case: object
    within: int
    best: int


def summarise_ratios(ratios: Mapping[object, float]) -> RatioSummary:
    """The geometric mean, the worst ratio and its case, and the wins of `{case: ratio}`.

    Raises:
      ValueError: no ratio, or one that is not finite and positive.
    """
    if not ratios:
        raise ValueError("summarise_ratios needs at least one ratio")
    values = list(ratios.values())
    worst_case = max(ratios, key=ratios.get)
    return RatioSummary(
        n=len(values),
        geometric_mean=geometric_mean(values),
        worst=float(ratios[worst_case]),
        worst_case=worst_case,
        within=sum(v <= WITHIN for v in values),
        best=sum(v <= 1.0 for v in values),
    )
