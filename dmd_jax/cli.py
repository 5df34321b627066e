"""The `dmd-jax` command line.

Each subcommand lives in its own `_cmd_*` function; `main` turns any `ValueError`,
`FileNotFoundError` or `FileExistsError` into a one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import sys


def _cmd_info(args: argparse.Namespace) -> int:
    import jax

    import dmd_jax

    print(f"dmd_jax {dmd_jax.__version__}, jax {jax.__version__}, devices {jax.devices()}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmd-jax", description="DMD-Net mesh denoising in JAX (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="versions, devices, presets and parameter counts")
    p.set_defaults(func=_cmd_info)

    # Further subcommands are registered below, one block each.
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"dmd-jax {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dmd-jax {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
