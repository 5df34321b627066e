"""`python -m experiments`: run, list and aggregate the ablation sweeps.

Examples::

    python -m experiments run --preset cpu                      # all studies, 3 seeds
    python -m experiments run --preset cpu-quick                # a first look (make ablate-quick)
    python -m experiments run --preset cpu --studies structure depth
    python -m experiments run --preset test --out out/ablate-smoke --data-dir out/ablate-data
    python -m experiments list --preset cpu                     # the runs and their ids
    python -m experiments aggregate experiments/results/cpu     # tables, plots, README
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _parser() -> argparse.ArgumentParser:
    from experiments.studies import PRESETS, STUDY_KEYS

    parser = argparse.ArgumentParser(
        prog="python -m experiments", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p):
        p.add_argument(
            "--preset",
            default=os.environ.get("ABLATE_PRESET", "cpu"),
            choices=sorted(PRESETS),
            help="sweep size (default: $ABLATE_PRESET or cpu)",
        )
        p.add_argument(
            "--studies", nargs="+", choices=STUDY_KEYS, help="default: the preset's (cpu: all)"
        )
        p.add_argument(
            "--seeds",
            nargs="+",
            type=int,
            help="run (or list) only these seeds now (default: the preset's); the tables "
            "keep every seed of the preset",
        )
        p.add_argument(
            "--out", type=Path, help="results dir (default experiments/results/<preset>)"
        )
        p.add_argument("--data-dir", type=Path, help="dataset cache (default data/ablate-<preset>)")

    p = sub.add_parser("run", help="run or resume a sweep, then aggregate")
    common(p)
    p.add_argument("--workers", type=int, help="parallel training processes")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-aggregate", action="store_true")
    p.add_argument(
        "--clean-checkpoints",
        action="store_true",
        help="delete the checkpoints afterwards (noise/rotation runs added later retrain)",
    )

    p = sub.add_parser("list", help="print every run of a sweep and whether it is finished")
    common(p)

    p = sub.add_parser("aggregate", help="write tables, CSVs, plots and README of a results dir")
    p.add_argument("out", type=Path)
    p.add_argument("--index", type=Path, help="also rewrite this results root's README.md")

    p = sub.add_parser("index", help="rewrite a results root's README.md from its presets")
    p.add_argument("root", type=Path, nargs="?", default=REPO / "experiments" / "results")
    return parser


def _resolve(args):
    from experiments.studies import get_preset

    # `--seeds` chooses what runs now; the preset (and the plan the tables read) keeps
    # its own seeds too (`runner.run_sweep`).
    p = get_preset(args.preset)
    out = args.out or REPO / "experiments" / "results" / p.name
    data = args.data_dir or REPO / "data" / f"ablate-{p.dataset_name}"
    return p, out, data


def _folder(path: Path, what: str) -> None:
    """Refuses, in one line, a `path` that is not an existing folder."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such folder ({what})")
    if not path.is_dir():
        raise NotADirectoryError(f"{path}: is not a folder ({what})")


def _json_file(path: Path) -> None:
    """Refuses a `path` that is not a readable JSON file, naming it."""
    import json

    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (not a sweep's results folder? run the sweep)")
    try:
        json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None


def _check_paths(args) -> None:
    """Every path `aggregate` and `index` read or write, checked before any work, so a
    missing, empty or wrong path is one line (as `dmd-jax` says it), not a traceback
    or a README written into the wrong folder."""
    if args.command == "aggregate":
        _folder(args.out, "a sweep's results folder")
        _json_file(args.out / "plan.json")
    root = args.index if args.command == "aggregate" else args.root
    if args.command == "index" or root is not None:
        _folder(root, "a results root")
        presets = [d for d in root.iterdir() if (d / "summary.json").is_file()]
        if args.command == "index" and not presets:
            raise FileNotFoundError(
                f"{root}: holds no preset folder with a summary.json (not a results root?)"
            )
        for d in presets:
            _json_file(d / "summary.json")


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.command in ("aggregate", "index"):
        try:
            _check_paths(args)
        except (OSError, ValueError) as exc:
            print(f"python -m experiments {args.command}: error: {exc}", file=sys.stderr)
            return 2
    if args.command == "run":
        # run_sweep puts the preset's XLA flag in the environment before JAX starts its
        # backend (importing JAX does not start it).
        from experiments import runner

        p, out, data = _resolve(args)
        session = runner.run_sweep(
            p,
            out,
            data,
            studies=args.studies,
            seeds=args.seeds,
            workers=args.workers,
            progress=not args.no_progress,
            aggregate=not args.no_aggregate,
        )
        if args.clean_checkpoints:
            runner.clean_checkpoints(out)
        return 1 if session["failures"] else 0
    if args.command == "list":
        from experiments import runner
        from experiments import studies as st

        p, out, data = _resolve(args)
        ds_ready = (data / runner.CALIBRATION_FILE).is_file() or not p.calibrate_curvature
        gammas = (
            runner._read_json(data / runner.CALIBRATION_FILE)
            if p.calibrate_curvature and ds_ready
            else None
        )
        recorded = out / "plan.json"
        if p.calibrate_curvature and gammas is None:
            # A fresh clone has the results but not the dataset: the recorded plan holds
            # the calibration the run ids were made with.
            if recorded.is_file():
                gammas = runner._read_json(recorded)["calibration"]
                print(f"(no calibration in {data} yet: ids below use {recorded}'s)")
            else:
                print(f"(no calibration in {data} yet: ids below use the paper's gammas)")
        base = st.base_config(p, gammas)
        p = p.with_seeds(args.seeds)
        runs = st.plan(p, base, args.studies or p.studies, out_dir=out)
        homes = st.training_homes(runs)
        for r in runs:
            if args.seeds and r.seed not in args.seeds:
                continue
            done = (out / r.study / r.run_id / "metrics.json").is_file()
            home = homes[r.train_hash]
            shared = "" if home is r else f"  (model of {home.study}/{home.run_id})"
            print(f"{'done' if done else 'todo'}  {r.study}/{r.run_id}  {r.row}{shared}")
        print(f"{len(runs)} runs, {len(homes)} distinct trainings")
        return 0
    if args.command == "aggregate":
        from experiments import aggregate

        _, records = aggregate.load_records(args.out)
        if not any(recs for rows in records.values() for recs in rows.values()):
            # The runs' folders are not in git (`.gitignore`): in a fresh clone this
            # would overwrite the committed tables with empty ones.
            print(
                f"{args.out}: no finished run to aggregate (the runs' folders are not in "
                "git; run the sweep here first)",
                file=sys.stderr,
            )
            return 1
        aggregate.aggregate(args.out)
        if args.index:
            aggregate.write_index(args.index)
        return 0
    if args.command == "index":
        from experiments import aggregate

        print(aggregate.write_index(args.root))
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
