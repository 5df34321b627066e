"""Fits the weights' denoising policy on the validation split and reports it (`make calibrate`).

A thin script over `dmd_jax.calibrate` (where the method is described): it measures the
pass rule and the pre-smoothing rule of DMD-Net weights on the validation split of
`../shared/meshes/train`, fits both, writes `results/pass_tolerance.{md,csv}` and
`results/presmooth_fit.{md,csv}`, prints the fitted `DenoisePolicy` and, with `--out`,
writes a weights file with the same params and the fitted policy. Weights trained as a
cascade (`train.passes` above 1) keep their trained pass count: only the pre-smoothing
rule is fitted, and the pass report is left as it is. Never run on the test meshes.

```bash
python benchmarks/quality/calibrate.py                     # bundled weights (~20 min, 2 cores)
python benchmarks/quality/calibrate.py --weights run.msgpack --out run_fitted.msgpack
python benchmarks/quality/calibrate.py --reuse             # refit from the two CSVs
```
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    environment,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax import calibrate as cal  # noqa: E402
from dmd_jax import protocol  # noqa: E402
from dmd_jax.presmooth import MAX_STEPS  # noqa: E402

PRESMOOTH_CSV_HEADER = [*cal.PRESMOOTH_HEADER, *(f"steps_{k}" for k in range(MAX_STEPS + 1))]


def pass_report(rows, best: float, weights, out: Path) -> Path:
    """`pass_tolerance.md`: per level and for every candidate tolerance."""
    levels = sorted({r[2] for r in rows})

    def bench_mean(t):
        return np.mean([cal.simulate_passes(rows, t, lv) for lv in protocol.NOISE_LEVELS])

    curve = [
        [f"{t:.2f}"]
        + [f"{cal.simulate_passes(rows, t, lv):.2f}" for lv in levels]
        + [f"{bench_mean(t):.3f}"]
        for t in cal.TOLERANCES
    ]
    per_level = [
        [
            f"{lv}",
            f"{np.mean([r[4] for r in rows if r[2] == lv]):.2f}",
            f"{np.mean([r[5] for r in rows if r[2] == lv]):.2f}",
            f"{sum(r[5] < r[4] for r in rows if r[2] == lv)} / {sum(r[2] == lv for r in rows)}",
            f"{np.median([r[6] for r in rows if r[2] == lv]):.3f}",
            f"{cal.simulate_passes(rows, best, lv):.2f}",
            f"{sum(r[6] > best for r in rows if r[2] == lv)}",
            f"{sum(r[6] > best and r[7] > best for r in rows if r[2] == lv)}",
        ]
        for lv in levels
    ]
    headers = ["σ (edges)", "one pass", "two passes", "two better", "median first move"]
    headers += [f"rule at {best:.2f}", "second pass runs", "a third would run"]
    levels_text = " / ".join(f"{lv:g}" for lv in protocol.NOISE_LEVELS)
    return write_report(
        out,
        title="`pass_tolerance`: when a second DMD-Net pass helps",
        env=environment(packages=("dmd_jax", "jax", "numpy")),
        intro=(
            "The pass rule of `dmd_jax.calibrate` (`pass_rows`, `fit_pass_tolerance`) on "
            "the validation split: benchmark noise (`dmd_jax.protocol`) at "
            f"{', '.join(f'{lv:g}' for lv in cal.PASS_LEVELS)} mean edges, the normal error "
            "after one and two passes and how far the first pass moved the mesh; the "
            f"tolerance minimises the mean over {levels_text}.\n\n"
            f"Chosen tolerance: **{best:.2f}** mean edges."
        ),
        sections=[
            (
                "Per level (validation split, mean normal error in degrees)",
                markdown_table(headers, per_level),
            ),
            (
                "Every candidate tolerance",
                markdown_table(
                    ["tolerance"] + [f"σ {lv}" for lv in levels] + [f"mean of {levels_text}"],
                    curve,
                ),
            ),
        ],
        weights=weights,
    )


def presmooth_report(rows, clean, start, per_step, errs, weights, out: Path) -> Path:
    """`presmooth_fit.md`: the rule against the network alone, the Laplacian and the
    per-mesh oracle, per noise condition."""
    names = [cal.condition_name(d, lv) for d, lv in cal.PRESMOOTH_CONDITIONS]

    def mean_of(col):
        return {n: float(np.mean([col(r) for r in rows if r[2] == n])) for n in names}

    columns = {
        "noisy roughness (median °)": {
            n: float(np.median([r[4] for r in rows if r[2] == n])) for n in names
        },
        "Laplacian ×10 (the baseline)": mean_of(lambda r: r[5]),
        "network alone (0 steps)": mean_of(lambda r: r[6]),
        f"rule ({start:g}, {per_step:g})": errs,
        "best steps per mesh (oracle)": mean_of(lambda r: min(r[6:])),
    }
    table = markdown_table(
        ["noise (mean edges)", *columns],
        [
            [n] + [f"{c[n]:.1f}" if "roughness" in h else f"{c[n]:.2f}" for h, c in columns.items()]
            for n in names
        ]
        + [["mean"] + [f"{np.mean(list(c.values())):.2f}" for c in columns.values()]],
    )
    clean_table = markdown_table(
        ["clean validation mesh", "roughness (°)"],
        [[m, f"{r:.1f}"] for m, r in sorted(clean.items())],
    )
    return write_report(
        out,
        title="Pre-smoothing before DMD-Net: how many Laplacian steps heavy noise needs",
        env=environment(packages=("dmd_jax", "jax", "numpy")),
        intro=(
            "The pre-smoothing rule of `dmd_jax.calibrate` (`presmooth_rows`, "
            "`fit_presmooth`) on the validation split (crops of at most "
            f"{cal.PRESMOOTH_MAX_FACES:,} faces): per noise condition, the error of "
            f"`denoise(..., presmooth=0)` after 0-{MAX_STEPS} Laplacian steps; the rule "
            "minimises the mean over the conditions among those leaving every clean mesh "
            "alone.\n\n"
            f"Chosen rule: **start {start:g}°, {per_step:g}° a step** "
            f"(`dmd-jax export-weights ... --presmooth {start:g} {per_step:g}`)."
        ),
        sections=[
            ("Mean normal error (degrees) per noise condition, validation split", table),
            ("Clean validation meshes (the rule must leave them alone)", clean_table),
        ],
        weights=weights,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--weights", default=None, help="weights (default: bundled)")
    parser.add_argument("--val-meshes", default=str(protocol.validation_dir()))
    parser.add_argument("--out", default=None, help="write the weights with the fitted policy")
    parser.add_argument("--reuse", action="store_true", help="refit from the existing CSVs")
    parser.add_argument("--results", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)

    from dmd_jax.checkpoints import load_model, save_weights

    bundle = load_model(args.weights)
    # A network trained as a cascade (train.passes > 1) runs its trained passes: only
    # the pre-smoothing rule is fitted for it.
    fit_passes = bundle.config.train.passes == 1
    results = Path(args.results)
    pass_csv, presmooth_csv = results / "pass_tolerance.csv", results / "presmooth_fit.csv"
    if args.reuse:
        p_rows = cal.read_pass_csv(pass_csv) if fit_passes else []
        s_rows, clean = cal.read_presmooth_csv(presmooth_csv)
        tolerance = cal.fit_pass_tolerance(p_rows) if fit_passes else None
        start, per_step, errs = cal.fit_presmooth(s_rows, clean)
        policy = cal.fitted_policy(
            bundle.policy, pass_tolerance=tolerance, presmooth=(start, per_step)
        )
    else:
        fit = cal.calibrate(bundle, args.val_meshes, echo=print, fit_passes=fit_passes)
        policy, p_rows, s_rows, clean, errs = fit
        tolerance, start, per_step = (
            policy.pass_tolerance,
            policy.presmooth_start,
            policy.presmooth_per_step,
        )
        if fit_passes:
            write_csv(pass_csv, cal.PASS_HEADER, p_rows)
        blank = [""] * (len(PRESMOOTH_CSV_HEADER) - 5)
        clean_rows = [[m, "", "clean", "", r, *blank] for m, r in clean.items()]
        write_csv(presmooth_csv, PRESMOOTH_CSV_HEADER, s_rows + clean_rows)
    weights = args.weights or BUNDLED
    if fit_passes:
        pass_report(p_rows, tolerance, weights, results / "pass_tolerance.md")
    else:
        print(f"pass count trained, not fitted: {policy.max_passes} (train.passes)")
    presmooth_report(s_rows, clean, start, per_step, errs, weights, results / "presmooth_fit.md")
    print(f"fitted policy: {policy}")
    if args.out:
        meta = {**bundle.meta, "policy_fitted_by": "benchmarks/quality/calibrate.py"}
        save_weights(args.out, bundle.params, bundle.config, meta, policy=policy)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
