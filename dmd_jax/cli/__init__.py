"""The `dmd-jax` command line.

One module per subcommand, its parser (`add_parser`) next to its handler (`_cmd_*`);
`_common` holds what several share (reading an input, checking an output). `main` turns
any `ValueError` or `OSError` (missing file, existing output, a directory or unwritable
path) into a one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import os
import sys

from dmd_jax.cli import (
    add_noise,
    demo,
    denoise,
    evaluate,
    export_weights,
    info,
    make_dataset,
    render,
    train,
    train_cnr,
    warmup,
)
from dmd_jax.cli._common import MESH_SUFFIXES, METHODS, WEIGHTED_METHODS, _HelpFormatter

# Re-exported: tests build a training config from parsed flags as `train` does.
from dmd_jax.cli.train import _parse_edits as _parse_edits
from dmd_jax.cli.train import _train_config as _train_config

__all__ = ["EXAMPLES", "METHODS", "MESH_SUFFIXES", "WEIGHTED_METHODS", "build_parser", "main"]

# The subcommands in the order `dmd-jax --help` lists them; a new one adds its module here.
_SUBCOMMANDS = (
    info,
    denoise,
    add_noise,
    evaluate,
    render,
    make_dataset,
    train,
    export_weights,
    demo,
    train_cnr,
    warmup,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmd-jax", description="DMD-Net mesh denoising in JAX (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    for command in _SUBCOMMANDS:
        command.add_parser(sub)

    # Every subcommand's help shows the defaults and an example (dmd-jax CMD --help).
    parser.formatter_class = _HelpFormatter
    parser.epilog = "examples: dmd-jax demo --out out/demo; dmd-jax COMMAND --help"
    for name, p in sub.choices.items():
        p.formatter_class = _HelpFormatter
        p.epilog = "example:\n  " + "\n  ".join(EXAMPLES[name])
    return parser


# One or two example command lines per subcommand, shown by `dmd-jax CMD --help`.
EXAMPLES = {
    "info": ["dmd-jax info --preset small"],
    "denoise": [
        "dmd-jax denoise scan.ply -o scan_dmd.ply",
        "dmd-jax denoise scan.ply -o scan_bnf.ply --method bnf",
        "dmd-jax denoise scans/ --out scans_dmd/ --max-memory 8GB",
    ],
    "add-noise": ["dmd-jax add-noise part.obj -o part_noisy.obj --level 0.2 --units edge"],
    "evaluate": ["dmd-jax evaluate --gt part.obj --mesh part_noisy.obj part_dmd.obj"],
    "render": [
        "dmd-jax render part_noisy.obj part_dmd.obj --gt part.obj -o cmp.png",
        "dmd-jax render part_noisy.obj part_dmd.obj --gt part.obj -o cmp.html",
    ],
    "make-dataset": [
        "dmd-jax make-dataset --out data/procedural --per-category 40",
        "dmd-jax make-dataset --out data/tiny --per-category 2   # 38 meshes, ~16 s",
    ],
    "train": [
        "dmd-jax train --data data/procedural --workdir runs/small --preset small",
        "dmd-jax train --data data/tiny --workdir runs/tiny --preset test   # a first run",
    ],
    "export-weights": ["dmd-jax export-weights runs/small/checkpoints/best -o mine.msgpack"],
    "demo": ["dmd-jax demo --out out/demo"],
    "train-cnr": ["dmd-jax train-cnr --data data/procedural --out cnr.msgpack"],
    "warmup": [
        "dmd-jax warmup   # every mesh size from 1k to 1M faces, once per version",
        "dmd-jax warmup --max-faces 2000000 --all-layouts",
    ],
}


class _Terminated(KeyboardInterrupt):
    """SIGTERM (`timeout`, schedulers, `docker stop`), raised like Ctrl-C so that every
    cleanup runs: an atomic write removes its temporary file."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def console() -> None:
    """The `dmd-jax` script and `python -m dmd_jax.cli`: `main`, then exit at once.

    Everything a command writes is closed by the time `main` returns (files are
    renamed into place whole), so the interpreter's teardown of JAX's runtime, a
    tenth of a second to half a second of a cold `dmd-jax denoise` on 2 cores
    (docs/cold-start.md), is skipped with `os._exit` once the standard streams are
    flushed; a process with another live non-daemon thread exits normally.
    """
    import threading

    code = main()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except OSError:  # a closed pipe: the output went nowhere
        code = code or 1
    if any(t is not threading.main_thread() and not t.daemon for t in threading.enumerate()):
        sys.exit(code)
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    parser = build_parser()
    args = parser.parse_args(argv)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _run(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as exc:
        # One line whatever the message holds (some library errors span several lines).
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"dmd-jax {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, _Terminated)
        what = "terminated" if terminated else "interrupted"
        print(f"dmd-jax {args.command}: {what}{getattr(exc, 'hint', '')}", file=sys.stderr)
        return 143 if terminated else 130
