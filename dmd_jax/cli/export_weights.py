"""`dmd-jax export-weights`: a checkpoint directory (or weights file) to one weights file."""

from __future__ import annotations

import argparse

from dmd_jax.cli._common import _check_output, check_local_path, check_range


def _cmd_export_weights(args: argparse.Namespace) -> int:
    import platform
    from pathlib import Path

    from dmd_jax.checkpoints import load_params, load_weights, save_weights
    from dmd_jax.policy import MAX_PASSES_LIMIT, MAX_RELAX_STEPS, trained_policy

    # Everything the flags can get wrong, before any file is read.
    meta_edits = _meta(args.meta)
    check_range("--max-passes", args.max_passes, 1, MAX_PASSES_LIMIT)
    check_range("--relax-steps", args.relax_steps, 0, MAX_RELAX_STEPS)
    check_local_path("checkpoint", args.checkpoint)
    check_local_path("--policy-from", args.policy_from)
    check_local_path("--controller", args.controller)
    inputs = [args.checkpoint] + [p for p in (args.policy_from, args.controller) if p]
    # The output is never one of the inputs, --overwrite or not.
    _check_output(args.output, inputs, args.overwrite)
    source = Path(args.checkpoint)
    if source.is_file():
        # A weights file: the same params with a newly fitted inference policy.
        bundle = load_weights(source)
        params, cfg, meta = bundle.params, bundle.config, dict(bundle.meta)
        policy, controller = bundle.policy, bundle.controller
        step = meta.get("step")
        meta["exported_from"] = str(args.checkpoint)
    else:
        params, cfg = load_params(source)
        policy, controller = trained_policy(cfg), None
        step = _latest_step(source)
        meta = {"source": str(args.checkpoint), "platform": platform.platform()}
        if step is not None:
            meta["step"] = step
    if args.policy_from is not None:
        # A fine-tune keeps the rules fitted for the weights it started from; the
        # edits below still apply on top of them. Not the donor's controller: it was
        # trained on searches of the donor's network (`--controller` adds one).
        donor = load_weights(args.policy_from)
        policy, controller = donor.policy.replace(controller=False), None
        meta["policy_from"] = str(args.policy_from)
    policy = _edited_policy(policy, args)
    if args.controller is not None:
        controller = _read_controller(args.controller)
        meta["controller_from"] = str(args.controller)
    if args.controller_default is not None:
        if controller is None:
            raise ValueError("--controller-default needs weights with a controller (--controller)")
        policy = policy.replace(controller=args.controller_default == "on")
    meta.update(meta_edits)
    path = save_weights(
        args.output,
        params,
        cfg,
        meta,
        policy=policy,
        controller=controller,
        overwrite=args.overwrite,
    )
    print(
        f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB): "
        + (f"step {step}" if step is not None else "the newest step")
        + f" of {args.checkpoint}, preset {cfg.name}"
    )
    return 0


def _meta(text: str | None) -> dict:
    """`--meta`: a JSON object of finite values, or a one-line error naming the flag."""
    import json

    if not text:
        return {}

    def refuse_constant(name):
        raise ValueError(f"--meta: {name} is not JSON (store a string or null instead)")

    try:
        value = json.loads(text, parse_constant=refuse_constant)
    except RecursionError:
        raise ValueError("--meta: the JSON is nested too deeply") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"--meta is not valid JSON ({exc})") from None
    if not isinstance(value, dict):
        raise ValueError(
            f'--meta must be a JSON object such as \'{{"note": "..."}}\', got a '
            f"{type(value).__name__}"
        )
    return value


def _edited_policy(policy, args: argparse.Namespace):
    """`policy` with export-weights' --pass-tolerance, --max-passes, --presmooth and
    --relax-steps applied (a tolerance on a one-pass policy without --max-passes gets
    `policy.LEGACY_AUTO_MAX_PASSES`, the cap such weights always had)."""
    from dmd_jax.policy import LEGACY_AUTO_MAX_PASSES

    edits = {}
    if args.pass_tolerance is not None:
        edits["pass_tolerance"] = args.pass_tolerance
        if args.pass_tolerance > 0 and policy.max_passes == 1:
            edits["max_passes"] = LEGACY_AUTO_MAX_PASSES
    if args.max_passes is not None:
        edits["max_passes"] = args.max_passes
    if args.presmooth is not None:
        edits["presmooth_start"], edits["presmooth_per_step"] = args.presmooth
    if args.relax_steps is not None:
        edits["relax_steps"] = args.relax_steps
    return policy.with_edits(edits)


def _read_controller(path):
    """The `ControllerParams` of a `.npz` written by `scripts/train_controller.py`.

    Raises:
      ValueError: not such a file.
    """
    import numpy as np

    from dmd_jax.controller import ControllerParams

    try:
        with np.load(path, allow_pickle=False) as z:
            fields = {k: z[k] for k in z.files}
    except (OSError, ValueError) as err:
        raise ValueError(f"--controller {path}: not a controller file ({err})") from None
    if "options" in fields:
        fields["options"] = fields["options"].tolist()
    return ControllerParams.from_dict(fields)


def _latest_step(checkpoint_dir) -> int | None:
    """The step `load_params` reads: the newest checkpoint of an Orbax manager directory."""
    from pathlib import Path

    import orbax.checkpoint as ocp

    return ocp.CheckpointManager(Path(checkpoint_dir).absolute()).latest_step()


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser("export-weights", help="checkpoint directory -> one weights file")
    p.add_argument(
        "checkpoint",
        help="an Orbax checkpoint directory (e.g. RUN/checkpoints/best), or a weights file "
        "to rewrite with a new --pass-tolerance / --presmooth",
    )
    p.add_argument("-o", "--output", required=True, help="weights file to write (.msgpack)")
    p.add_argument("--meta", default=None, help="JSON object of provenance to store")
    p.add_argument(
        "--pass-tolerance",
        type=float,
        default=None,
        help="store this pass tolerance in the weights' policy: passes repeat while the last "
        "moved the mesh by more than it, in mean edges (0: every one of --max-passes)",
    )
    p.add_argument(
        "--max-passes",
        type=int,
        default=None,
        help="store this most network passes in the weights' policy",
    )
    p.add_argument(
        "--relax-steps",
        type=int,
        default=None,
        help="store this many tangential relaxation steps in the weights' policy",
    )
    p.add_argument(
        "--presmooth",
        type=float,
        nargs=2,
        default=None,
        metavar=("START", "PER_STEP"),
        help="store this pre-smoothing rule in the weights' policy (degrees of roughness: "
        "round((roughness - START) / PER_STEP) steps; START 0 turns it off)",
    )
    p.add_argument(
        "--policy-from",
        default=None,
        metavar="WEIGHTS",
        help="take the inference policy (pass and pre-smoothing rules) from this weights "
        "file instead of the checkpoint's trained policy, e.g. the weights a fine-tune "
        "started from; the options above still edit it. Not its smoothing controller "
        "(trained for its network): --controller adds one",
    )
    p.add_argument(
        "--controller",
        default=None,
        metavar="NPZ",
        help="store this learned smoothing controller (scripts/train_controller.py --out) "
        "beside the network; denoise then lets it choose pre-smoothing, passes and update",
    )
    p.add_argument(
        "--controller-default",
        choices=("on", "off"),
        default=None,
        help="on: denoise lets the stored controller choose unless the caller fixes the "
        "passes or pre-smoothing (the policy's 'controller'); off: only when asked "
        "(denoise(controller=True), dmd-jax denoise --controller)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_export_weights)
