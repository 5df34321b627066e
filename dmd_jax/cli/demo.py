"""`dmd-jax demo`: denoise a generated noisy CAD part; metrics, meshes and a PNG."""

from __future__ import annotations

import argparse


def _cmd_demo(args: argparse.Namespace) -> int:
    import contextlib
    import os

    from dmd_jax.cli._common import check_weights_path, output_lock
    from dmd_jax.demo import check_demo_outputs, run_demo

    check_weights_path("--weights", args.weights)
    check_demo_outputs(args.out, args.weights, args.overwrite, render=not args.no_render)
    with contextlib.ExitStack() as stack:
        if os.path.isdir(args.out):  # two runs writing one folder at once: refused
            stack.enter_context(output_lock(args.out))
        run_demo(
            args.out, weights=args.weights, overwrite=args.overwrite, render=not args.no_render
        )
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser(
        "demo", help="denoise a generated noisy CAD part; print metrics, write meshes and a PNG"
    )
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument(
        "--weights",
        default=None,
        help="weights file or checkpoint directory (default: bundled model)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--no-render", action="store_true", help="skip before_after.png")
    p.set_defaults(func=_cmd_demo)
