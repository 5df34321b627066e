"""`dmd-jax warmup`: compile the network for every mesh size once, into the on-disk cache."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import check_range, check_weights_path

# The largest face count a warm-up covers (the rung of a 2^25-face mesh).
MAX_FACES = 2**25


def _cmd_warmup(args: argparse.Namespace) -> int:
    import time

    from dmd_jax import compile_cache
    from dmd_jax.shape_ladder import LAYOUTS, STANDARD_WIDTHS
    from dmd_jax.warmup import warm_up

    check_weights_path("--weights", args.weights)
    check_range("--min-faces", args.min_faces, 1, MAX_FACES)
    check_range("--max-faces", args.max_faces, 1, MAX_FACES)
    check_range("--jobs", args.jobs, 1, 64)
    if args.min_faces > args.max_faces:
        raise ValueError(
            f"--min-faces ({args.min_faces}) must not exceed --max-faces ({args.max_faces})"
        )
    where = compile_cache.settings().path
    bundle = None
    if args.weights is not None:
        from dmd_jax.checkpoints import load_model

        bundle = load_model(args.weights)
    layouts = LAYOUTS if args.all_layouts else (STANDARD_WIDTHS,)

    def report(w) -> None:
        if not args.quiet:
            what = "compiled" if w.compiled else "ready"
            print(
                f"  {w.rung:>9,d} padded vertices (up to {2 * w.rung:,d} faces), tables "
                f"{_widths(w.widths)}, {w.update} update: {what} in {w.seconds:.1f} s",
                flush=True,
            )

    start = time.perf_counter()
    done = warm_up(
        bundle,
        min_faces=args.min_faces,
        max_faces=args.max_faces,
        layouts=layouts,
        jobs=args.jobs,
        report=report,
    )
    compiled = sum(w.compiled for w in done)
    print(
        f"{len(done)} programs for meshes of {args.min_faces:,d} to {args.max_faces:,d} "
        f"faces: {compiled} compiled, {len(done) - compiled} already cached, in "
        f"{time.perf_counter() - start:.0f} s; cache {where}"
    )
    return 0


def _widths(widths) -> str:
    return "/".join("edge lists" if w is None else str(w) for w in widths)


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    from dmd_jax.warmup import DEFAULT_MAX_FACES, DEFAULT_MIN_FACES

    p = sub.add_parser(
        "warmup",
        help="compile the network for every mesh size once (then any mesh loads its program)",
        description=(
            "Compiles the whole-mesh network program of every rung of the shape ladder "
            "(dmd_jax.shape_ladder) from --min-faces to --max-faces into the on-disk "
            "compilation cache, so that a later dmd-jax denoise on a mesh of any size in "
            "the range loads its program instead of compiling it. Run it once per "
            "version of dmd_jax and weights file (--weights); programs already cached "
            "are loaded, not compiled again. Meshes too large for the memory budget run "
            "in patches, whose programs are compiled on first use."
        ),
    )
    p.add_argument(
        "--weights", help="weights file or checkpoint directory (default: bundled model)"
    )
    p.add_argument("--min-faces", type=int, default=DEFAULT_MIN_FACES, help="smallest mesh")
    p.add_argument("--max-faces", type=int, default=DEFAULT_MAX_FACES, help="largest mesh")
    p.add_argument(
        "--all-layouts",
        action="store_true",
        help="also the programs of meshes with a vertex of valence above 15",
    )
    p.add_argument("--jobs", type=int, default=2, help="programs compiled at once")
    p.add_argument("--quiet", action="store_true", help="only the summary line")
    p.set_defaults(func=_cmd_warmup)
