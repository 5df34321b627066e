"""The review after the network (`dmd_jax.review`): measured, fitted, scored (issue 29).

The learned pre-smoothing choice reads only the noisy mesh; under light noise it cannot
tell a CAD part whose flats the network blurs from a mesh the network denoises well. The
review reads the network's result beside the σ 0.2 route's and keeps it or takes a
route (`calibrate.fit_review`: least mean regret over the nearest training examples).

What this script does:

1. **measures** on the *training* split (the crops and draws of
   `presmooth_learn.py`, `calibrate.LEARN_CONDITIONS`), for every case where the weights'
   learned choice runs the network, the review's features and the normal error of the
   network's result and of each route (`review_learn_train.csv`; about 15 min on two
   cores for the 93 meshes);
2. **fits** the review there, its neighbour count by cross-validation over whole meshes;
3. **measures and scores** it on the validation split (the crops, conditions and seeds
   of `make sota-lite`, and the clean crops; `review_learn_val.csv`): mean normal error /
   per-shape geometric mean over the best other library method (`sota_lite.csv`) /
   share within 5 %, without and with the review, beside the oracle over its options;
4. with `--out`, writes the weights with the review in their policy.

```bash
python benchmarks/quality/review_learn.py                  # measure, fit, report
python benchmarks/quality/review_learn.py --reuse          # refit (measures missing CSVs)
python benchmarks/quality/review_learn.py --reuse --out dmd_jax/weights/dmd_small.msgpack --force
```
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    best_others,
    environment,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax import calibrate, protocol  # noqa: E402


def sota_draw(name, clean, faces, cond):
    """`make sota-lite`'s draw of one validation crop (None: the clean crop)."""
    if cond is None:
        return "clean", 0.0, 0, clean
    seed = protocol.condition_seed(name, cond)
    return cond.kind, float(cond.level), seed, protocol.condition_noise(clean, faces, cond, seed)


def rows_or_measure(path, reuse, measure, routes):
    """`path`'s rows with `reuse` where it exists, else `measure()`'s, written there."""
    if reuse and Path(path).exists():
        return calibrate.read_review_csv(path, routes)
    rows = measure()
    write_csv(path, calibrate.review_header(routes), rows)
    return rows


def dmd_errors(reference_csv, mesh_set: str) -> dict[tuple, float]:
    """`{(mesh, noise, level, seed): DMD-Net's error}` of one set of a `sota_lite` CSV."""
    out = {}
    with open(reference_csv, newline="") as fh:
        for r in csv.DictReader(fh):
            if r["set"] == mesh_set and r["method"] == "dmd":
                key = (r["mesh"], r["noise"], float(r["level"]), int(r["seed"]))
                out[key] = float(r["normal_deg"])
    return out


def score(rows, chosen, best, n_routes, routed):
    """Per condition: mean error, per-shape geometric mean over the best other method and
    share within 5 %, of the options `chosen` (`[n]` indices) on the noisy rows, with the
    cases the first stage routes (`routed`: `{case: error}`, not in `rows`) as they are."""
    _, errors = calibrate.review_arrays(rows, n_routes)
    picked = errors[np.arange(len(rows)), chosen]
    out = {}
    cases = [((r[0], r[1], float(r[2]), int(r[3])), picked[i]) for i, r in enumerate(rows)]
    for key, error in [*cases, *routed.items()]:
        if key[1] == "clean":
            continue
        label = protocol.NoiseCondition(key[1], key[2]).label
        out.setdefault(label, []).append((error, best[key]))
    cells = {}
    for label, pairs in [*out.items(), ("all", [p for v in out.values() for p in v])]:
        e = np.array(pairs)
        ratio = e[:, 0] / e[:, 1]
        cells[label] = (
            f"{e[:, 0].mean():.2f} / {np.exp(np.log(ratio).mean()):.3f} / "
            f"{np.mean(ratio <= 1.05):.0%}"
        )
    return cells


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, help="weights file (default: bundled)")
    parser.add_argument(
        "--reuse", action="store_true", help="refit from the CSVs, measuring those missing"
    )
    parser.add_argument("--limit", type=int, help="measure only the first N training meshes")
    parser.add_argument("--reference", type=Path, default=RESULTS_DIR / "sota_lite.csv")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default="review_learn")
    parser.add_argument("--out", type=Path, help="write the weights with the review")
    parser.add_argument("--force", action="store_true", help="let --out replace a file")
    args = parser.parse_args(argv)

    import dmd_jax
    from dmd_jax.checkpoints import save_weights

    bundle = dmd_jax.load_weights(args.weights) if args.weights else dmd_jax.load_pretrained()
    policy = bundle.policy.without_review()
    bundle = bundle._replace(policy=policy)
    routes = list(zip(policy.route_sigmas, policy.route_passes, strict=True))
    start = time.perf_counter()
    try:
        if not routes:
            raise ValueError("the weights' policy has no routes (presmooth_learn.py --routes)")
        train = rows_or_measure(
            args.out_dir / f"{args.name}_train.csv",
            args.reuse,
            lambda: calibrate.review_rows(
                calibrate.training_cases()[: args.limit], bundle, echo=print
            ),
            routes,
        )
        val = rows_or_measure(
            args.out_dir / f"{args.name}_val.csv",
            args.reuse,
            lambda: calibrate.review_rows(
                calibrate.validation_cases(),
                bundle,
                (*protocol.QUALITY_CONDITIONS, None),
                draw=sota_draw,
                echo=print,
            ),
            routes,
        )
        best = best_others(args.reference, "val")
        reviewed = {(r[0], r[1], float(r[2]), int(r[3])) for r in val}
        # The cases the first stage routes: their error as `make sota-lite` measured it.
        routed = {
            k: e
            for k, e in dmd_errors(args.reference, "val").items()
            if k not in reviewed and k in best
        }
        if len(routed) + sum(r[1] != "clean" for r in val) != len(best):
            raise ValueError(f"{args.reference} does not cover the validation cases")
        fit = calibrate.fit_review(train, len(routes))
    except (ValueError, FileNotFoundError) as exc:
        print(f"review_learn: error: {exc}", file=sys.stderr)
        return 2
    val_features, val_errors = calibrate.review_arrays(val, len(routes))
    chosen = fit.choose_options(val_features)
    strategies = {
        "network (no review)": np.zeros(len(val), int),
        "with the review": chosen,
        "oracle over the network and the routes": val_errors.argmin(axis=1),
    }
    labels = [c.label for c in protocol.QUALITY_CONDITIONS] + ["all"]
    table = markdown_table(
        ["strategy", *labels],
        [
            [name, *(score(val, c, best, len(routes), routed).get(k, "") for k in labels)]
            for name, c in strategies.items()
        ],
    )
    names = ["network", *(f"σ{s:g} ×{p}" for s, p in routes)]
    taken = [
        f"{r[0]} {protocol.NoiseCondition(r[1], r[2]).label if r[1] != 'clean' else 'clean'}"
        f": {names[c]} ({val_errors[i, 0]:.2f} → {val_errors[i, c]:.2f}°)"
        for i, (r, c) in enumerate(zip(val, chosen, strict=True))
        if c
    ]
    clean = [i for i, r in enumerate(val) if r[1] == "clean"]
    cv = markdown_table(
        ["neighbours", "cross-validated regret (over the best option)"],
        [
            [f"{k}" + (" (chosen)" if k == fit.neighbours else ""), f"{v:.4f}"]
            for k, v in fit.cv_regret.items()
        ],
    )
    _, train_errors = calibrate.review_arrays(train, len(routes))
    train_note = (
        f"{len(train)} training cases where the learned choice runs the network "
        f"({len({r[0] for r in train})} meshes); regret: geometric mean of the chosen "
        "option's error over the best option's. Always the network: "
        f"{calibrate.regret_of(train_errors, np.zeros(len(train), int)):.4f}."
    )
    clean_note = (
        f"{sum(1 for i in clean if chosen[i])} of {len(clean)} clean validation crops take a "
        "route; their mean normal error from the clean surface: network "
        f"{val_errors[clean, 0].mean():.2f}°, with the review "
        f"{val_errors[clean, chosen[clean]].mean():.2f}°."
    )
    write_report(
        args.out_dir / f"{args.name}.md",
        title="The review after the network: learned on the training split, scored on validation",
        env={**environment(), "wall time (s)": f"{time.perf_counter() - start:.0f}"},
        intro=(
            "Cells: mean normal error (°) / per-shape geometric mean of DMD-Net over the best "
            "other library method (`sota_lite.csv`) / share of meshes best or within 5 %, on "
            "the validation crops and draws of `make sota-lite`. The first stage is the "
            "weights' learned choice; the cases it routes (the review never sees them) "
            "enter every row with their `sota_lite.csv` error."
        ),
        sections=[
            ("Validation", table),
            ("Cases the review routes (validation)", "\n".join(f"- {t}" for t in taken) or "none"),
            ("Clean validation crops", clean_note),
            ("Fit (training split)", cv + "\n\n" + train_note),
        ],
        weights=args.weights or BUNDLED,
    )
    print((args.out_dir / f"{args.name}.md").read_text())
    if args.out:
        meta = {**bundle.meta, "review_learned_by": "benchmarks/quality/review_learn.py"}
        save_weights(
            args.out,
            bundle.params,
            bundle.config,
            meta,
            policy=policy.replace(**fit.policy_fields()),
            overwrite=args.force,
        )
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
