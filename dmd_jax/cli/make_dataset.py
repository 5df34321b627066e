"""`dmd-jax make-dataset`: procedural training meshes, or a converted mesh folder."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import (
    MAX_PER_CATEGORY,
    MAX_VERTICES,
    MAX_WORKERS,
    MIN_VERTICES,
    check_range,
    output_lock,
)


def _check_args(args: argparse.Namespace) -> None:
    """The counts' bounds, and an --out that is not the --from-folder, before any work."""
    import os

    check_range("--per-category", args.per_category, 1, MAX_PER_CATEGORY)
    check_range("--workers", args.workers, 1, MAX_WORKERS)
    check_range("--min-vertices", args.min_vertices, MIN_VERTICES, MAX_VERTICES)
    check_range("--max-vertices", args.max_vertices, MIN_VERTICES, MAX_VERTICES)
    check_range("--intra-fraction", args.intra_fraction, 0, 1)
    if args.from_folder is not None:
        out, src = os.path.realpath(args.out), os.path.realpath(args.from_folder)
        # --overwrite empties --out: never the input folder, nor one holding or inside it.
        if out == src or src.startswith(out + os.sep) or out.startswith(src + os.sep):
            raise ValueError(
                f"--out {args.out}: is, holds or lies inside the input folder --from-folder "
                f"{args.from_folder}; write the dataset elsewhere"
            )


def _cmd_make_dataset(args: argparse.Namespace) -> int:
    import contextlib
    import os
    import time

    from dmd_jax.data.dataset import build_dataset

    _check_args(args)

    def names(text):
        # None: the option was not given; "" gives (): e.g. --test-inter "" holds out nothing.
        return None if text is None else tuple(x.strip() for x in text.split(",") if x.strip())

    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if os.path.isdir(args.out):  # two runs filling one folder at once: refused
            stack.enter_context(output_lock(args.out))
        ds = build_dataset(
            args.out,
            from_folder=args.from_folder,
            per_category=args.per_category,
            categories=names(args.categories),
            test_inter=names(args.test_inter),
            remesh=args.remesh,
            seed=args.seed,
            intra_fraction=args.intra_fraction,
            workers=args.workers,
            min_vertices=args.min_vertices,
            max_vertices=args.max_vertices,
            progress=not args.no_progress,
            overwrite=args.overwrite,
        )
    counts = ds.counts()
    skipped = len(ds.manifest.get("skipped", []))
    print(
        f"wrote {len(ds)} meshes to {args.out} in {time.perf_counter() - start:.1f} s: "
        f"train {counts['train']}, test_intra {counts['test_intra']}, "
        f"test_inter {counts['test_inter']} ({', '.join(ds.test_inter_categories) or 'none'})"
        + (f"; {skipped} skipped (see manifest.json)" if skipped else "")
    )
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser(
        "make-dataset", help="generate procedural training meshes, or convert a mesh folder"
    )
    p.add_argument("--out", required=True, help="output directory (must be empty)")
    p.add_argument("--per-category", type=int, default=None, help="shapes per category")
    p.add_argument("--seed", type=int, default=0, help="shape and split seed")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--min-vertices", type=int, default=1000, help="smallest vertex count")
    p.add_argument("--max-vertices", type=int, default=6000, help="largest vertex count")
    p.add_argument(
        "--test-inter",
        default=None,
        help='comma-separated categories held out whole; "" holds out none (default: '
        "fastener,bottle,metaballs for procedural data, none for folders)",
    )
    p.add_argument("--categories", default=None, help="comma-separated subset of categories")
    p.add_argument("--intra-fraction", type=float, default=0.2, help="test-intra share")
    p.add_argument(
        "--from-folder", default=None, help="convert a category/*.obj|off|ply folder instead"
    )
    p.add_argument("--remesh", action="store_true", help="remesh folder meshes into the range")
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_make_dataset)
