"""The `dmd-jax` command line.

Each subcommand lives in its own `_cmd_*` function; `main` turns any `ValueError` or
`OSError` (missing file, existing output, a directory or unwritable path) into a
one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import sys


def _cmd_info(args: argparse.Namespace) -> int:
    import jax

    import dmd_jax

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
    return 0


def _load_model_or_method(args: argparse.Namespace):
    """The denoiser the user asked for: a baseline name, a weights file, a checkpoint dir."""
    from dmd_jax.checkpoints import load_model

    if getattr(args, "method", "dmd") != "dmd":
        return None
    return load_model(args.weights)


def _cmd_denoise(args: argparse.Namespace) -> int:
    import time

    from dmd_jax import inference
    from dmd_jax.io import load_mesh, save_mesh

    if args.iterations < 1:
        raise ValueError(f"--iterations must be at least 1, got {args.iterations}")
    vertices, faces = load_mesh(args.input)
    _check_output(args.output, args.input, args.overwrite)
    t0 = time.perf_counter()
    if args.method == "dmd":
        bundle = _load_model_or_method(args)
        out = inference.denoise(vertices, faces, bundle, iterations=args.iterations)
    else:
        from dmd_jax import baselines

        out = vertices
        for _ in range(args.iterations):
            out = baselines.denoise_with(args.method, out, faces)
    elapsed = time.perf_counter() - t0
    save_mesh(args.output, out, faces, overwrite=args.overwrite, protect=[args.input])
    print(
        f"denoised {args.input} ({len(vertices)} vertices, {len(faces)} faces) with "
        f"{args.method} in {elapsed:.2f} s -> {args.output}"
    )
    return 0


def _check_output(output, inputs, overwrite: bool) -> None:
    """Refuses to clobber an input, or an existing output without --overwrite."""
    from pathlib import Path

    out = Path(output)
    for src in [inputs] if isinstance(inputs, (str, Path)) else inputs:
        if Path(src).resolve() == out.resolve():
            raise ValueError(f"{output}: the output path is the input file; choose another")
    if out.is_dir():
        raise ValueError(f"{output}: is a directory; give a file name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{output}: already exists (pass --overwrite to replace it)")
    if not out.parent.resolve().is_dir():
        raise FileNotFoundError(f"{out.parent}: output directory does not exist")


def _cmd_add_noise(args: argparse.Namespace) -> int:
    import jax
    import numpy as np

    from dmd_jax.io import load_mesh, save_mesh
    from dmd_jax.noise import add_noise

    vertices, faces = load_mesh(args.input)
    _check_output(args.output, args.input, args.overwrite)
    noisy = add_noise(
        jax.random.PRNGKey(args.seed), vertices, faces, args.kind, args.level, units=args.units
    )
    save_mesh(
        args.output,
        np.asarray(noisy, np.float64),
        faces,
        overwrite=args.overwrite,
        protect=[args.input],
    )
    print(
        f"added {args.kind} noise, level {args.level} ({args.units} units, seed {args.seed}) "
        f"-> {args.output}"
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import mesh_metrics

    gt_v, gt_f = load_mesh(args.gt)
    rows = []
    for path in args.mesh:
        v, f = load_mesh(path)
        if v.shape != gt_v.shape or f.shape != gt_f.shape or (f != gt_f).any():
            raise ValueError(
                f"{path}: vertex/face correspondence with {args.gt} is required "
                f"({len(v)} vs {len(gt_v)} vertices, {len(f)} vs {len(gt_f)} faces)"
            )
        m = mesh_metrics(v, gt_v, gt_f)
        rows.append({"mesh": str(path), **{k: float(x) for k, x in m.items()}})
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"{'mesh':40s} {'vertex(1e-4)':>13s} {'normal(deg)':>12s} {'chamfer(1e-4)':>14s}")
        for r in rows:
            print(
                f"{r['mesh'][-40:]:40s} {r['vertex'] * 1e4:13.4f} {r['normal_deg']:12.3f} "
                f"{r['chamfer'] * 1e4:14.4f}"
            )
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from pathlib import Path

    from dmd_jax.io import load_mesh
    from dmd_jax.render import render_meshes

    _check_output(args.output, args.inputs + ([args.gt] if args.gt else []), args.overwrite)
    meshes = [load_mesh(p) for p in args.inputs]
    values = None
    if args.gt:
        from dmd_jax.metrics import face_normal_errors_deg

        gt_v, gt_f = load_mesh(args.gt)
        values = []
        for path, (v, f) in zip(args.inputs, meshes, strict=True):
            if v.shape != gt_v.shape or (f.shape != gt_f.shape) or (f != gt_f).any():
                raise ValueError(f"{path}: needs the same vertices/faces layout as {args.gt}")
            values.append(face_normal_errors_deg(v, gt_v, gt_f))
    titles = args.titles.split(",") if args.titles else [Path(p).stem for p in args.inputs]
    render_meshes(meshes, args.output, titles=titles, face_values=values, overwrite=args.overwrite)
    print(f"wrote {args.output}")
    return 0


def _cmd_make_dataset(args: argparse.Namespace) -> int:
    import time

    from dmd_jax.data import DEFAULT_TEST_INTER, convert_folder, make_dataset

    def names(text):
        return tuple(x.strip() for x in text.split(",") if x.strip()) if text else None

    start = time.perf_counter()
    common = dict(
        seed=args.seed,
        intra_fraction=args.intra_fraction,
        workers=args.workers,
        min_vertices=args.min_vertices,
        max_vertices=args.max_vertices,
        progress=not args.no_progress,
        overwrite=args.overwrite,
    )
    if args.from_folder:
        if args.per_category is not None or args.categories:
            raise ValueError(
                "--per-category and --categories apply to procedural data, not --from-folder"
            )
        ds = convert_folder(
            args.from_folder,
            args.out,
            test_inter=names(args.test_inter),
            remesh=args.remesh,
            **common,
        )
    else:
        if args.per_category is None:
            raise ValueError("--per-category is required (or give --from-folder)")
        test_inter = names(args.test_inter)
        ds = make_dataset(
            args.out,
            per_category=args.per_category,
            categories=names(args.categories),
            test_inter=DEFAULT_TEST_INTER if test_inter is None else test_inter,
            **common,
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


def _cmd_train(args: argparse.Namespace) -> int:
    import json
    import time

    import jax

    # Before anything touches a device: the device list then spans every process.
    distributed = _distributed_args(args)
    if distributed is not None:
        jax.distributed.initialize(**distributed)
    primary = jax.process_index() == 0

    from dmd_jax.config import preset
    from dmd_jax.data.dataset import load_dataset
    from dmd_jax.pipeline import make_examples
    from dmd_jax.train import train

    cfg = preset(args.preset).with_edits(_parse_edits(args.set or []))
    data = load_dataset(args.data)
    train_ex = make_examples(data.arrays("train"))
    evals = {}
    for split in ("test_intra", "test_inter"):
        records = data.split(split)[: args.eval_meshes]
        evals[split] = make_examples([r.load() for r in records])
    if primary:
        print(
            f"training {cfg.name} on {len(train_ex)} meshes from {args.data}; evaluating on "
            + ", ".join(f"{k}: {len(v)}" for k, v in evals.items())
            + (f"; data-parallel over {jax.device_count()} devices" if args.data_parallel else "")
        )
    init = None
    if args.init_from:
        from dmd_jax.checkpoints import load_params

        init, init_cfg = load_params(args.init_from)
        if init_cfg.model != cfg.model:
            raise ValueError(f"{args.init_from}: its model config differs from this run's")
    t0 = time.time()
    result = train(
        cfg,
        train_ex,
        args.workdir,
        eval_sets=evals,
        progress=primary and not args.no_progress,
        init_params=init,
        data_parallel=args.data_parallel,
    )
    result.pop("state", None)
    result["wall_time_s"] = time.time() - t0
    if primary:
        print(json.dumps(result, indent=2))
    return 0


def _cmd_export_weights(args: argparse.Namespace) -> int:
    import json
    import platform

    from dmd_jax.checkpoints import load_params, save_weights

    params, cfg = load_params(args.checkpoint)
    meta = {"source": str(args.checkpoint), "platform": platform.platform()}
    if args.meta:
        meta.update(json.loads(args.meta))
    path = save_weights(args.output, params, cfg, meta, overwrite=args.overwrite)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from dmd_jax.demo import run_demo

    run_demo(args.out, weights=args.weights, overwrite=args.overwrite, render=not args.no_render)
    return 0


def _cmd_train_cnr(args: argparse.Namespace) -> int:
    import shlex

    from dmd_jax.baselines.cascaded_regression import train_main

    train_main(args, "dmd-jax " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmd-jax", description="DMD-Net mesh denoising in JAX (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="versions, devices, presets and parameter counts")
    p.add_argument(
        "--preset",
        choices=("paper", "small", "test"),
        help="print the parameter count of a preset's model",
    )
    p.add_argument("--variant", help="structure-ablation variant, e.g. FGT-3 or fgt3")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("denoise", help="denoise a mesh file")
    p.add_argument("input", help="noisy mesh (.obj .off .ply .stl)")
    p.add_argument("-o", "--output", required=True, help="where to write the result")
    p.add_argument(
        "--weights",
        default=None,
        help="weights file or checkpoint directory (default: bundled model)",
    )
    p.add_argument(
        "--method",
        default="dmd",
        help="'dmd' (the network) or a classic baseline: laplacian, taubin, bmd, "
        "nifp, fefp, bnf, gnf, l0",
    )
    p.add_argument("--iterations", type=int, default=1, help="passes of the denoiser")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_denoise)

    p = sub.add_parser("add-noise", help="add synthetic noise to a mesh file")
    p.add_argument("input")
    p.add_argument("-o", "--output", required=True)
    p.add_argument(
        "--kind", default="gaussian", choices=["gaussian", "uniform", "gamma", "impulse"]
    )
    p.add_argument("--level", type=float, required=True)
    p.add_argument(
        "--units",
        default="canonical",
        choices=["canonical", "edge"],
        help="canonical: fraction of the longest bbox side; edge: × mean edge length",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_cmd_add_noise)

    p = sub.add_parser("evaluate", help="vertex / normal / chamfer metrics against a ground truth")
    p.add_argument("--gt", required=True, help="ground-truth mesh (same vertex order)")
    p.add_argument("--mesh", required=True, nargs="+", help="meshes to score")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("render", help="shaded PNG of meshes side by side")
    p.add_argument("inputs", nargs="+")
    p.add_argument("-o", "--output", required=True, help="PNG path")
    p.add_argument("--gt", default=None, help="colour faces by normal error against this mesh")
    p.add_argument("--titles", default=None, help="comma-separated panel titles")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser(
        "make-dataset", help="generate procedural training meshes, or convert a mesh folder"
    )
    p.add_argument("--out", required=True, help="output directory (must be empty)")
    p.add_argument("--per-category", type=int, default=None, help="shapes per category")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--min-vertices", type=int, default=1000)
    p.add_argument("--max-vertices", type=int, default=6000)
    p.add_argument(
        "--test-inter",
        default=None,
        help="comma-separated categories held out whole (default: fastener,bottle,metaballs "
        "for procedural data, none for folders)",
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
        default=16,
        help="meshes of each test split used for periodic evaluation",
    )
    p.add_argument(
        "--init-from",
        default=None,
        help="checkpoint directory to fine-tune from (same model config)",
    )
    p.add_argument("--no-progress", action="store_true")
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

    p = sub.add_parser("export-weights", help="checkpoint directory -> one weights file")
    p.add_argument("checkpoint", help="an Orbax checkpoint directory (e.g. RUN/checkpoints/best)")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--meta", default=None, help="JSON object of provenance to store")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_cmd_export_weights)

    # Further subcommands are registered below, one block each.
    p = sub.add_parser(
        "demo", help="denoise a generated noisy CAD part; print metrics, write meshes and a PNG"
    )
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument(
        "--weights",
        default=None,
        help="weights file or checkpoint directory (default: bundled model)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--no-render", action="store_true", help="skip before_after.png")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "train-cnr", help="train the CNR baseline (dmd_jax.baselines.cascaded_regression)"
    )
    p.add_argument("--data", required=True, help="dataset directory (make-dataset output)")
    p.add_argument("--out", required=True, help="weights file to write (.msgpack)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--max-meshes", type=int, default=None, help="first N train meshes only")
    p.add_argument("--draws", type=int, default=1, help="noisy copies per mesh")
    p.add_argument("--faces-per-mesh", type=int, default=512, help="faces sampled per copy")
    p.add_argument("--steps", type=int, default=2000, help="Adam steps per stage")
    p.add_argument("--batch-size", type=int, default=1024)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stages", type=int, default=2, help="cascade length")
    p.add_argument("--hidden", type=int, nargs="+", default=[128, 128, 64])
    p.add_argument("--vertex-iterations", type=int, default=20)
    p.add_argument("--eval-meshes", type=int, default=8, help="test-intra meshes checked")
    p.set_defaults(func=_cmd_train_cnr)

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as exc:
        # One line whatever the message holds (some library errors span several lines).
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"dmd-jax {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dmd-jax {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
