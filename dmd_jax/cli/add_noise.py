"""`dmd-jax add-noise`: synthetic noise on a mesh file."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import (
    MAX_NOISE_LEVEL,
    MESH_SUFFIXES,
    _check_output,
    _load_input,
    _make_parent,
    check_range,
)
from dmd_jax.constants import NOISE_KINDS


def _cmd_add_noise(args: argparse.Namespace) -> int:
    import numpy as np

    from dmd_jax.api import add_noise
    from dmd_jax.io import save_mesh

    if not -(2**63) <= args.seed < 2**63:  # jax.random.PRNGKey takes a 64-bit signed seed
        raise ValueError(f"--seed must lie in [-2**63, 2**63), got {args.seed}")
    check_range("--level", args.level, 0, MAX_NOISE_LEVEL)
    _check_output(
        args.output, args.input, args.overwrite, parents=args.parents, suffixes=MESH_SUFFIXES
    )
    vertices, faces = _load_input(args.input)
    # The same noise as dmd_jax.add_noise(seed, ...) in Python, whatever JAX's x64 mode.
    noisy = add_noise(
        args.seed,
        vertices,
        faces,
        args.kind,
        args.level,
        units=args.units,
        direction=args.direction,
    )
    if not np.isfinite(noisy).all():
        # Not the output file's fault: the noise itself left float64's range.
        raise ValueError(
            f"--level {args.level:g} ({args.units} units) moves {args.input}'s vertices "
            "beyond float64's range; give a smaller level"
        )
    if args.parents:
        _make_parent(args.output)
    save_mesh(args.output, noisy, faces, overwrite=args.overwrite, protect=[args.input])
    print(
        f"added {args.kind} noise, level {args.level} ({args.units} units, seed {args.seed}) "
        f"-> {args.output}"
    )
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser("add-noise", help="add synthetic noise to a mesh file")
    p.add_argument("input", help="clean mesh (.obj .off .ply .stl)")
    p.add_argument("-o", "--output", required=True, help="where to write the noisy mesh")
    p.add_argument(
        "--kind",
        default="gaussian",
        choices=NOISE_KINDS,
        help="noise distribution per coordinate, or scanner: depth-sensor noise along a "
        "view drawn from --seed (dmd_jax.noise explains each)",
    )
    p.add_argument(
        "--level",
        type=float,
        required=True,
        help="noise level in --units: σ for gaussian, the amplitude for the other kinds",
    )
    p.add_argument(
        "--units",
        default="canonical",
        choices=["canonical", "edge"],
        help="canonical: fraction of the longest bbox side; edge: × mean edge length",
    )
    p.add_argument(
        "--direction",
        choices=("isotropic", "normal"),
        default="isotropic",
        help="isotropic: per coordinate; normal: one draw per vertex along its normal "
        "(the benchmark protocol)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed; same seed, same noise")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--parents", action="store_true", help="create -o's missing folders")
    p.set_defaults(func=_cmd_add_noise)
