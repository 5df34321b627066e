"""The paper's three evaluation metrics: vertex, normal (degrees) and chamfer.

Both meshes are first mapped into the canonical frame of the ground truth (bounding box
centred, longest side 1), the same map applied to both, so the numbers do not depend on
where a mesh sits or how large it is. The metrics are the training losses of
`dmd_jax.losses`, evaluated on one mesh pair; only the frame is added here.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import losses
from dmd_jax.graph import bucket_size
from dmd_jax.mesh import canonical_frame

# A prediction farther than this from the ground truth (in the ground truth's canonical
# frame, where it spans 1) or smaller than its inverse is scored with the safeguards of
# `_scale_safe`: float32 squares overflow near 1e19 and underflow near 1e-19, and lose
# their precision long before.
_SAFE_RANGE = 1e6


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
    return pred, gt, f


def _scale_safe(pred, gt):
    """`(pred, gt, pred for normals, far)` in the ground truth's frame, float64.

    Normals do not change under a uniform scale and a shift, so a prediction of an
    extreme size (a copy of the ground truth 1e15 times larger, say) has its normals
    taken in its own canonical frame, where float32 cannot overflow or underflow; `far`
    (its largest coordinate in the ground truth's frame) says whether the vertex and
    chamfer errors need float64 too.
    """
    frame = canonical_frame(gt)
    with np.errstate(over="ignore", invalid="ignore"):
        p = frame.apply(pred)
        far = float(np.abs(p).max()) if p.size else 0.0
        extent = float(np.ptp(p, axis=0).max()) if p.size else 0.0
    for_normals = p
    if np.all(np.isfinite(pred)) and not (1 / _SAFE_RANGE <= extent <= _SAFE_RANGE):
        try:
            for_normals = canonical_frame(pred).apply(pred)
        except ValueError:  # zero extent: every face degenerate whatever the frame
            pass
    return p, frame.apply(gt), for_normals, far


def _in_gt_frame(pred_vertices, gt_vertices, faces):
    pred, gt, f = _checked(pred_vertices, gt_vertices, faces)
    _, g, for_normals, _ = _scale_safe(pred, gt)
    return jnp.asarray(for_normals), jnp.asarray(g), jnp.asarray(f)


def _far_errors(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """`(vertex, chamfer)` in float64 on the host, for a prediction far off the ground
    truth (the same definitions as `losses.vertex_loss` and `losses.chamfer_distance`)."""
    from scipy.spatial import cKDTree

    with np.errstate(over="ignore", invalid="ignore"):
        vertex = float(np.mean(np.sum((pred - gt) ** 2, axis=1)))
        if not np.all(np.isfinite(pred)):
            return vertex, math.inf
        to_gt = cKDTree(gt).query(pred)[0]
        to_pred = cKDTree(pred).query(gt)[0]
        chamfer = float(np.mean(to_gt**2) + np.mean(to_pred**2))
    return vertex, chamfer


def mesh_metrics(
    pred_vertices, gt_vertices, faces, *, chamfer_block=1024, min_rows: int = 0
) -> dict:
    """Vertex, normal and chamfer errors of a mesh against its ground truth.

    Args:
      pred_vertices: `[n_vertex, 3]` denoised (or noisy) positions, same order as the
        ground truth.
      gt_vertices: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices shared by both meshes.
      chamfer_block: block size of the chamfer search.
      min_rows: pad to at least this many vertex rows (e.g. the largest mesh of an
        evaluation set: one compiled program for the whole set).

    Returns:
      Dict of Python floats:
      `vertex`: mean squared vertex distance (`losses.vertex_loss`, eq. vertex_loss);
      `vertex_per_coord`: the same divided by 3, the per-coordinate mean squared error,
        which is what the paper's tables report (their noisy-input reference values are
        `level² · E[X²]` per coordinate, see `dmd_jax.noise`);
      `normal_deg`: mean angle between face normals in degrees, zero-area ground-truth
        faces left out (`losses.normal_loss`);
      `chamfer`: symmetric chamfer distance of the vertex sets (`losses.chamfer_distance`).
      All lengths in the ground truth's canonical frame. Honest at every scale: a
      prediction far off the ground truth is scored in float64 (`inf` only where even
      float64 overflows), never as a small or perfect error; `normal_deg` is NaN when
      no ground-truth face has a non-zero area (the normal error is then undefined).
    """
    pred64, gt64, f64 = _checked(pred_vertices, gt_vertices, faces)
    p64, g64, for_normals, far = _scale_safe(pred64, gt64)
    pred, gt, f = jnp.asarray(for_normals), jnp.asarray(g64), jnp.asarray(f64)
    # One compiled program per size bucket, not per mesh: the arrays are padded (zeros,
    # faces (0, 0, 0)) and the padding masked, which changes no sum.
    n_vertex, n_face = pred.shape[0], f.shape[0]
    rows_v = bucket_size(max(n_vertex, min_rows))
    # Faces follow the vertex bucket (f <= 2v for a closed mesh, fewer with boundaries),
    # so the bucket pair, hence the program, is one per vertex bucket.
    rows_f = max(2 * rows_v, bucket_size(n_face))
    # Far off: float32 would overflow; _far_errors replaces these two numbers below.
    p_rows = _pad_rows(p64 if far <= _SAFE_RANGE else np.zeros_like(p64), rows_v)
    vertex, normal, chamfer, n_normal = _padded_metrics(
        p_rows,
        _pad_rows(pred, rows_v),
        _pad_rows(gt, rows_v),
        _pad_rows(f, rows_f),
        jnp.arange(rows_v) < n_vertex,
        jnp.arange(rows_f) < n_face,
        chamfer_block,
    )
    vertex, chamfer = float(vertex), float(chamfer)
    if not far <= _SAFE_RANGE:  # NaN included
        vertex, chamfer = _far_errors(p64, g64)
    return {
        "vertex": vertex,
        "vertex_per_coord": vertex / 3.0,
        "normal_deg": float(normal) if int(n_normal) else math.nan,
        "chamfer": chamfer,
    }


def _pad_rows(x, rows: int):
    x = np.asarray(x)
    return jnp.asarray(np.concatenate([x, np.zeros((rows - x.shape[0],) + x.shape[1:], x.dtype)]))


@partial(jax.jit, static_argnums=6)
def _padded_metrics(pred, for_normals, gt, faces, vertex_mask, face_mask, chamfer_block):
    vertex = losses.vertex_loss(pred, gt, vertex_mask=vertex_mask)
    normal = losses.normal_term(for_normals, gt, faces, face_mask=face_mask)
    chamfer = losses.chamfer_distance(
        pred, gt, a_mask=vertex_mask, b_mask=vertex_mask, block_size=chamfer_block
    )
    return vertex, normal.mean() * (180.0 / math.pi), chamfer, normal.count


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
    pred, gt, f = _in_gt_frame(pred_vertices, gt_vertices, faces)
    angles, gt_ok = losses.face_normal_angles(pred, gt, f)
    deg = np.asarray(angles, np.float64) * (180.0 / math.pi)
    return np.where(np.asarray(gt_ok), deg, float(undefined))


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
    """The displayed number of one raw metric value (scaled, fixed decimals)."""
    return f"{float(value) * spec.scale:.{spec.digits}f}"


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
