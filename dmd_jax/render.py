"""Shaded renders of meshes side by side (matplotlib, headless), optional error colour maps."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dmd_jax.io import atomic_write
from dmd_jax.mesh import canonical_frame

# A fixed view and light so renders of different methods compare pixel for pixel.
_ELEV, _AZIM = 20.0, -60.0
_LIGHT = np.array([0.4, -0.6, 0.7])


def _face_normals_np(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _view_direction(elev: float, azim: float) -> np.ndarray:
    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def render_meshes(
    meshes: Sequence[tuple[np.ndarray, np.ndarray]],
    path,
    *,
    titles: Sequence[str] | None = None,
    face_values: Sequence[np.ndarray | None] | None = None,
    value_label: str = "normal error (deg)",
    value_range: tuple[float, float] | None = None,
    elev: float = _ELEV,
    azim: float = _AZIM,
    panel_size: float = 3.2,
    overwrite: bool = False,
    max_faces: int = 200_000,
) -> Path:
    """Renders meshes side by side to a PNG, each in its own canonical frame.

    Args:
      meshes: `(vertices [n, 3], faces [f, 3])` pairs.
      path: output PNG (written atomically).
      titles: one title per panel.
      face_values: per panel, `[f]` values to colour faces by (e.g. normal error against
        a ground truth), or None for grey Lambert shading.
      value_label: colour-bar label for `face_values`.
      value_range: colour scale limits; default 0 to the 99th percentile over panels.
      elev, azim: camera angles in degrees.
      panel_size: inches per panel.
      overwrite: replace an existing file.
      max_faces: refuse meshes larger than this (matplotlib is not a rasteriser for
        millions of faces).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if not meshes:
        raise ValueError("render_meshes needs at least one mesh")
    titles = list(titles) if titles is not None else [""] * len(meshes)
    face_values = list(face_values) if face_values is not None else [None] * len(meshes)
    if len(titles) != len(meshes) or len(face_values) != len(meshes):
        raise ValueError("titles and face_values need one entry per mesh")
    vals = [np.asarray(x) for x in face_values if x is not None]
    if vals and value_range is None:
        value_range = (0.0, float(np.percentile(np.concatenate(vals), 99)) or 1.0)
    cmap = plt.get_cmap("inferno")
    view = _view_direction(elev, azim)
    light = _LIGHT / np.linalg.norm(_LIGHT)

    fig = plt.figure(figsize=(panel_size * len(meshes), panel_size + 0.3))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0)
    for i, ((v, f), title, fv) in enumerate(zip(meshes, titles, face_values, strict=True)):
        v = np.asarray(v, np.float64)
        f = np.asarray(f, np.int64)
        if f.shape[0] > max_faces:
            raise ValueError(f"mesh {i} has {f.shape[0]} faces; render supports ≤ {max_faces}")
        v = canonical_frame(v).apply(v)
        n = _face_normals_np(v, f)
        # Two-sided Lambert shading, so inconsistent winding still renders.
        shade = 0.25 + 0.75 * np.abs(n @ light)
        if fv is None:
            colors = np.repeat(shade[:, None], 3, axis=1) * np.array([0.75, 0.78, 0.85])
            colors = np.concatenate([colors, np.ones((len(f), 1))], axis=1)
        else:
            lo, hi = value_range
            t = np.clip((np.asarray(fv) - lo) / max(hi - lo, 1e-12), 0, 1)
            colors = cmap(t)
            colors[:, :3] *= (0.55 + 0.45 * shade)[:, None]
        # Painter's algorithm: draw far faces first.
        depth = v[f].mean(axis=1) @ view
        order = np.argsort(depth)
        ax = fig.add_subplot(1, len(meshes), i + 1, projection="3d")
        poly = Poly3DCollection(
            v[f[order]], facecolors=colors[order], edgecolors="none", linewidths=0
        )
        ax.add_collection3d(poly)
        ax.set_xlim(-0.5, 0.5)
        ax.set_ylim(-0.5, 0.5)
        ax.set_zlim(-0.5, 0.5)
        ax.set_box_aspect((1, 1, 1), zoom=1.25)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    if vals:
        sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(*value_range))
        fig.colorbar(sm, ax=fig.axes, shrink=0.6, label=value_label)
    else:
        fig.tight_layout()

    def write(tmp):
        fig.savefig(tmp, dpi=110, format="png")

    try:
        return atomic_write(path, write, overwrite=overwrite)
    finally:
        plt.close(fig)
