"""Static pictures of meshes side by side (matplotlib, headless): shaded, zoomed, coloured.

Each mesh is drawn in its own canonical frame with an orthographic camera: faces are
projected to 2-D and painted back to front (`PolyCollection`), so a panel's limits are
the mesh's projected extent and panels fill the figure edge to edge, with no 3-D axes
box around them. One figure holds up to three rows, one column per mesh:

* `shaded`: grey two-sided Lambert shading, to judge edges and flat regions;
* `zoom`: the same, zoomed on one face (e.g. the sharpest feature, `sharpest_face`);
* `values`: faces coloured by a per-face value (e.g. the normal error against the
  clean mesh), on a colour scale from `nice_range` unless given; one colour bar in a
  strip under the row.

`up` names the model's up axis (`"z"`, `"y"` or `"auto"`, see `guess_up_axis`), so a
Y-up scan is seen from above its equator, not from below.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dmd_jax.io import atomic_write
from dmd_jax.mesh import canonical_frame, face_normals_np, validate_mesh

# A fixed view so renders of different methods compare pixel for pixel.
_ELEV, _AZIM = 20.0, -60.0
UP_AXES = ("z", "y", "auto")
_GREY = np.array([0.74, 0.77, 0.84])
# Bounds on the picture: a panel's longer side in inches, and the whole canvas in
# pixels (Agg allocates 4 bytes a pixel at once; 100 M pixels is 400 MB).
MIN_PANEL_SIZE, MAX_PANEL_SIZE = 0.5, 20.0
MIN_DPI, MAX_DPI = 30, 1200
MAX_PIXELS = 100e6
_TITLE_IN = 0.3  # inches of title strip above the first row
_BAR_IN = 0.62  # inches of colour-bar strip under the values row


# The camera angles `render_meshes`, `sharpest_face` and the HTML viewer take, in
# degrees: a turn either way is every view there is; NaN or 1e20 is a mistake.
MAX_VIEW_DEGREES = 360.0


def check_view(elev, azim) -> None:
    """Refuses camera angles that are not finite numbers within ±`MAX_VIEW_DEGREES`.

    Raises:
      ValueError: naming `elev` or `azim` and the value.
    """
    for name, value in (("elev", elev), ("azim", azim)):
        try:
            ok = abs(float(value)) <= MAX_VIEW_DEGREES  # False for NaN
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(
                f"{name} must be an angle from -{MAX_VIEW_DEGREES:g} to {MAX_VIEW_DEGREES:g} "
                f"degrees, got {value!r}"
            )


def _camera(elev: float, azim: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(towards the viewer, screen right, screen up) unit vectors, Z-up world."""
    check_view(elev, azim)
    e, a = math.radians(elev), math.radians(azim)
    view = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    right = np.array([-math.sin(a), math.cos(a), 0.0])
    return view, right, np.cross(view, right)


def check_direction(name: str, value) -> np.ndarray:
    """A camera direction or a point: three finite numbers, as a float64 `[3]` array.

    Raises:
      ValueError: naming `name`, for anything else.
    """
    try:
        d = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        d = None
    if d is None or d.shape != (3,) or not np.all(np.isfinite(d)):
        raise ValueError(f"{name} must be three finite numbers x, y, z, got {value!r}")
    return d


def view_angles(view, up: str = "z") -> tuple[float, float]:
    """`(elev, azim)` in degrees of a camera looking along `view`.

    Args:
      view: `[3]` the direction the camera looks along, in the meshes' coordinates
        (the convention of `dmd_jax.simulate_scan`'s `view`: the sensor's side of the
        surface is the side shown).
      up: `"z"` or `"y"`, the up axis the angles are taken about (`render_meshes`' `up`).

    Raises:
      ValueError: `view` not three finite numbers, or zero.
    """
    d = check_direction("view", view)
    length = float(np.linalg.norm(d))
    if not length > 0:
        raise ValueError(f"view must not be zero, got {view!r}")
    # The camera sits on the side it looks from: towards the viewer is -view.
    towards = _to_z_up((-d / length)[None, :], _resolve_up(up, None, None))[0]
    elev = math.degrees(math.asin(float(np.clip(towards[2], -1.0, 1.0))))
    azim = math.degrees(math.atan2(towards[1], towards[0]))
    return elev, azim


# An open mesh whose faces' area vectors add up to at least this share of its area is
# seen from one side (a single-view scan: 0.63 to 0.69 for `simulate_scan` of the
# shared bunny; a hemisphere 0.5); a closed mesh adds up to 0.
AUTO_VIEW_MIN_OPENNESS = 0.3


def auto_view(meshes) -> np.ndarray | None:
    """The direction to look along that faces a single-view scan, or None.

    The meshes' mean area-weighted face normal, each mesh weighted alike: a range scan's
    faces are wound to face the sensor (`simulate_scan`'s are, as real scans' are), so
    the camera looks against it. None when the normals cancel (a closed mesh, or an open
    one seen from all round, less than `AUTO_VIEW_MIN_OPENNESS`): keep the default view.

    Args:
      meshes: `(vertices [n, 3], faces [f, 3])` pairs.

    Returns:
      `[3]` unit look direction in the meshes' coordinates (for `view_angles`), or None.
    """
    total = np.zeros(3)
    for v, f in meshes:
        v = np.asarray(v, np.float64)
        f = np.asarray(f, np.int64)
        v = canonical_frame(v).apply(v)
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        area = float(np.linalg.norm(cross, axis=1).sum())
        if area > 0:
            total += cross.sum(axis=0) / area
    total /= max(len(meshes), 1)
    openness = float(np.linalg.norm(total))
    if not openness >= AUTO_VIEW_MIN_OPENNESS:
        return None
    return -total / openness


def _to_z_up(v: np.ndarray, up: str) -> np.ndarray:
    """Rotates Y-up coordinates so that +Y becomes +Z (a right-handed turn about X)."""
    if up == "z":
        return v
    if up == "y":
        return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)
    raise ValueError(f"up must be one of {UP_AXES}, got {up!r}")


def guess_up_axis(vertices, faces) -> str:
    """`"y"` or `"z"`: the up axis a mesh most plausibly has.

    Z when the mesh clearly stands on a flat base at the bottom of Z, as CAD parts and
    this project's generated shapes do: faces whose normal is within 25° of the axis
    (either winding) and whose centroid lies in the lowest 5 % of the extent hold at
    least 8 % of the surface area, and 1.5 times as much as the same measure along Y.
    Otherwise Y, the convention of graphics models and scans (OBJ, OFF, PLY): animals
    on legs, busts and reliefs have no flat base to go by. A heuristic: on
    `../shared/meshes` it picks Y for all but `screwdriver.off` (Z), which looks right
    for the 18 Y-up libigl/TGV models; on the procedural categories it picks Z for
    bracket, extrusion, gear, fastener, vase, cup, torus and relief, and Y for the rest,
    which is wrong for the Z-up flange, bottle, csg, blocks and terrain shapes (the
    organic ones have no preferred side). `--up y|z` (or `up=`) overrides it.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    v = canonical_frame(v).apply(v)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = face_normals_np(v, f)
    centroid = v[f].mean(axis=1)
    support = {}
    for name, axis in (("y", 1), ("z", 2)):
        low = v[:, axis].min()
        extent = max(np.ptp(v[:, axis]), 1e-12)
        at_base = centroid[:, axis] <= low + 0.05 * extent
        flat = np.abs(normal[:, axis]) >= math.cos(math.radians(25))
        support[name] = float(area[at_base & flat].sum())
    total = float(area.sum()) or 1.0
    clear_z_base = support["z"] >= 0.08 * total and support["z"] > 1.5 * support["y"]
    return "z" if clear_z_base else "y"


def dihedral_angles(vertices, faces) -> np.ndarray:
    """Per face, the largest angle (degrees) between its normal and a neighbour's.

    Only edges shared by exactly two faces count; a face with none gets 0.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    n = face_normals_np(v, f)
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2)
    edges = edges.reshape(-1, 2)
    owner = np.repeat(np.arange(len(f)), 3)
    key = edges[:, 0] * (int(v.shape[0]) + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    _, start, count = np.unique(key, return_index=True, return_counts=True)
    pairs = start[count == 2]
    a, b = owner[pairs], owner[pairs + 1]
    angle = np.degrees(np.arccos(np.clip(np.sum(n[a] * n[b], axis=1), -1.0, 1.0)))
    out = np.zeros(len(f))
    np.maximum.at(out, a, angle)
    np.maximum.at(out, b, angle)
    return out


def sharpest_face(
    vertices,
    faces,
    *,
    elev: float = _ELEV,
    azim: float = _AZIM,
    up: str = "z",
    crop_size: float = 0.15,
) -> int:
    """A face on the sharpest feature of a mesh that the camera sees: a crop centre.

    Candidates are faces whose largest dihedral angle is within 20 % of the mesh's
    largest and whose normal faces the camera (either winding); of up to 32 of them,
    the one whose zoom window (`crop_size`, canonical units) is most covered by
    surface, with candidates hidden behind another face left out.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    v = _to_z_up(canonical_frame(v).apply(v), _resolve_up(up, v, f))
    sharp = dihedral_angles(v, f)
    candidates = np.flatnonzero(sharp >= 0.8 * sharp.max())
    return _best_in_view(v, f, candidates, np.zeros(len(f)), elev, azim, crop_size)


def _best_in_view(v, f, candidates, score, elev, azim, crop_size) -> int:
    """Of `candidates` (face indices), the one with the best `score` plus the share of
    its zoom window covered by surface; facing the camera preferred, hidden ones (behind
    another face) left out. `v` in the canonical frame, Z up."""
    view, right, screen_up = _camera(elev, azim)
    facing = np.abs(face_normals_np(v, f[candidates]) @ view) > 0.2
    if facing.any():
        candidates = candidates[facing]
    if len(candidates) > 32:
        best_first = candidates[np.argsort(-score[candidates], kind="stable")]
        top = best_first[: 32 if np.ptp(score[candidates]) > 0 else len(best_first)]
        candidates = np.sort(top)
        if len(candidates) > 32:
            candidates = candidates[np.linspace(0, len(candidates) - 1, 32).astype(int)]
    xy = np.stack([v @ right, v @ screen_up], axis=1)
    tri = xy[f]  # [n_face, 3, 2]
    depth = v[f].mean(axis=1) @ view

    def covering(points):
        """[n_point, n_face] bool: the point lies inside the face's projection."""
        p = points[:, None, :]
        d = [
            (tri[None, :, (k + 1) % 3, 0] - tri[None, :, k, 0]) * (p[..., 1] - tri[None, :, k, 1])
            - (tri[None, :, (k + 1) % 3, 1] - tri[None, :, k, 1]) * (p[..., 0] - tri[None, :, k, 0])
            for k in range(3)
        ]
        return ((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0)) | ((d[0] <= 0) & (d[1] <= 0) & (d[2] <= 0))

    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)
    best, best_score = int(candidates[0]), -np.inf
    for c in candidates:
        p = tri[c].mean(axis=0)
        hidden = np.any(covering(p[None])[0] & (depth > depth[c] + 1e-3))
        covered = covering(p + crop_size * grid).any(axis=1).mean()
        total = float(score[c]) + float(covered) - (10.0 if hidden else 0.0)
        if total > best_score:
            best, best_score = int(c), total
    return best


def most_different_face(
    meshes,
    *,
    elev: float = _ELEV,
    azim: float = _AZIM,
    up: str = "z",
    crop_size: float = 0.15,
) -> int:
    """A face where the meshes differ most, in view: a crop centre for `zoom="auto"`.

    Per face, the largest angle between the normals of any two meshes; averaged over the
    zoom window (faces whose centroid lies within `crop_size` of the face's, in the last
    mesh's canonical frame: the clean one of `dmd-jax render --gt`), so one stray face
    does not outweigh a region; the best of those that face the camera and are not
    hidden. Meshes that do not differ give `sharpest_face` of the last one.

    Args:
      meshes: `(vertices [n, 3], faces [f, 3])` pairs sharing their faces.
      elev, azim: the camera, degrees.
      up: the up axis, `"z"`, `"y"` or `"auto"`.
      crop_size: half-width of the zoom window, canonical units.

    Returns:
      The face index (the same in every mesh).

    Raises:
      ValueError: meshes with different faces.
    """
    from scipy.spatial import cKDTree

    ref_v, ref_f = (np.asarray(x) for x in meshes[-1])
    if not all(np.shape(f) == ref_f.shape and np.array_equal(f, ref_f) for _, f in meshes):
        raise ValueError("zoom 'auto' compares faces one to one: the meshes must share faces")
    f = ref_f.astype(np.int64)
    normals = [face_normals_np(np.asarray(v, np.float64), f) for v, _ in meshes]
    spread = np.zeros(len(f))
    for i in range(len(normals)):
        for j in range(i + 1, len(normals)):
            cos = np.clip(np.sum(normals[i] * normals[j], axis=1), -1.0, 1.0)
            spread = np.maximum(spread, np.degrees(np.arccos(cos)))
    v = np.asarray(ref_v, np.float64)
    v = _to_z_up(canonical_frame(v).apply(v), _resolve_up(up, v, f))
    if not spread.max() > 1e-6:
        return sharpest_face(v, f, elev=elev, azim=azim, up="z", crop_size=crop_size)
    centroid = v[f].mean(axis=1)
    candidates = np.argsort(-spread, kind="stable")[:256]
    near = cKDTree(centroid).query_ball_point(centroid[candidates], crop_size)
    window = np.zeros(len(f))
    window[candidates] = [spread[k].mean() for k in near]
    # Scores in units of the best window (coverage, in [0, 1], breaks near-ties).
    score = 4.0 * window / window.max()
    return _best_in_view(v, f, candidates, score, elev, azim, crop_size)


def nice_range(values: Sequence[np.ndarray], percentile: float = 95.0) -> tuple[float, float]:
    """A colour range that resolves the best panel: `(0, p95)`, rounded up.

    `values` holds one array per panel. The top is the smallest, over panels, of each
    panel's `percentile` (panels whose percentile is 0 left out), rounded up to 1, 2,
    2.5 or 5 times a power of ten: the best result's errors span the whole scale, and a
    worse panel (the noisy input) saturates in the brightest colour rather than
    squashing every other panel into the darkest tenth. Values with negative entries
    get a symmetric `(-t, t)` from the absolute values.
    """
    arrays = [np.ravel(np.asarray(x, np.float64)) for x in values]
    arrays = [a[np.isfinite(a)] for a in arrays]
    arrays = [a for a in arrays if a.size]
    if not arrays:
        return 0.0, 1.0
    signed = any(bool((a < 0).any()) for a in arrays)
    tops = [float(np.percentile(np.abs(a) if signed else a, percentile)) for a in arrays]
    tops = [t for t in tops if t > 0]
    top = min(tops) if tops else max(float(np.abs(a).max()) for a in arrays) or 1.0
    power = 10.0 ** math.floor(math.log10(top))
    top = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= top * (1 - 1e-9))
    return (-top, top) if signed else (0.0, top)


def resolve_up(up: str, meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> str:
    """`up` itself, or for `"auto"` the majority of `guess_up_axis` over the meshes.

    Noise can hide a flat base, so several versions of one shape (noisy, denoised,
    clean) vote; a tie goes to Z.
    """
    if up != "auto":
        return _resolve_up(up, None, None)
    votes = [guess_up_axis(v, f) for v, f in meshes]
    return "y" if votes.count("y") > votes.count("z") else "z"


def _resolve_up(up: str, v, f) -> str:
    if up == "auto":
        return guess_up_axis(v, f)
    if up not in ("y", "z"):
        raise ValueError(f"up must be one of {UP_AXES}, got {up!r}")
    return up


def render_meshes(
    meshes: Sequence[tuple[np.ndarray, np.ndarray]],
    path,
    *,
    titles: Sequence[str] | None = None,
    face_values: Sequence[np.ndarray | None] | None = None,
    value_label: str = "normal error (°)",
    value_range: tuple[float, float] | None = None,
    elev: float = _ELEV,
    azim: float = _AZIM,
    up: str = "z",
    view=None,
    panel_size: float = 3.2,
    shaded_row: bool | None = None,
    crop_face: int | None = None,
    zoom: str | None = None,
    zoom_at=None,
    crop_size: float = 0.15,
    cmap: str = "inferno",
    dpi: int = 110,
    overwrite: bool = False,
    max_faces: int = 200_000,
) -> Path:
    """Renders meshes side by side to a PNG: shaded, zoomed and coloured rows.

    Args:
      meshes: `(vertices [n, 3], faces [f, 3])` pairs, each drawn in its own canonical
        frame.
      path: output PNG (written atomically).
      titles: one title per column.
      face_values: per mesh, `[f]` values to colour faces by (e.g. normal error
        against a ground truth), or None (that panel is shaded grey and marked
        `reference`). Without it there is no values row.
      value_label: colour-bar label for `face_values`.
      value_range: colour scale limits; default `nice_range` of all values (0 to the
        95th percentile, rounded up; symmetric if any value is negative).
      elev, azim: camera angles in degrees, about the model's up axis.
      up: the model's up axis, `"z"`, `"y"` or `"auto"` (`resolve_up`: the meshes vote).
      view: instead of `elev`/`azim`, the direction `[3]` the camera looks along, in the
        meshes' coordinates (`simulate_scan`'s `view` shows the side its sensor saw;
        `view_angles`), or `"auto"`: facing a single-view scan (`auto_view`), and
        `elev`/`azim` for a closed mesh.
      panel_size: inches of a panel's longer side, `MIN_PANEL_SIZE` (0.5) to
        `MAX_PANEL_SIZE` (20).
      shaded_row: add a grey shaded row above the values; default: only when there are
        no `face_values` (then it is the only row).
      crop_face: a face index (the same in every mesh, e.g. from `sharpest_face`):
        adds a shaded row zoomed on that face.
      zoom: instead of `crop_face`, `"sharpest"` (`sharpest_face` of the last mesh) or
        `"auto"` (`most_different_face`: where the meshes differ most); both need
        meshes that share their faces.
      zoom_at: instead of `crop_face`, a point `[3]` in the meshes' coordinates: the
        zoom row is centred on it in every panel (each mesh in its own canonical frame).
      crop_size: half-width of the zoom window, in canonical units (bounding box
        longest side 1).
      cmap: matplotlib colour map of the values row.
      dpi: pixels per inch, `MIN_DPI` (30) to `MAX_DPI` (1200).
      overwrite: replace an existing file.
      max_faces: refuse meshes larger than this (matplotlib is not a rasteriser for
        millions of faces).

    Returns:
      The path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    if not meshes:
        raise ValueError("render_meshes needs at least one mesh")
    n_col = len(meshes)
    titles = list(titles) if titles is not None else [""] * n_col
    has_values = face_values is not None
    face_values = list(face_values) if has_values else [None] * n_col
    if len(titles) != n_col or len(face_values) != n_col:
        raise ValueError("titles and face_values need one entry per mesh")
    if not (isinstance(panel_size, int | float) and MIN_PANEL_SIZE <= panel_size <= MAX_PANEL_SIZE):
        # Bounds, not only a sign: 150 inches asks Agg for a 1 GB canvas and dies in C++,
        # and a panel under a pixel leaves Agg an empty image it cannot write.
        raise ValueError(
            f"panel_size must be in [{MIN_PANEL_SIZE:g}, {MAX_PANEL_SIZE:g}] inches, "
            f"got {panel_size!r}"
        )
    if not (isinstance(dpi, int | float) and MIN_DPI <= dpi <= MAX_DPI):
        raise ValueError(f"dpi must be in [{MIN_DPI}, {MAX_DPI}], got {dpi!r}")
    if sum(x is not None for x in (crop_face, zoom, zoom_at)) > 1:
        raise ValueError("give one of crop_face, zoom and zoom_at")
    if zoom not in (None, "sharpest", "auto"):
        raise ValueError(f"zoom must be 'sharpest', 'auto' or None, got {zoom!r}")
    if zoom_at is not None:
        zoom_at = check_zoom_point(zoom_at, meshes)
    prepared, frames = [], []
    for i, (v, f) in enumerate(meshes):
        if np.shape(f)[:1] and np.shape(f)[0] > max_faces:
            raise ValueError(f"mesh {i} has {np.shape(f)[0]} faces; render supports ≤ {max_faces}")
        if np.ndim(f) != 2 or np.shape(f)[1] != 3 or len(f) == 0:
            raise ValueError(f"mesh {i}: faces must be a non-empty [n_face, 3] array")
        # The same checks as denoise's (indices in range, finite coordinates): one
        # ValueError naming the mesh, never an IndexError from deep in the drawing.
        v, f = validate_mesh(v, f, name=f"mesh {i}")
        v, f = v.astype(np.float64), f.astype(np.int64)
        if crop_face is not None and not 0 <= crop_face < len(f):
            raise ValueError(f"crop_face {crop_face} is out of range for mesh {i}")
        frames.append(canonical_frame(v))
        prepared.append((frames[-1].apply(v), f))
    for i, fv in enumerate(face_values):
        if fv is not None and np.shape(fv) != (len(prepared[i][1]),):
            raise ValueError(f"face_values[{i}] needs one value per face of mesh {i}")
    up = resolve_up(up, prepared)
    if isinstance(view, str):
        if view != "auto":
            raise ValueError(f"view must be 'auto' or three numbers x, y, z, got {view!r}")
        view = auto_view(prepared)
    if view is not None:
        elev, azim = view_angles(view, up)
    if zoom is not None:
        ref_f = prepared[-1][1]
        if any(f.shape != ref_f.shape or (f != ref_f).any() for _, f in prepared):
            raise ValueError(f"zoom {zoom!r} needs meshes that share their faces")
        if zoom == "sharpest":
            crop_face = sharpest_face(*prepared[-1], elev=elev, azim=azim, up=up)
        else:
            crop_face = most_different_face(prepared, elev=elev, azim=azim, up=up)
    vals = [np.asarray(x, np.float64) for x in face_values if x is not None]
    if has_values and not vals:
        has_values = False
    if has_values and value_range is None:
        value_range = nice_range(vals)
    if value_range is not None and not value_range[1] > value_range[0]:
        raise ValueError(f"value_range needs low < high, got {tuple(value_range)}")

    view, right, screen_up = _camera(elev, azim)
    # Light from the upper left of the viewer, fixed to the camera.
    light = view + 0.55 * screen_up - 0.45 * right
    light /= np.linalg.norm(light)
    projected, crop_centres = [], []
    for (v, f), frame in zip(prepared, frames, strict=True):
        v = _to_z_up(v, up)
        xy = np.stack([v @ right, v @ screen_up], axis=1)
        order = np.argsort(v[f].mean(axis=1) @ view)  # painter's algorithm: far first
        shade = 0.22 + 0.78 * np.abs(face_normals_np(v, f) @ light)
        projected.append((xy, f, order, shade))
        if zoom_at is not None:
            point = _to_z_up(frame.apply(zoom_at)[None, :], up)[0]
            crop_centres.append(np.array([point @ right, point @ screen_up]))
        elif crop_face is not None:
            crop_centres.append(xy[f[crop_face]].mean(axis=0))

    # Panel shape: the projected extent of the first mesh, clamped to 1:2 .. 2:1.
    lo = np.min([p[0].min(axis=0) for p in projected], axis=0)
    hi = np.max([p[0].max(axis=0) for p in projected], axis=0)
    span = hi - lo
    aspect = float(np.clip(span[1] / max(span[0], 1e-12), 0.5, 2.0))
    panel_w, panel_h = (
        (panel_size, panel_size * aspect)
        if aspect <= 1
        else (
            panel_size / aspect,
            panel_size,
        )
    )
    rows = []
    if shaded_row or not has_values:
        rows.append("shaded")
    if crop_centres:
        rows.append("zoom")
    if has_values:
        rows.append("values")
    pixels = n_col * panel_w * len(rows) * panel_h * dpi * dpi
    if pixels > MAX_PIXELS:
        raise ValueError(
            f"a {n_col} x {len(rows)} picture of {panel_size:g}-inch panels at {dpi} dpi "
            f"has {pixels / 1e6:.0f} M pixels, over the {MAX_PIXELS / 1e6:.0f} M limit "
            "(fewer panels, a smaller panel_size or dpi)"
        )
    title_in = _TITLE_IN * (1 + max(t.count("\n") for t in titles)) if any(titles) else 0.0
    # The colour bar goes into the values cell of a mesh without values (the reference,
    # which would only repeat its shaded panel), else into a strip under the figure.
    bar_cell = next((i for i, x in enumerate(face_values) if x is None), None)
    bar_in = _BAR_IN if has_values and bar_cell is None else 0.0
    fig_w = panel_w * n_col
    fig_h = title_in + panel_h * len(rows) + bar_in
    fig = plt.figure(figsize=(fig_w, fig_h))
    cm = plt.get_cmap(cmap)
    zoom_factor = max(span.max(), 1e-12) / (2 * crop_size)

    def limits(center, half_w, half_h, ax):
        ax.set_xlim(center[0] - half_w, center[0] + half_w)
        ax.set_ylim(center[1] - half_h, center[1] + half_h)

    for r, row in enumerate(rows):
        bottom = bar_in + panel_h * (len(rows) - 1 - r)
        for c, (xy, f, order, shade) in enumerate(projected):
            ax = fig.add_axes(
                [c * panel_w / fig_w, bottom / fig_h, panel_w / fig_w, panel_h / fig_h]
            )
            ax.set_axis_off()
            fv = face_values[c]
            if row == "values" and c == bar_cell:
                bar = ax.inset_axes([0.12, 0.22, 0.76, 0.07])
                _colour_bar(fig, bar, cm, value_range, value_label, vals)
                continue
            if row == "values" and fv is not None:
                t = (np.asarray(fv, np.float64) - value_range[0]) / (
                    value_range[1] - value_range[0]
                )
                colors = cm(np.clip(np.nan_to_num(t), 0, 1))
                colors[:, :3] *= (0.6 + 0.4 * shade)[:, None]
            else:
                colors = np.concatenate(
                    [shade[:, None] * _GREY[None, :], np.ones((len(f), 1))], axis=1
                )
            ax.add_collection(
                PolyCollection(
                    xy[f[order]],
                    facecolors=colors[order],
                    edgecolors=colors[order],
                    linewidths=0.15,
                    antialiaseds=False,
                )
            )
            # Half-extents of a panel in data units (2 % margin), widened to its shape.
            half = 0.5 * np.maximum(span, 1e-12) * 1.04
            if half[0] / half[1] < panel_w / panel_h:
                half[0] = half[1] * panel_w / panel_h
            else:
                half[1] = half[0] * panel_h / panel_w
            if row == "zoom":
                limits(crop_centres[c], half[0] / zoom_factor, half[1] / zoom_factor, ax)
            else:
                limits(0.5 * (lo + hi), half[0], half[1], ax)
            label = {"shaded": "", "zoom": f"zoom ×{zoom_factor:.1f}", "values": ""}[row]
            if row == "values" and fv is None:
                label = "reference"
            if label:
                ax.text(
                    0.03,
                    0.97,
                    label,
                    transform=ax.transAxes,
                    ha="left",
                    va="top",
                    fontsize=8,
                    color="0.25",
                )
            if r == 0 and titles[c]:
                fig.text(
                    (c + 0.5) * panel_w / fig_w,
                    1 - 0.5 * title_in / fig_h,
                    titles[c],
                    ha="center",
                    va="center",
                    fontsize=9,
                )
    if has_values and bar_cell is None:
        bar = fig.add_axes([0.2, (0.34 * bar_in) / fig_h, 0.6, 0.16 * bar_in / fig_h])
        _colour_bar(fig, bar, cm, value_range, value_label, vals)

    def write(tmp):
        fig.savefig(tmp, dpi=dpi, format="png")

    try:
        return atomic_write(path, write, overwrite=overwrite)
    finally:
        plt.close(fig)


def check_zoom_point(point, meshes, name: str = "zoom_at") -> np.ndarray:
    """A zoom centre `[3]` that lies on or near the meshes, as float64.

    Raises:
      ValueError: naming `name`: not three finite numbers, or outside every mesh's
        bounding box grown by a tenth of its longest side (the zoom would show nothing).
    """
    point = check_direction(name, point)
    for v, _ in meshes:
        # The canonical frame's box has half-sides of at most 0.5.
        if np.all(np.abs(canonical_frame(v).apply(point)) <= 0.6):
            return point
    raise ValueError(
        f"{name} {point.tolist()} lies outside the meshes (beyond their bounding boxes); "
        "its zoom would be empty"
    )


def saturation_note(value_range, vals) -> str:
    """Says where values leave the colour range (they take its end colours), or `""`."""
    lo, hi = value_range
    above = any(float(np.nanmax(x)) > hi for x in vals)
    below = any(float(np.nanmin(x)) < lo for x in vals)
    if above and below:
        return f"end colours: below {lo:.3g} and above {hi:.3g}"
    if above:
        return f"top colour: {hi:.3g} and above"
    if below:
        return f"bottom colour: {lo:.3g} and below"
    return ""


def _colour_bar(fig, cax, cm, value_range, value_label, vals) -> None:
    import matplotlib.pyplot as plt

    sm = plt.cm.ScalarMappable(cmap=cm, norm=plt.Normalize(*value_range))
    cb = fig.colorbar(sm, cax=cax, orientation="horizontal")
    cb.ax.tick_params(labelsize=7, length=2, pad=1)
    note = saturation_note(value_range, vals)
    cb.set_label(value_label + (f"\n{note}" if note else ""), fontsize=8, labelpad=2)
    cb.ax.xaxis.set_label_position("top")


def white_fraction(png_path, *, threshold: int = 250) -> float:
    """Share of a PNG's pixels that are blank (every channel ≥ `threshold`)."""
    from PIL import Image

    with Image.open(png_path) as image:
        rgb = np.asarray(image.convert("RGB"))
    return float(np.mean(np.all(rgb >= threshold, axis=-1)))
