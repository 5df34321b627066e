"""`dmd-jax train`: DMD-Net on a dataset made by make-dataset (one or several hosts)."""

from __future__ import annotations

import argparse


def _parse_edits(items: list[str]) -> dict:
    """`["train.steps=10", "loss.vertex=50"]` -> nested dict (values parsed as JSON)."""
    import json

    edits: dict = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set takes SECTION.FIELD=VALUE, got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if isinstance(value, list):
            value = tuple(value)
        node = edits
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return edits


def _distributed_args(args: argparse.Namespace) -> dict | None:
    """`jax.distributed.initialize` keywords from the multi-host flags, or None if unset.

    Raises:
      ValueError: only some of the three flags, bad values, or no --data-parallel.
    """
    flags = {
        "--coordinator": args.coordinator,
        "--num-processes": args.num_processes,
        "--process-id": args.process_id,
    }
    given = [k for k, v in flags.items() if v is not None]
    if not given:
        return None
    if len(given) != len(flags):
        missing = ", ".join(k for k in flags if k not in given)
        raise ValueError(
            f"multi-host training needs --coordinator, --num-processes and --process-id "
            f"together; missing {missing}"
        )
    host, sep, port = args.coordinator.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"--coordinator takes HOST:PORT, got {args.coordinator!r}")
    if args.num_processes < 1:
        raise ValueError(f"--num-processes must be at least 1, got {args.num_processes}")
    if not 0 <= args.process_id < args.num_processes:
        raise ValueError(
            f"--process-id must be in 0..{args.num_processes - 1}, got {args.process_id}"
        )
    if not args.data_parallel:
        raise ValueError("--coordinator, --num-processes and --process-id need --data-parallel")
    return {
        "coordinator_address": args.coordinator,
        "num_processes": args.num_processes,
        "process_id": args.process_id,
    }


def _train_config(args: argparse.Namespace):
    """The run's `ExperimentConfig`: the preset, its `--set` edits, then the flags that
    set config fields (`--data`, and `--eval-meshes`, `--real-meshes`, `--init-from`
    when given)."""
    from dmd_jax.config import preset

    cfg = preset(args.preset).with_edits(_parse_edits(args.set or []))
    data = {"dataset_dir": args.data}
    if args.eval_meshes is not None:
        data["eval_meshes_per_split"] = args.eval_meshes
    if args.real_meshes:
        data["real_root"] = args.real_meshes
    edits = {"data": data}
    if args.init_from is not None:
        edits["train"] = {"init_from": args.init_from}
    return cfg.with_edits(edits)


def _cmd_train(args: argparse.Namespace) -> int:
    import json

    import jax

    from dmd_jax.cli._common import MAX_EVAL_MESHES, check_local_path, check_range

    check_range("--eval-meshes", args.eval_meshes, 0, MAX_EVAL_MESHES)
    for flag, value in (
        ("--data", args.data),
        ("--init-from", args.init_from),
        ("--real-meshes", args.real_meshes),
        ("--workdir", args.workdir),
    ):
        check_local_path(flag, value)
    # Before anything touches a device: the device list then spans every process.
    distributed = _distributed_args(args)
    if distributed is not None:
        jax.distributed.initialize(**distributed)

    from dmd_jax.train import train_and_evaluate

    cfg = _train_config(args)
    hooks = []
    if args.long_run is not None:
        check_local_path("--long-run", args.long_run)
        check_range("--checkpoint-minutes", args.checkpoint_minutes, 0.1, 24 * 60)
        hooks.append(_long_run_hook(args, cfg))
    result = train_and_evaluate(
        cfg,
        args.workdir,
        pad=args.pad,
        data_parallel=args.data_parallel,
        progress=not args.no_progress,
        verbose=True,
        hooks=hooks,
    )
    result.pop("state", None)
    if jax.process_index() == 0:
        print(json.dumps(result, indent=2) if args.json else _train_summary(result))
    return 0


def _long_run_hook(args: argparse.Namespace, cfg):
    """The `dmd_jax.long_run.LongRun` hook of `--long-run`, with the process's pid
    recorded in the workdir (`make train-long-save` and `-status` read it)."""
    import os
    from pathlib import Path

    from dmd_jax.io import write_text_atomic
    from dmd_jax.long_run import PID_FILE, LongRun

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(workdir / PID_FILE, f"{os.getpid()}\n")
    return LongRun(
        workdir,
        args.long_run,
        cfg.to_dict(),
        checkpoint_seconds=60.0 * args.checkpoint_minutes,
        say=lambda line: print(line, flush=True),
    )


def _train_summary(result: dict) -> str:
    """One line: the trained model's mean normal error against its noisy input's, per
    evaluation set, e.g. `test_intra normal error 9.5° vs noisy 20.1° (-53 %)`."""
    parts = []
    for key in sorted(k for k in result if k.endswith("/normal_deg") and "/noisy_" not in k):
        split = key.split("/")[0]
        model, noisy = result[key], result.get(f"{split}/noisy_normal_deg")
        if noisy is None:
            continue
        change = 100.0 * (model - noisy) / noisy if noisy else 0.0
        parts.append(f"{split} normal error {model:.1f}° vs noisy {noisy:.1f}° ({change:+.0f} %)")
    head = f"step {result['step']}, {result['wall_time_s']:.0f} s"
    if not parts:
        return f"{head}: no evaluation set, nothing to compare"
    return f"{head}: " + "; ".join(parts)


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
    p = sub.add_parser("train", help="train DMD-Net on a dataset made by make-dataset")
    p.add_argument("--data", required=True, help="dataset directory (make-dataset output)")
    p.add_argument("--workdir", required=True, help="checkpoints, log.jsonl, loss_curve.png")
    p.add_argument("--preset", default="small", help="paper, small or test")
    p.add_argument(
        "--set",
        nargs="*",
        metavar="SECTION.FIELD=VALUE",
        help="config edits, e.g. train.steps=3000 loss.vertex=50",
    )
    p.add_argument(
        "--eval-meshes",
        type=int,
        default=None,
        help="sets data.eval_meshes_per_split: meshes of each test split used for "
        "periodic evaluation (default: the config's, 8 of each)",
    )
    p.add_argument(
        "--init-from",
        default=None,
        help="sets train.init_from: checkpoint directory or weights file to fine-tune from "
        "(the same parameter shapes; settings that hold no parameters, such as "
        "vertex_iterations, may differ)",
    )
    p.add_argument(
        "--real-meshes",
        default=None,
        metavar="DIR",
        help="sets data.real_root: folder of real meshes (e.g. ../shared/meshes/train): "
        "its training split is added as connected patches, its fixed validation split "
        "(dmd_jax.data.real) is evaluated as 'val' with the benchmark noise and picks the "
        "best checkpoint (patch sizes: data.real_* fields, e.g. --set "
        "data.real_patch_faces=4000)",
    )
    p.add_argument(
        "--pad",
        choices=("auto", "bucket", "largest", "classes"),
        default="auto",
        help="bucket: each batch padded to its own vertex bucket (one compiled program per "
        "bucket, least padding); largest: every batch to the largest the data can form (one "
        "program); classes: the smallest of four size classes (four programs, compiled "
        "before the first step); auto: largest for runs of at most 500 steps "
        "(dmd_jax.train.AUTO_PAD_MAX_STEPS), classes with train.candidate_pool, else bucket",
    )
    p.add_argument(
        "--json", action="store_true", help="print the final evaluation as JSON, not one line"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--long-run",
        default=None,
        metavar="STATE",
        help="a run that outlives sessions (dmd_jax.long_run): resume from this committed "
        "state file (params, optimiser, step) unless the workdir is ahead of it, export "
        "every checkpoint to WORKDIR/state.msgpack, stop cleanly on WORKDIR/STOP or SIGTERM",
    )
    p.add_argument(
        "--checkpoint-minutes",
        type=float,
        default=10.0,
        help="with --long-run: the longest wall time between two checkpoints (default 10)",
    )
    p.add_argument(
        "--data-parallel",
        action="store_true",
        help="split each global batch over every device (train.batch_size >= devices)",
    )
    p.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="multi-host: address of process 0 (with --num-processes, --process-id)",
    )
    p.add_argument(
        "--num-processes", type=int, default=None, help="multi-host: number of processes"
    )
    p.add_argument("--process-id", type=int, default=None, help="multi-host: this process, 0..N-1")
    p.set_defaults(func=_cmd_train)
