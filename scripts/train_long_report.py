"""Learning curves of the long run: training loss and the evaluation sets' mean
face-normal error against steps, from its committed curve (all sessions).

    python scripts/train_long_report.py training/long_run_curve.csv \\
        --out benchmarks/results/train_long.png

Prints the evaluation table (markdown) and writes the plot. The curve is the long
format `make train-long-save` appends (`dmd_jax.long_run`: step, kind, name, value).
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path


def read_curve(path: Path) -> tuple[dict, dict]:
    """`(train, evals)`: `{step: {name: value}}` of the training rows and of the
    evaluation rows of a curve CSV."""
    train, evals = defaultdict(dict), defaultdict(dict)
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            table = train if row["kind"] == "train" else evals
            table[int(row["step"])][row["name"]] = float(row["value"])
    return dict(train), dict(evals)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("curve", type=Path, help="the run's curve CSV")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args(argv)
    train, evals = read_curve(args.curve)
    sets = sorted({k.split("/")[0] for r in evals.values() for k in r if k.endswith("/normal_deg")})
    print("| step | " + " | ".join(f"{s} normal (°)" for s in sets) + " |")
    print("|---:|" + "---:|" * len(sets))
    for step, r in sorted(evals.items()):
        cells = [f"{r[f'{s}/normal_deg']:.2f}" if f"{s}/normal_deg" in r else "" for s in sets]
        print(f"| {step} | " + " | ".join(cells) + " |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.4))
    steps = sorted(s for s, r in train.items() if "loss" in r)
    a.plot(steps, [train[s]["loss"] for s in steps], lw=0.8)
    a.set(title="training loss (logged every 100 steps)", xlabel="step", yscale="log")
    for s in sets:
        pts = sorted((k, r[f"{s}/normal_deg"]) for k, r in evals.items() if f"{s}/normal_deg" in r)
        if pts:
            b.plot(*zip(*pts, strict=True), marker="o", label=s)
    b.set(title="mean face-normal error (°)", xlabel="step")
    if sets:
        b.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
