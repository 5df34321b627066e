"""Learning curves of a `make train-long` run: training loss and the evaluation sets'
mean face-normal error against steps, from the run's `log.jsonl`.

    python scripts/train_long_report.py runs/long/ft --out benchmarks/results/train_long.png

Prints the evaluation table (markdown) and writes the plot.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def read_log(path: Path) -> tuple[list[dict], list[dict]]:
    """The `train` and `eval` records of a run's `log.jsonl`, in step order."""
    train, evals = [], []
    for line in path.read_text().splitlines():
        record = json.loads(line)
        (train if record.get("kind") == "train" else evals).append(record)
    return train, [r for r in evals if r.get("kind") == "eval"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the run's workdir (holds log.jsonl)")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args(argv)
    train, evals = read_log(args.run / "log.jsonl")
    sets = sorted({k.split("/")[0] for r in evals for k in r if k.endswith("/normal_deg")})
    print("| step | " + " | ".join(f"{s} normal (°)" for s in sets) + " |")
    print("|---:|" + "---:|" * len(sets))
    for r in evals:
        cells = [f"{r[f'{s}/normal_deg']:.2f}" if f"{s}/normal_deg" in r else "" for s in sets]
        print(f"| {r['step']} | " + " | ".join(cells) + " |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.4))
    a.plot([r["step"] for r in train], [r["loss"] for r in train], lw=0.8)
    a.set(title="training loss (logged every 100 steps)", xlabel="step", yscale="log")
    for s in sets:
        pts = [(r["step"], r[f"{s}/normal_deg"]) for r in evals if f"{s}/normal_deg" in r]
        b.plot(*zip(*pts, strict=True), marker="o", label=s)
    b.set(title="mean face-normal error (°)", xlabel="step")
    b.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
