"""`dmd-jax evaluate`: vertex, normal and chamfer errors against a ground truth."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import _in_gt_order, _load_input


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json
    import math
    import sys
    import time

    from dmd_jax.metrics import mesh_metrics, metrics_table

    gt_v, gt_f = _load_input(args.gt)
    rows = []
    for i, path in enumerate(args.mesh):
        start = time.perf_counter()
        v, f = _load_input(path)
        v = _in_gt_order(v, f, gt_v, gt_f, path, args.gt)
        m = mesh_metrics(v, gt_v, gt_f)
        if math.isnan(m["normal_deg"]):
            raise ValueError(
                f"{args.gt}: no face of the ground truth has a non-zero area, so the normal "
                "error is undefined (a degenerate mesh cannot be a ground truth)"
            )
        bad = [k for k, x in m.items() if not math.isfinite(x)]
        if bad:
            raise ValueError(
                f"{path}: its {bad[0]} error overflows float64 (the mesh lies astronomically "
                f"far from {args.gt}: another unit or a corrupt file?)"
            )
        rows.append({"mesh": str(path), **{k: float(x) for k, x in m.items()}})
        if len(args.mesh) > 1 and not args.quiet:
            # Progress for a long list; stderr, so stdout stays the table or the JSON.
            took = time.perf_counter() - start
            print(f"[{i + 1}/{len(args.mesh)}] {path}: {took:.2f} s", file=sys.stderr)
    if args.json:
        # allow_nan=False: never the non-JSON `Infinity`/`NaN` (refused above).
        print(json.dumps(rows, indent=2, allow_nan=False))
    else:
        print(metrics_table({r["mesh"]: r for r in rows}, style="text"), end="")
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser("evaluate", help="vertex / normal / chamfer metrics against a ground truth")
    p.add_argument(
        "--gt",
        required=True,
        help="ground-truth mesh: the same vertices as each --mesh, in the same order (a "
        "mesh whose faces match but whose vertices were renumbered, e.g. an STL output, is "
        "matched through its faces)",
    )
    p.add_argument("--mesh", required=True, nargs="+", help="meshes to score")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no progress line per mesh on stderr (printed when there are several meshes)",
    )
    p.set_defaults(func=_cmd_evaluate)
