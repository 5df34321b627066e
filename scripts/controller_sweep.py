"""What limits the smoothing controller on real meshes: variants scored on the stored grid.

    python scripts/controller_sweep.py data/smoothing \\
        --report benchmarks/results/controller_sweep.md

Trains controllers (`controller.fit`) on the generated set's train and validation splits
(`train_controller.split_of`; the test split is left out as `make controller` leaves it
out of the final fit) with one thing changed at a time: the seed, how much of the data,
the width, the weight decay, the objective, the weight of the whole meshes, and the
options it may choose (a greedy subset on the generated training rows). Each is scored on
the real validation split's grid (`benchmarks/quality/oracle_val.py`: every option's error
per mesh and condition, the CSV of `--controller-weights none`) per shape against the best
other library method, as `controller_oracle_val.md` scores the controller, without running
the network again: the picks are read off the grid. The statistics of the validation
meshes are computed once and cached beside the grid's CSV. A variant's seeds are one
ensemble (mean scores), unless it is a single seed. Deterministic for a set and a grid.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import environment, markdown_table, write_report  # noqa: E402
from benchmarks.quality import oracle_val as ov  # noqa: E402
from dmd_jax import comparison, controller, protocol  # noqa: E402
from dmd_jax.data import smoothing_set  # noqa: E402
from scripts.train_controller import split_of  # noqa: E402

BASE = {"objective": "regret", "hidden": 64, "l2": 1e-4}  # `make controller`'s choice
SEEDS = (0, 1, 2)
# name -> (fit settings over BASE, seeds, share of the rows, whole-mesh weight, options)
VARIANTS = {
    **{f"seed {s}": ({}, (s,), 1.0, 1, 0) for s in range(5)},
    "ensemble of 5 seeds": ({}, tuple(range(5)), 1.0, 1, 0),
    "25 % of the rows": ({}, SEEDS, 0.25, 1, 0),
    "50 % of the rows": ({}, SEEDS, 0.5, 1, 0),
    "75 % of the rows": ({}, SEEDS, 0.75, 1, 0),
    "all rows": ({}, SEEDS, 1.0, 1, 0),
    "width 32": ({"hidden": 32}, SEEDS, 1.0, 1, 0),
    "weight decay 1e-3": ({"l2": 1e-3}, SEEDS, 1.0, 1, 0),
    "weight decay 1e-2": ({"l2": 1e-2}, SEEDS, 1.0, 1, 0),
    "softmax objective": ({"objective": "softmax"}, SEEDS, 1.0, 1, 0),
    "whole meshes x2": ({}, SEEDS, 1.0, 2, 0),
    "whole meshes x4": ({}, SEEDS, 1.0, 4, 0),
    "6 options": ({}, SEEDS, 1.0, 1, 6),
    "10 options": ({}, SEEDS, 1.0, 1, 10),
    "16 options": ({}, SEEDS, 1.0, 1, 16),
}


def val_statistics(grid_csv: Path, cache: Path):
    """`(keys, [n, C, F] statistics, [n, C] mask)` of every case of the grid, as `decide`
    reads its noisy mesh (cached in `cache`)."""
    from dmd_jax.controller_features import CROPS, crops, features

    if cache.exists():
        z = np.load(cache, allow_pickle=False)
        return z["keys"].tolist(), z["feats"], z["mask"]
    keys, feats, masks = [], [], []
    for r, cond, noisy, tri in ov.stored_cases(ov.read_rows(grid_csv)):
        x, oriented, _ = ov.as_denoise_reads(noisy, tri)
        f = np.array([features(v, t) for v, t in crops(x, oriented)])
        pad, mask = np.zeros((CROPS, f.shape[1])), np.zeros(CROPS, bool)
        pad[: len(f)], mask[: len(f)] = f, True
        keys.append(f"{cond.label}|{r['mesh']}")
        feats.append(pad)
        masks.append(mask)
    np.savez(cache, keys=np.array(keys), feats=np.array(feats), mask=np.array(masks))
    return keys, np.array(feats), np.array(masks)


def val_cases(grid_csv: Path):
    """`(keys, conditions, [n, O] grid errors, default, best other)` of the cases the
    sota-lite CSVs also hold."""
    labels = [o.label for o in ov.grid_options()]
    sota = ov.method_errors(ov.SOTA_CSVS)
    keys, conds, errs, default, other = [], [], [], [], []
    for r in ov.read_rows(grid_csv):
        m = sota.get(ov.case_key(r["noise"], r["level"], r["mesh"]), {})
        rivals = [e for k, e in m.items() if protocol.is_rival(k)]
        if "dmd" not in m or not rivals:
            continue
        label = protocol.NoiseCondition(r["noise"], float(r["level"])).label
        keys.append(f"{label}|{r['mesh']}")
        conds.append(label)
        errs.append([float(r[k]) for k in labels])
        default.append(m["dmd"])
        other.append(min(rivals))
    return keys, np.array(conds), np.array(errs), np.array(default), np.array(other)


def greedy_options(regret: np.ndarray, k: int) -> list[int]:
    """`k` options chosen one by one to minimise the mean log regret of the best of them."""
    chosen: list[int] = []
    for _ in range(k):
        rest = [o for o in range(regret.shape[1]) if o not in chosen]
        chosen.append(min(rest, key=lambda o: regret[:, chosen + [o]].min(axis=1).mean()))
    return chosen


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--grid", type=Path, default=ov.DEFAULT_CSV, help="the grid's CSV")
    parser.add_argument("--report", type=Path, help="markdown report to write")
    args = parser.parse_args(argv)

    keys, conds, grid, default, other = val_cases(args.grid)
    skeys, sfeats, smask = val_statistics(args.grid, args.grid.with_suffix(".statistics.npz"))
    rows_of = [skeys.index(k) for k in keys]
    vf, vm = sfeats[rows_of], smask[rows_of]
    data = smoothing_set.load(args.data)
    grid_args = (smoothing_set.PRESMOOTH_GRID, smoothing_set.UPDATES, smoothing_set.SEARCH_PASSES)
    opts = controller.options(*grid_args)
    errors = controller.option_errors(data["errors"], *grid_args)
    split = np.array([split_of(s) for s in data["specs"]])
    whole = np.array([bool(s.get("whole")) for s in data["specs"]])
    fit_rows = np.flatnonzero(split != "test")
    order = dict.fromkeys(conds)
    floor = comparison.RATIO_FLOOR_DEG

    def per_shape(errs):
        r = np.maximum(errs, floor) / np.maximum(other, floor)
        per = [float(np.exp(np.log(r[conds == c]).mean())) for c in order]
        return float(np.exp(np.log(r).mean())), float(r.max()), per

    out = []
    for label, errs, capture in (
        ("default call", default, None),
        ("grid oracle", grid.min(axis=1), None),
    ):
        out.append((label, *per_shape(errs), capture))
    for name, (settings, seeds, share, whole_weight, k) in VARIANTS.items():
        rows = fit_rows
        if share < 1:
            rows = np.random.default_rng(0).permutation(rows)[: round(share * len(rows))]
        rows = np.concatenate([rows] + [rows[whole[rows]]] * (whole_weight - 1))
        score = 0.0
        for seed in seeds:
            params = controller.fit(
                data["crop_features"][rows],
                errors[rows],
                opts,
                crop_mask=data["crop_mask"][rows],
                seed=seed,
                **{**BASE, **settings},
            )
            score = score + controller.crop_scores(params, vf, vm)
        if k:
            allowed = greedy_options(np.log1p(controller.relative_regret(errors[rows])), k)
            score = np.where(np.isin(np.arange(len(opts)), allowed), score, -np.inf)
        chosen = np.argmax(score, axis=1)
        capture = controller.evaluate(chosen, grid, default)["capture"]
        out.append((name, *per_shape(grid[np.arange(len(chosen)), chosen]), capture))
        print(f"{name}: {out[-1][1]:.3f} (worst {out[-1][2]:.2f}), capture {capture:.0%}")

    headers = ["controller", "all", "worst", "capture", *order]
    table = markdown_table(
        headers,
        [
            [n, f"{g:.3f}", f"{w:.2f}", "" if c is None else f"{c:.0%}", *(f"{p:.3f}" for p in per)]
            for n, g, w, per, c in out
        ],
    )
    if args.report:
        write_report(
            args.report,
            title="What limits the smoothing controller on the validation split",
            env=environment(),
            intro=__doc__.split("\n\n", 2)[2].strip()
            + f"\n\nSet `{args.data}` ({len(errors)} examples, {len(fit_rows)} fitted on); "
            f"base: objective {BASE['objective']}, width {BASE['hidden']}, weight decay "
            f"{BASE['l2']:g}, seeds {SEEDS} unless named. Columns: per shape over the best "
            "other method (geometric mean over the 200 mesh-conditions, worst), the share of "
            "the oracle's gain over the default realised (`controller.evaluate`), and the "
            "geometric mean per condition.",
            command=f"python scripts/controller_sweep.py {args.data} --report {args.report}",
            sections=[("Per shape against the best other method", table)],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
