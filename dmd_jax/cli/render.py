"""`dmd-jax render`: meshes side by side, a PNG picture or an interactive HTML page."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import (
    MAX_PANELS,
    _check_output,
    _in_gt_order,
    _load_input,
    _make_parent,
    check_range,
)

# The camera of `--elev`/`--azim` alone, and of `--view auto` on a closed mesh.
_DEFAULT_ELEV, _DEFAULT_AZIM = 20.0, -60.0


def _triple(flag: str, text: str):
    """`x,y,z` of `--view` / `--zoom-at` as a float64 `[3]` array, or a one-line error
    naming the option."""
    from dmd_jax.render import check_direction

    parts = str(text).split(",")
    try:
        numbers = [float(x) for x in parts]
    except ValueError:
        numbers = None
    try:
        if numbers is None:
            raise ValueError
        return check_direction(flag, numbers)
    except ValueError:
        raise ValueError(
            f"{flag} must be three finite numbers x,y,z (e.g. 0,0,-1), got {text!r}"
        ) from None


def _cmd_render(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from dmd_jax.render import auto_view, render_meshes, resolve_up, view_angles

    kind = Path(args.output).suffix.lower()
    if kind not in (".png", ".html"):
        raise ValueError(f"{args.output}: write a .png (static picture) or .html (3-D page)")
    if args.range is not None and not args.range[0] < args.range[1]:
        raise ValueError(f"--range needs LOW < HIGH, got {args.range[0]:g} {args.range[1]:g}")
    if args.range is not None:
        # Degrees of normal error: 0 to 180, both ends finite.
        check_range("--range", args.range[0], -180, 180)
        check_range("--range", args.range[1], -180, 180)
    from dmd_jax.render import MAX_PANEL_SIZE, MAX_VIEW_DEGREES, MIN_PANEL_SIZE

    check_range("--elev", args.elev, -MAX_VIEW_DEGREES, MAX_VIEW_DEGREES)
    check_range("--azim", args.azim, -MAX_VIEW_DEGREES, MAX_VIEW_DEGREES)
    check_range("number of panels", len(args.inputs) + bool(args.gt), 1, MAX_PANELS)

    if not MIN_PANEL_SIZE <= args.panel_size <= MAX_PANEL_SIZE:  # NaN fails too
        # Below half an inch a panel has too few pixels to show a mesh (under a pixel,
        # none at all: matplotlib cannot write the empty image).
        raise ValueError(
            f"--panel-size must be in [{MIN_PANEL_SIZE:g}, {MAX_PANEL_SIZE:g}] inches, "
            f"got {args.panel_size:g}"
        )
    angles_given = args.elev is not None or args.azim is not None
    view = "auto" if args.view is None and not angles_given else args.view
    if view is not None and view != "auto":
        view = _triple("--view", view)
        if not np.linalg.norm(view) > 0:
            raise ValueError(f"--view must not be zero, got {args.view!r}")
    if view is not None and angles_given:
        raise ValueError("give --view or --elev/--azim, not both")
    zoom_at = None if args.zoom_at is None else _triple("--zoom-at", args.zoom_at)
    zoom = "none" if args.no_zoom else args.zoom
    if zoom_at is not None and zoom != "sharpest":  # sharpest: the default, overridden
        raise ValueError("give --zoom-at or --zoom auto/none/--no-zoom, not both")
    if kind == ".html" and zoom_at is not None:
        raise ValueError("--zoom-at draws a zoom row of a .png; an .html page has none")
    _check_output(
        args.output,
        args.inputs + ([args.gt] if args.gt else []),
        args.overwrite,
        parents=args.parents,
    )
    meshes = [_load_input(p) for p in args.inputs]
    if zoom_at is not None:
        from dmd_jax.render import check_zoom_point

        check_zoom_point(zoom_at, meshes, "--zoom-at")
    if args.parents:
        _make_parent(args.output)
    titles = args.titles.split(",") if args.titles else [Path(p).stem for p in args.inputs]
    values = None
    if args.gt:
        from dmd_jax.metrics import face_normal_errors_deg

        gt_v, gt_f = _load_input(args.gt)
        values = []
        for i, (path, (v, f)) in enumerate(zip(args.inputs, meshes, strict=True)):
            # evaluate's correspondence: renumbered vertices (an STL) matched, else refused.
            v = _in_gt_order(v, f, gt_v, gt_f, path, args.gt)
            meshes[i] = (v, gt_f)
            values.append(face_normal_errors_deg(v, gt_v, gt_f))
        # The clean mesh is the last panel, with no error of its own.
        meshes.append((gt_v, gt_f))
        values.append(None)
        stem = Path(args.gt).stem
        if len(titles) == len(args.inputs):
            titles.append(stem if stem == "clean" else f"{stem} (clean)")
    if len(titles) != len(meshes):
        raise ValueError(f"--titles gives {len(titles)} titles for {len(meshes)} panels")
    if args.gt:
        # Each title gets its mesh's mean normal error: `evaluate`'s normal (°) column.
        import math

        import numpy as np

        from dmd_jax.metrics import NORMAL, face_normal_errors_deg, format_metric

        for i, (v, _) in enumerate(meshes[: len(args.inputs)]):
            mean = np.nanmean(face_normal_errors_deg(v, gt_v, gt_f, undefined=math.nan))
            titles[i] += f"\n{NORMAL.name} {format_metric(NORMAL, mean)}{NORMAL.unit}"
    up = resolve_up(args.up, meshes)
    elev = _DEFAULT_ELEV if args.elev is None else args.elev
    azim = _DEFAULT_AZIM if args.azim is None else args.azim
    if isinstance(view, str):  # auto: facing a single-view scan, else the default view
        view = auto_view(meshes)
    if view is not None:
        elev, azim = view_angles(view, up)
    camera = dict(
        titles=titles,
        face_values=values,
        value_range=None if args.range is None else tuple(args.range),
        elev=elev,
        azim=azim,
        up=up,
    )
    if kind == ".html":
        from dmd_jax.viewer import comparison_html

        comparison_html(
            meshes,
            args.output,
            overwrite=args.overwrite,
            panel_px=round(130 * args.panel_size),
            **camera,
        )
    else:
        ref_f = meshes[-1][1]
        shared = all(f.shape == ref_f.shape and (f == ref_f).all() for _, f in meshes)
        # sharpest: the sharpest feature of the clean mesh (or of the last input); auto:
        # where the panels differ most. Both compare faces one to one; meshes with
        # faces of their own get no zoom row unless --zoom-at names a point.
        render_meshes(
            meshes,
            args.output,
            shaded_row=True,
            zoom=zoom if zoom != "none" and zoom_at is None and shared else None,
            zoom_at=zoom_at,
            panel_size=args.panel_size,
            overwrite=args.overwrite,
            **camera,
        )
    print(f"wrote {args.output}")
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser(
        "render", help="meshes side by side: a PNG picture or an interactive HTML page"
    )
    p.add_argument("inputs", nargs="+", help="meshes to show (.obj .off .ply .stl)")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help=".png: shaded, zoomed and error rows; .html: one self-contained 3-D page",
    )
    p.add_argument(
        "--gt",
        default=None,
        help="clean mesh: colour faces by normal error against it, shown as the last panel",
    )
    p.add_argument("--titles", default=None, help="comma-separated panel titles")
    p.add_argument(
        "--view",
        default=None,
        metavar="auto|X,Y,Z",
        help="the direction the camera looks along, in the meshes' coordinates (e.g. "
        "the view of dmd_jax.simulate_scan: the side its sensor saw), or auto: facing "
        "a single-view scan (against its mean face normal), the --elev/--azim default "
        "for a closed mesh (default: auto unless --elev or --azim is given; a vector "
        "that starts with a minus is written --view=-1,0,0)",
    )
    p.add_argument(
        "--elev", type=float, default=None, help="camera elevation, degrees (default: 20)"
    )
    p.add_argument(
        "--azim", type=float, default=None, help="camera azimuth, degrees (default: -60)"
    )
    p.add_argument(
        "--up",
        default="auto",
        choices=["auto", "y", "z"],
        help="the models' up axis; auto: z if the meshes stand on a flat base under z, "
        "else y (the convention of scans; dmd_jax.render.guess_up_axis)",
    )
    p.add_argument(
        "--panel-size",
        type=float,
        default=3.2,
        help="inches per panel, 0.5 to 20 (HTML: × 130 px)",
    )
    p.add_argument(
        "--range",
        type=float,
        nargs=2,
        metavar=("LOW", "HIGH"),
        default=None,
        help="error colour range in degrees (default: 0 to the best panel's 95th "
        "percentile, rounded up)",
    )
    p.add_argument(
        "--zoom",
        default="sharpest",
        choices=["sharpest", "auto", "none"],
        help="PNG zoom row: on the sharpest edge of the last panel, or auto: where the "
        "panels differ most (their face normals), or none",
    )
    p.add_argument(
        "--zoom-at",
        default=None,
        metavar="X,Y,Z",
        help="PNG: centre the zoom row on this point, in the meshes' coordinates",
    )
    p.add_argument("--no-zoom", action="store_true", help="PNG: no zoom row (--zoom none)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--parents", action="store_true", help="create -o's missing folders")
    p.set_defaults(func=_cmd_render)
