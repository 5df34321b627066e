"""`dmd-jax info`: versions, devices, presets and parameter counts."""

from __future__ import annotations

import argparse


def _cmd_info(args: argparse.Namespace) -> int:
    import jax

    import dmd_jax
    from dmd_jax.cli._common import check_weights_path

    if getattr(args, "weights", None) not in (None, "bundled"):
        check_weights_path("--weights", args.weights)

    print(f"dmd_jax {dmd_jax.__version__}, jax {jax.__version__}, devices {jax.devices()}")
    if getattr(args, "preset", None) is not None:
        from dmd_jax.config import preset, variant_config
        from dmd_jax.model import param_count, param_counts_by_module

        model = preset(args.preset).model
        if args.variant is not None:
            model = variant_config(model, args.variant)
        print(
            f"preset {args.preset}, variant {model.variant}, width {model.width}, "
            f"depth {model.depth}"
        )
        for name, count in param_counts_by_module(model).items():
            print(f"  {name:<18} {count:>12,d} parameters")
        print(f"  {'total':<18} {param_count(model):>12,d} parameters")
        if args.preset == "paper":
            print("  (the paper says about 30 M; dmd_jax.config explains the difference)")
    elif getattr(args, "variant", None) is not None:
        raise ValueError("--variant needs --preset")
    if getattr(args, "weights", None) is not None:
        from dmd_jax.checkpoints import load_model
        from dmd_jax.model import param_count

        bundle = load_model(None if args.weights == "bundled" else args.weights)
        model = bundle.config.model
        print(
            f"weights {args.weights}: preset {bundle.config.name}, width {model.width}, "
            f"{param_count(model):,d} parameters, encoding {model.encoding}, head {model.head}"
        )
        print("  policy: " + bundle.policy.describe())
    return 0


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser("info", help="versions, devices, presets and parameter counts")
    p.add_argument(
        "--preset",
        choices=("paper", "small", "test"),
        help="print the parameter count of a preset's model",
    )
    p.add_argument("--variant", help="structure-ablation variant, e.g. FGT-3 or fgt3")
    p.add_argument(
        "--weights",
        default=None,
        help="also describe these weights (a file, a checkpoint directory, or 'bundled'): "
        "the network and the denoising policy stored with it",
    )
    p.set_defaults(func=_cmd_info)
