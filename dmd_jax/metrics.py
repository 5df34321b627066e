"""The paper's three evaluation metrics: vertex, normal (degrees) and chamfer.

Both meshes are first mapped into the canonical frame of the ground truth (bounding box
centred, longest side 1), the same map applied to both, so the numbers do not depend on
where a mesh sits or how large it is. The definitions are those of the training losses
(`dmd_jax.losses.vertex_loss`, `normal_loss`, `chamfer_distance`), computed here on the
host in float64 (NumPy, and SciPy's k-d tree for the chamfer term's nearest
neighbours) whatever JAX's precision: float32 in the canonical frame of a scene with a
small part far away loses that part's faces and errors to rounding, and an all-pairs
nearest-vertex search is quadratic (12 s at 82k faces, where the tree takes 0.1 s).

A face has zero area, and no normal, when its height is at most `ZERO_AREA_RATIO` of
its own longest edge (`zero_area_faces`): a test relative to the face itself, so a part
a million times smaller than the rest of the scene, or two parts 1e8 apart, keep their
faces.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from dmd_jax.mesh import canonical_frame

# A face is degenerate (zero area, undefined normal) when twice its area is at most this
# share of its longest edge squared, i.e. its height is at most 1e-12 of that edge: far
# above float64's rounding of a truly flat face (~1e-16), far below any real sliver.
ZERO_AREA_RATIO = 1e-12


def _checked(pred_vertices, gt_vertices, faces):
    pred = np.asarray(pred_vertices, np.float64)
    gt = np.asarray(gt_vertices, np.float64)
    f = np.asarray(faces)
    if pred.ndim != 2 or pred.shape[-1] != 3:
        raise ValueError(f"pred_vertices must have shape [n_vertex, 3], got {pred.shape}")
    if pred.shape != gt.shape:
        raise ValueError(
            f"pred_vertices and gt_vertices must correspond one to one, got shapes "
            f"{pred.shape} and {gt.shape}"
        )
    if f.ndim != 2 or f.shape[-1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integer [n_face, 3], got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= gt.shape[0]):
        raise ValueError(f"face indices must lie in [0, {gt.shape[0]})")
    return pred, gt, f.astype(np.int64)


def face_normals_checked(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals in float64 at any scale, and which faces have one.

    Each face's edges are divided by their largest coordinate before the cross product,
    so neither a face of size 1e-300 nor one of 1e300 underflows or overflows, and the
    zero-area test compares the face with itself, not with the whole mesh.

    Args:
      vertices: `[n_vertex, 3]` positions (any float dtype; computed in float64).
      faces: `[n_face, 3]` int vertex indices.

    Returns:
      `(normals, ok)`: `[n_face, 3]` float64 unit normals (right-hand rule), zero rows
      where `ok` is False; `[n_face]` bool, False for a face of zero area (its height at
      most `ZERO_AREA_RATIO` of its longest edge) or with a non-finite corner.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        e1, e2, e3 = p1 - p0, p2 - p0, p2 - p1
        big = np.max(np.abs(np.concatenate([e1, e2, e3], axis=1)), axis=1)
        unit = np.where(np.isfinite(big) & (big > 0), big, 1.0)[:, None]
        a, b, c = e1 / unit, e2 / unit, e3 / unit
        cross = np.cross(a, b)
        doubled = np.linalg.norm(cross, axis=1)  # twice the area, in the face's own unit
        longest_sq = np.max(np.stack([_sq(a), _sq(b), _sq(c)]), axis=0)
        ok = np.isfinite(big) & (big > 0) & (doubled > ZERO_AREA_RATIO * longest_sq)
        normals = np.where(ok[:, None], cross / np.where(ok, doubled, 1.0)[:, None], 0.0)
    return normals, ok


def _sq(x: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", x, x)


def zero_area_faces(vertices, faces) -> np.ndarray:
    """`[n_face]` bool: the faces without a normal (`face_normals_checked`'s `not ok`)."""
    return ~face_normals_checked(vertices, faces)[1]


def _normal_angles(pred, gt, f) -> tuple[np.ndarray, np.ndarray]:
    """`(angles, gt_ok)`: `[n_face]` radians between the unit normals of `pred` and
    `gt`, π/2 where `pred`'s face is degenerate (`losses.face_normal_angles`), and
    whether the ground truth's face has a normal."""
    n_p, ok_p = face_normals_checked(pred, f)
    n_t, ok_t = face_normals_checked(gt, f)
    # atan2(|n_p × n_t|, n_p · n_t): exact near 0 and π, where arccos is not.
    angle = np.arctan2(np.linalg.norm(np.cross(n_p, n_t), axis=1), _dot(n_p, n_t))
    return np.where(ok_p & ok_t, angle, 0.5 * math.pi), ok_t


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _nearest(points: np.ndarray, tree_points: np.ndarray) -> np.ndarray | None:
    """`[n]` index of the nearest of `tree_points` to each of `points` (k-d tree), or
    None where a squared distance overflows float64 (the tree then finds no neighbour)."""
    from scipy.spatial import cKDTree

    index = cKDTree(tree_points).query(points)[1]
    return None if np.any(index >= len(tree_points)) else index


def mesh_metrics(pred_vertices, gt_vertices, faces, *, chamfer_block=None, min_rows=0) -> dict:
    """Vertex, normal and chamfer errors of a mesh against its ground truth.

    Args:
      pred_vertices: `[n_vertex, 3]` denoised (or noisy) positions, same order as the
        ground truth.
      gt_vertices: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices shared by both meshes.
      chamfer_block, min_rows: ignored; kept for callers of the former blockwise JAX
        computation (which padded to `min_rows` to share a compiled program).

    Returns:
      Dict of Python floats:
      `vertex`: mean squared vertex distance (`losses.vertex_loss`, eq. vertex_loss);
      `vertex_per_coord`: the same divided by 3, the per-coordinate mean squared error,
        which is what the paper's tables report (their noisy-input reference values are
        `level² · E[X²]` per coordinate, see `dmd_jax.noise`);
      `normal_deg`: mean angle between face normals in degrees, zero-area ground-truth
        faces left out (`losses.normal_loss`; zero area is judged per face against its
        own edges, `face_normals_checked`), a face degenerate only in the prediction
        counted as 90°;
      `chamfer`: symmetric chamfer distance of the vertex sets (`losses.chamfer_distance`).
      Lengths in the ground truth's canonical frame, so a small part of a large scene
      has small vertex and chamfer errors by definition; the normal error is free of
      scale and counts every face alike. All in float64: honest at every scale, never
      a rounded-away or perfect error for a mesh that differs (`inf` only where even
      float64 overflows); `normal_deg` is NaN when no ground-truth face has a non-zero
      area (the normal error is then undefined).

    Raises:
      ValueError: shapes that do not match, non-integer or out-of-range faces, a
        ground truth with non-finite coordinates or zero extent.
    """
    pred, gt, f = _checked(pred_vertices, gt_vertices, faces)
    frame = canonical_frame(gt)
    with np.errstate(over="ignore", invalid="ignore"):
        # The difference before the scaling: exact for nearby points at any offset.
        vertex = float(np.mean(_sq((pred - gt) / frame.scale))) if len(gt) else 0.0
        chamfer = _chamfer(pred, gt, frame)
    angles, gt_ok = _normal_angles(pred, gt, f)
    normal = float(np.degrees(angles[gt_ok].mean())) if gt_ok.any() else math.nan
    return {
        "vertex": vertex,
        "vertex_per_coord": vertex / 3.0,
        "normal_deg": normal,
        "chamfer": chamfer,
    }


def _chamfer(pred: np.ndarray, gt: np.ndarray, frame) -> float:
    """`mean_p min_g |p − g|² + mean_g min_p |p − g|²` in the ground truth's frame
    (`losses.chamfer_distance`); `inf` for a prediction whose coordinates overflow
    float64 in that frame.

    The tree finds each nearest point in frame coordinates; the distance is then taken
    between the input coordinates and scaled, so a part at an offset of 1e8 keeps
    every digit its coordinates hold (the frame's rounding would cost four of them).
    """
    p, g = frame.apply(pred), frame.apply(gt)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(g))):
        return math.inf
    if len(p) == 0:
        return 0.0
    near_gt, near_pred = _nearest(p, g), _nearest(g, p)
    if near_gt is None or near_pred is None:
        return math.inf
    to_gt = _sq((pred - gt[near_gt]) / frame.scale)
    to_pred = _sq((gt - pred[near_pred]) / frame.scale)
    return float(np.mean(to_gt) + np.mean(to_pred))


def face_normal_errors_deg(pred_vertices, gt_vertices, faces, *, undefined=0.0) -> np.ndarray:
    """Angle between corresponding face normals, per face, in degrees (for colour maps).

    Args:
      pred_vertices: `[n_vertex, 3]` positions.
      gt_vertices: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      undefined: value for faces of zero area in the ground truth, whose normal error is
        undefined (`math.nan` marks them; 0 keeps colour-map ranges finite).

    Returns:
      `[n_face]` float64 NumPy array in `[0, 180]`; a face degenerate only in the
      prediction gets 90 (see `losses.face_normal_angles`).
    """
    pred, gt, f = _checked(pred_vertices, gt_vertices, faces)
    angles, gt_ok = _normal_angles(pred, gt, f)
    return np.where(gt_ok, np.degrees(angles), float(undefined))


# --------------------------------------------------------------------------------------
# One vocabulary for printing the metrics: names, units, scaling, legend.
# `dmd-jax evaluate`, the demo, benchmarks/quality/sota_lite.py and the notebooks all print
# through these, so a number means the same wherever it appears.
# --------------------------------------------------------------------------------------


class MetricSpec(NamedTuple):
    """How one entry of `mesh_metrics` is shown to a reader."""

    key: str  # key in the dict `mesh_metrics` returns
    name: str  # short column name
    unit: str  # unit of the displayed (scaled) number
    scale: float  # displayed number = raw value × scale
    digits: int  # decimals shown
    meaning: str  # one phrase for the legend


VERTEX = MetricSpec(
    "vertex_per_coord",
    "vertex",
    "×1e-4",
    1e4,
    3,
    "mean squared vertex error per coordinate (the paper's vertex metric)",
)
VERTEX_SUM = MetricSpec(
    "vertex",
    "vertex xyz",
    "×1e-4",
    1e4,
    3,
    "squared vertex distance summed over x, y, z (3 × vertex; the training loss)",
)
NORMAL = MetricSpec(
    "normal_deg", "normal", "°", 1.0, 2, "mean angle between corresponding face normals"
)
CHAMFER = MetricSpec(
    "chamfer",
    "chamfer",
    "×1e-4",
    1e4,
    3,
    "symmetric chamfer distance (squared) between the vertex sets",
)

# The three metrics shown by default, in this order (the paper's Table II columns).
DEFAULT_METRICS: tuple[MetricSpec, ...] = (VERTEX, NORMAL, CHAMFER)
ALL_METRICS: dict[str, MetricSpec] = {m.key: m for m in (VERTEX, VERTEX_SUM, NORMAL, CHAMFER)}

FRAME_NOTE = (
    "lengths in the clean mesh's canonical frame (bounding box centred, longest side 1); "
    "lower is better"
)


def metric_header(spec: MetricSpec) -> str:
    """Column header of a metric: `vertex (×1e-4)`, `normal (°)`."""
    return f"{spec.name} ({spec.unit})"


def format_metric(spec: MetricSpec, value: float) -> str:
    """The displayed number of one raw metric value (scaled, fixed decimals).

    A value that is not zero but would show as `0.000` (a small part of a large scene,
    say) is written with two significant digits instead (`3.2e-09`): never a perfect
    score for a mesh that differs.
    """
    shown = float(value) * spec.scale
    text = f"{shown:.{spec.digits}f}"
    if shown != 0.0 and math.isfinite(shown) and float(text) == 0.0:
        return f"{shown:.1e}"
    return text


def metric_cells(metrics: dict, specs=DEFAULT_METRICS) -> list[str]:
    """One table row's cells for a `mesh_metrics` dict."""
    return [format_metric(s, metrics[s.key]) for s in specs]


def metrics_legend(specs=DEFAULT_METRICS) -> str:
    """The legend line printed under every metrics table."""
    parts = [f"{s.name} ({s.unit}): {s.meaning}" for s in specs]
    return "; ".join(parts) + "; " + FRAME_NOTE + "."


def metrics_table(
    rows: dict, specs=DEFAULT_METRICS, *, label: str = "mesh", style: str = "markdown"
) -> str:
    """A table of metrics, one row per `name -> mesh_metrics dict`, then the legend line.

    Args:
      rows: `{row label: metrics dict}`; extra keys of a dict are ignored.
      specs: the metrics to show, as columns.
      label: header of the first column.
      style: `"markdown"` (GitHub table) or `"text"` (aligned columns for a terminal).
    """
    header = [label] + [metric_header(s) for s in specs]
    body = [[str(name), *metric_cells(m, specs)] for name, m in rows.items()]
    if style == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * len(specs)]
        lines += ["| " + " | ".join(row) + " |" for row in body]
    elif style == "text":
        widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]
        lines = [
            "  ".join(
                c.ljust(w) if i == 0 else c.rjust(w)
                for i, (c, w) in enumerate(zip(row, widths, strict=True))
            ).rstrip()
            for row in [header, *body]
        ]
    else:
        raise ValueError(f"style must be 'markdown' or 'text', got {style!r}")
    return "\n".join(lines) + "\n\n" + metrics_legend(specs) + "\n"
