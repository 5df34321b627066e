"""Interactive 3-D comparison pages: one self-contained HTML file (plotly, no network).

`comparison_html` puts meshes side by side (e.g. noisy / denoised / clean), each a
plotly `Mesh3d` in its own canonical frame, faces coloured by a per-face value such as
the normal error against the clean mesh. The cameras are linked: turning or zooming one
panel turns the others the same way. plotly.js is embedded in the page
(`include_plotlyjs=True`, about 4.7 MB), so the file opens offline and can be mailed or
archived as it is. `dmd-jax render … -o cmp.html` writes one; in a notebook,
`comparison_figure(...)` returns the plotly figure to show inline.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dmd_jax.mesh import canonical_frame, face_normals_np, validate_mesh
from dmd_jax.render import (
    _AZIM,
    _ELEV,
    _GREY,
    _camera,
    _to_z_up,
    nice_range,
    resolve_up,
    saturation_note,
)

# Links the cameras of every 3-D scene of the page: a turn or zoom in one is copied to
# the others (plotly has no built-in option for this). `{plot_id}` is plotly's div id.
_LINK_CAMERAS_JS = """
var gd = document.getElementById('{plot_id}');
var syncing = false;
function linkCameras(ev) {
  if (syncing || !ev) return;
  var cam = null;
  for (var key in ev) {
    if (/^scene\\d*\\.camera$/.test(key)) cam = ev[key];
  }
  if (!cam) return;
  var update = {};
  for (var name in gd._fullLayout) {
    if (/^scene\\d*$/.test(name)) update[name + '.camera'] = cam;
  }
  syncing = true;
  Plotly.relayout(gd, update).then(function () { syncing = false; });
}
gd.on('plotly_relayout', linkCameras);
gd.on('plotly_relayouting', linkCameras);
"""


def _hex(rgb) -> str:
    r, g, b = (int(round(255 * min(max(float(x), 0.0), 1.0))) for x in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def comparison_figure(
    meshes: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    titles: Sequence[str] | None = None,
    face_values: Sequence[np.ndarray | None] | None = None,
    value_label: str = "normal error (°)",
    value_range: tuple[float, float] | None = None,
    up: str = "z",
    elev: float = _ELEV,
    azim: float = _AZIM,
    panel_px: int = 420,
    max_faces: int = 500_000,
):
    """A plotly figure of meshes side by side with linked cameras.

    Args:
      meshes: `(vertices [n, 3], faces [f, 3])` pairs.
      titles: one title per panel.
      face_values: per mesh, `[f]` values to colour faces by, or None for plain grey.
      value_label: colour-bar title.
      value_range: colour scale limits; default `render.nice_range` of the values.
      up: the model's up axis, `"z"`, `"y"` or `"auto"` (`render.resolve_up`).
      elev, azim: initial camera angles in degrees.
      panel_px: width and height of one panel in pixels.
      max_faces: refuse larger meshes (the page would be slow to open).

    Returns:
      A `plotly.graph_objects.Figure`; `comparison_html` writes it to a file with the
      camera link.
    """
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    if not meshes:
        raise ValueError("comparison_figure needs at least one mesh")
    meshes = _checked_meshes(meshes)
    n = len(meshes)
    titles = list(titles) if titles is not None else [f"mesh {i}" for i in range(n)]
    face_values = list(face_values) if face_values is not None else [None] * n
    if len(titles) != n or len(face_values) != n:
        raise ValueError("titles and face_values need one entry per mesh")
    vals = [np.asarray(x, np.float64) for x in face_values if x is not None]
    if vals and value_range is None:
        value_range = nice_range(vals)
    up = resolve_up(up, meshes)
    view, right, screen_up = _camera(elev, azim)
    eye = dict(zip("xyz", (2.0 * view).tolist(), strict=True))
    # Shading is baked into the face colours (two-sided Lambert, a light fixed in the
    # scene, as in the PNG), because plotly lights one side of a face only and real
    # meshes often have flipped or inconsistent winding.
    light = view + 0.55 * screen_up - 0.45 * right
    light /= np.linalg.norm(light)
    import matplotlib

    cmap = matplotlib.colormaps["inferno"]

    fig = make_subplots(
        rows=1,
        cols=n,
        specs=[[{"type": "scene"}] * n],
        subplot_titles=[t.replace("\n", "<br>") for t in titles],
        horizontal_spacing=0.01,
    )
    bar_shown = False
    for i, ((v, f), fv) in enumerate(zip(meshes, face_values, strict=True)):
        v = np.asarray(v, np.float64)
        f = np.asarray(f, np.int64)
        if len(f) > max_faces:
            raise ValueError(f"mesh {i} has {len(f)} faces; the viewer supports ≤ {max_faces}")
        if fv is not None and np.shape(fv) != (len(f),):
            raise ValueError(f"face_values[{i}] needs one value per face of mesh {i}")
        v = _to_z_up(canonical_frame(v).apply(v), up)
        shade = 0.22 + 0.78 * np.abs(face_normals_np(v, f) @ light)
        if fv is None:
            rgb = shade[:, None] * _GREY[None, :]
        else:
            t = (np.asarray(fv, np.float64) - value_range[0]) / (value_range[1] - value_range[0])
            rgb = cmap(np.clip(np.nan_to_num(t), 0, 1))[:, :3] * (0.6 + 0.4 * shade)[:, None]
        v = v.astype(np.float32)
        fig.add_trace(
            go.Mesh3d(
                x=v[:, 0],
                y=v[:, 1],
                z=v[:, 2],
                i=f[:, 0],
                j=f[:, 1],
                k=f[:, 2],
                facecolor=[_hex(c) for c in rgb],
                flatshading=True,
                lighting=dict(ambient=1.0, diffuse=0.0, specular=0.0, fresnel=0.0),
                name=titles[i].split("\n")[0],
                hoverinfo="name",
            ),
            row=1,
            col=i + 1,
        )
    if vals:
        note = saturation_note(value_range, vals)
        bar_label = value_label + (f"; {note}" if note else "")
        # The colour bar: an invisible 2-D marker carrying the colour scale.
        fig.add_trace(
            go.Scatter(
                x=[None],
                y=[None],
                mode="markers",
                hoverinfo="skip",
                marker=dict(
                    colorscale="Inferno",
                    cmin=value_range[0],
                    cmax=value_range[1],
                    color=[value_range[0]],
                    showscale=True,
                    colorbar=dict(
                        title=dict(text=bar_label, side="top"),
                        orientation="h",
                        x=0.5,
                        y=-0.02,
                        yanchor="top",
                        len=0.5,
                        thickness=14,
                    ),
                ),
            )
        )
        bar_shown = True
        fig.update_xaxes(visible=False)
        fig.update_yaxes(visible=False)
    hidden = dict(visible=False, showbackground=False)
    for i in range(n):
        name = "scene" if i == 0 else f"scene{i + 1}"
        fig.layout[name].update(
            xaxis=hidden,
            yaxis=hidden,
            zaxis=hidden,
            aspectmode="data",
            camera=dict(eye=eye, up=dict(x=0, y=0, z=1)),
        )
    fig.update_layout(
        width=panel_px * n,
        height=panel_px + (90 if bar_shown else 40),
        margin=dict(l=0, r=0, t=40, b=70 if bar_shown else 0),
        paper_bgcolor="white",
        plot_bgcolor="white",
        showlegend=False,
        modebar=dict(orientation="v"),  # at the right edge, clear of the panel titles
    )
    return fig


def _checked_meshes(meshes) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each `(vertices, faces)` pair checked as `denoise` checks a mesh, naming it."""
    out = []
    for i, pair in enumerate(meshes):
        if not (isinstance(pair, tuple | list) and len(pair) == 2):
            raise ValueError(f"meshes[{i}] must be a (vertices, faces) pair")
        out.append(validate_mesh(pair[0], pair[1], name=f"meshes[{i}]"))
    return out


def comparison_html(
    meshes: Sequence[tuple[np.ndarray, np.ndarray]],
    path,
    *,
    overwrite: bool = False,
    title: str = "dmd-jax comparison",
    **kwargs,
) -> Path:
    """Writes `comparison_figure(meshes, **kwargs)` as one self-contained HTML page.

    Args:
      meshes: `(vertices, faces)` pairs, e.g. noisy, denoised, clean.
      path: the `.html` file to write (atomically).
      overwrite: replace an existing file.
      title: the page title.
      **kwargs: `comparison_figure` options (titles, face_values, value_range, up, ...).

    Returns:
      The path written. The page needs no network: plotly.js is inside it.
    """
    from dmd_jax.io import atomic_write

    fig = comparison_figure(meshes, **kwargs)
    html = fig.to_html(
        include_plotlyjs=True,
        full_html=True,
        post_script=_LINK_CAMERAS_JS,
        config={"displaylogo": False, "responsive": False},
    )
    html = html.replace("<head>", f"<head><meta charset='utf-8'><title>{title}</title>", 1)
    return atomic_write(
        path, lambda tmp: Path(tmp).write_text(html, encoding="utf-8"), overwrite=overwrite
    )
