"""`dmd-jax train-cnr`: the CNR baseline (dmd_jax.baselines.cascaded_regression)."""

from __future__ import annotations

import argparse
import sys


def _cmd_train_cnr(args: argparse.Namespace) -> int:
    import os
    import shlex

    from dmd_jax.baselines.cascaded_regression import train_main
    from dmd_jax.cli._common import MAX_CNR, MAX_CNR_HIDDEN, check_range

    # Every count bounded before any work (docs/refusals.md).
    for flag, most in MAX_CNR.items():
        low = 0 if flag in ("--vertex-iterations", "--eval-meshes") else 1
        check_range(flag, getattr(args, flag[2:].replace("-", "_")), low, most)
    check_range("--hidden (layers)", len(args.hidden), 1, MAX_CNR_HIDDEN[0])
    for width in args.hidden:
        check_range("--hidden", width, 1, MAX_CNR_HIDDEN[1])
    check_range("--lr", args.lr, 1e-12, 10.0)
    out, data = os.path.realpath(args.out), os.path.realpath(args.data)
    if out == data or out.startswith(data + os.sep):
        # Its meshes are the inputs: the weights never go in among them.
        raise ValueError(f"--out {args.out}: lies inside --data {args.data}; write it elsewhere")
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
