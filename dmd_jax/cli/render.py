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


def _cmd_render(args: argparse.Namespace) -> int:
    from pathlib import Path

    from dmd_jax.render import render_meshes, resolve_up, sharpest_face

    kind = Path(args.output).suffix.lower()
    if kind not in (".png", ".html"):
        raise ValueError(f"{args.output}: write a .png (static picture) or .html (3-D page)")
    if args.range is not None and not args.range[0] < args.range[1]:
        raise ValueError(f"--range needs LOW < HIGH, got {args.range[0]:g} {args.range[1]:g}")
    if args.range is not None:
        # Degrees of normal error: 0 to 180, both ends finite.
        check_range("--range", args.range[0], -180, 180)
        check_range("--range", args.range[1], -180, 180)
    from dmd_jax.render import MAX_PANEL_SIZE, MAX_VIEW_DEGREES

    check_range("--elev", args.elev, -MAX_VIEW_DEGREES, MAX_VIEW_DEGREES)
    check_range("--azim", args.azim, -MAX_VIEW_DEGREES, MAX_VIEW_DEGREES)
    check_range("number of panels", len(args.inputs) + bool(args.gt), 1, MAX_PANELS)

    if not 0 < args.panel_size <= MAX_PANEL_SIZE:  # NaN fails too
        raise ValueError(
            f"--panel-size must be in (0, {MAX_PANEL_SIZE:g}] inches, got {args.panel_size:g}"
        )
    _check_output(
        args.output,
        args.inputs + ([args.gt] if args.gt else []),
        args.overwrite,
        parents=args.parents,
    )
    meshes = [_load_input(p) for p in args.inputs]
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
    view = dict(
        titles=titles,
        face_values=values,
        value_range=None if args.range is None else tuple(args.range),
        elev=args.elev,
        azim=args.azim,
        up=resolve_up(args.up, meshes),
    )
    if kind == ".html":
        from dmd_jax.viewer import comparison_html

        comparison_html(
            meshes,
            args.output,
            overwrite=args.overwrite,
            panel_px=round(130 * args.panel_size),
            **view,
        )
    else:
        crop = None
        if not args.no_zoom:
            # Zoom on the sharpest feature of the clean mesh (or of the first input).
            ref_v, ref_f = meshes[-1]
            if all(f.shape == ref_f.shape and (f == ref_f).all() for _, f in meshes):
                crop = sharpest_face(ref_v, ref_f, elev=args.elev, azim=args.azim, up=view["up"])
        render_meshes(
            meshes,
            args.output,
            shaded_row=True,
            crop_face=crop,
            panel_size=args.panel_size,
            overwrite=args.overwrite,
            **view,
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
    p.add_argument("--elev", type=float, default=20.0, help="camera elevation, degrees")
    p.add_argument("--azim", type=float, default=-60.0, help="camera azimuth, degrees")
    p.add_argument(
        "--up",
        default="auto",
        choices=["auto", "y", "z"],
        help="the models' up axis; auto: z if the meshes stand on a flat base under z, "
        "else y (the convention of scans; dmd_jax.render.guess_up_axis)",
    )
    p.add_argument(
        "--panel-size", type=float, default=3.2, help="inches per panel (HTML: × 130 px)"
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
    p.add_argument("--no-zoom", action="store_true", help="PNG: no zoom on the sharpest edge")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--parents", action="store_true", help="create -o's missing folders")
    p.set_defaults(func=_cmd_render)
