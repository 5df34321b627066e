"""DMD-Net's rows of two sota-lite reports, mesh by mesh: how a change of weights or policy
moved each case, and each run per shape against the best other library denoiser.

    python benchmarks/quality/compare_dmd_rows.py benchmarks/results/sota_lite.csv \\
        runs/ctrl/val_ctrl.csv --set val --names default controller

Both reports must hold the same meshes, conditions and seeds (sota_lite's `--reuse-from`
the first report's classic rows). Prints a markdown table per condition: the geometric
mean of new / old per mesh (errors below 0.1° count as 0.1°, as sota_lite's per-shape
tables), how many meshes got better or worse by more than 2 %, the worst with its mesh,
and each run's geometric mean against the best other method of its own report.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np

FLOOR = 0.1
NOT_COMPARED = {"noisy", "dmd", "dmd_x2", "meshlab_taubin", "meshlab_two_step"}


def read(path: Path, wanted: str) -> dict:
    """`{(noise, level): {mesh: {method: normal_deg}}}` of one set of a report."""
    out: dict = defaultdict(lambda: defaultdict(dict))
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            if r["set"] == wanted:
                out[(r["noise"], r["level"])][r["mesh"]][r["method"]] = float(r["normal_deg"])
    return out


def geomean(x) -> float:
    return float(np.exp(np.mean(np.log(np.asarray(x, np.float64)))))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--set", default="val")
    parser.add_argument("--names", nargs=2, default=("old", "new"))
    args = parser.parse_args(argv)
    old, new = read(args.old, args.set), read(args.new, args.set)
    a, b = args.names
    print(
        f"| condition | meshes | {b} / {a} (geometric mean) | better | worse | worst (mesh) "
        f"| {a} / best other | {b} / best other |"
    )
    print("|---|---:|---:|---:|---:|---|---:|---:|")
    for cond in sorted(new, key=lambda c: (c[0], float(c[1]) if c[1] else 0.0)):
        meshes = sorted(
            m for m in new[cond] if "dmd" in new[cond][m] and "dmd" in old[cond].get(m, {})
        )
        if not meshes:
            continue
        ratio = np.array(
            [max(new[cond][m]["dmd"], FLOOR) / max(old[cond][m]["dmd"], FLOOR) for m in meshes]
        )

        def per_shape(report, cond=cond, meshes=meshes):
            rows = []
            for m in meshes:
                others = [v for k, v in report[cond][m].items() if k not in NOT_COMPARED]
                rows.append(max(report[cond][m]["dmd"], FLOOR) / max(min(others), FLOOR))
            return geomean(rows)

        worst = int(np.argmax(ratio))
        label = f"{cond[0]} {cond[1]}".strip()
        print(
            f"| {label} | {len(meshes)} | {geomean(ratio):.3f} | {int(np.sum(ratio < 0.98))} | "
            f"{int(np.sum(ratio > 1.02))} | {ratio[worst]:.2f} ({meshes[worst]}) | "
            f"{per_shape(old):.3f} | {per_shape(new):.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
