"""`dmd-jax train-cnr`: the CNR baseline (dmd_jax.baselines.cascaded_regression)."""

from __future__ import annotations

import argparse
import sys


def _cmd_train_cnr(args: argparse.Namespace) -> int:
    import shlex

    from dmd_jax.baselines.cascaded_regression import train_main

    train_main(args, "dmd-jax " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser(
        "train-cnr", help="train the CNR baseline (dmd_jax.baselines.cascaded_regression)"
    )
    p.add_argument("--data", required=True, help="dataset directory (make-dataset output)")
    p.add_argument("--out", required=True, help="weights file to write (.msgpack)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--max-meshes", type=int, default=None, help="first N train meshes only")
    p.add_argument("--draws", type=int, default=1, help="noisy copies per mesh")
    p.add_argument("--faces-per-mesh", type=int, default=512, help="faces sampled per copy")
    p.add_argument("--steps", type=int, default=2000, help="Adam steps per stage")
    p.add_argument("--batch-size", type=int, default=1024, help="faces per Adam step")
    p.add_argument("--lr", type=float, default=2e-3, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="noise and sampling seed")
    p.add_argument("--stages", type=int, default=2, help="cascade length")
    p.add_argument(
        "--hidden", type=int, nargs="+", default=[128, 128, 64], help="MLP hidden widths"
    )
    p.add_argument(
        "--vertex-iterations", type=int, default=20, help="vertex update passes per stage"
    )
    p.add_argument("--eval-meshes", type=int, default=8, help="test-intra meshes checked")
    p.set_defaults(func=_cmd_train_cnr)
