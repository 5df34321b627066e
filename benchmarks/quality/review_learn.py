"""The review after the network (`dmd_jax.review`): measured, fitted, scored (issue 29).

The learned pre-smoothing choice reads only the noisy mesh; under light noise it cannot
tell a CAD part whose flats the network blurs from a mesh the network denoises well. The
review reads the network's result beside the σ 0.2 route's and keeps it or takes a
route, and where it keeps it, keeps it or runs a cascade on it (a candidate field of the
network's result, `calibrate.REVIEW_CASCADES`); `calibrate.fit_review`: least mean regret
over the nearest training examples, for each of the two choices.

What this script does:

1. **measures** on the *training* split (the crops and draws of
   `presmooth_learn.py`, `calibrate.LEARN_CONDITIONS`), for every case where the weights'
   learned choice runs the network, the review's features and the normal error of the
   network's result, of each route and of each cascade (`review_learn_train.csv`; about
   25 min on two cores for the 95 meshes);
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
    choices_table,
    environment,
    markdown_table,
    routed_cases,
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


def rows_or_measure(path, reuse, measure, routes, cascades):
    """`path`'s rows with `reuse` where it exists, else `measure()`'s, written there."""
    if reuse and Path(path).exists():
        return calibrate.read_review_csv(path, routes, cascades)
    rows = measure()
    write_csv(path, calibrate.review_header(routes, cascades), rows)
    return rows


def cross_validated_choices(rows, n_routes, cascades, offered, folds=calibrate.LEARN_FOLDS):
    """`[n]` each training row's option (an index into the network, the routes and
    `offered`) as a review fitted without its mesh's fold chooses it."""
    names = sorted({r[0] for r in rows})
    fold = np.array([names.index(r[0]) % folds for r in rows])
    features, _ = calibrate.review_arrays(rows, 1 + n_routes + len(cascades))
    chosen = np.zeros(len(rows), int)
    for f in range(folds):
        fit = calibrate.fit_review(
            [r for r, k in zip(rows, fold, strict=True) if k != f],
            n_routes,
            cascades,
            offered=offered,
        )
        chosen[fold == f] = fit.choose_options(features[fold == f])
    return chosen


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
    parser.add_argument(
        "--offer",
        nargs="*",
        default=None,
        metavar="SIGMAxPASSES",
        help="the cascades the review may take, e.g. 0.2x16 (default: every measured one "
        "of calibrate.REVIEW_CASCADES; none given: no cascade)",
    )
    args = parser.parse_args(argv)
    cascades = list(calibrate.REVIEW_CASCADES)
    if args.offer is None:
        offered = cascades
    else:
        try:
            offered = [(float(c.split("x")[0]), int(c.split("x")[1])) for c in args.offer]
        except (ValueError, IndexError):
            parser.error(f"--offer takes SIGMAxPASSES pairs such as 0.2x16, got {args.offer}")

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
                calibrate.training_cases()[: args.limit], bundle, cascades=cascades, echo=print
            ),
            routes,
            cascades,
        )
        val = rows_or_measure(
            args.out_dir / f"{args.name}_val.csv",
            args.reuse,
            lambda: calibrate.review_rows(
                calibrate.validation_cases(),
                bundle,
                (*protocol.QUALITY_CONDITIONS, None),
                draw=sota_draw,
                cascades=cascades,
                echo=print,
            ),
            routes,
            cascades,
        )
        best = best_others(args.reference, "val")
        routed = routed_cases(args.reference, val, best)
        fit = calibrate.fit_review(train, len(routes), cascades, offered=offered)
        first_only = calibrate.fit_review(train, len(routes), cascades, offered=())
    except (ValueError, FileNotFoundError) as exc:
        print(f"review_learn: error: {exc}", file=sys.stderr)
        return 2
    n_options = 1 + len(routes) + len(cascades)
    val_features, val_errors = calibrate.review_arrays(val, n_options)
    # The offered options' columns: the network, the routes, the offered cascades.
    columns = np.array(
        [*range(1 + len(routes)), *(1 + len(routes) + cascades.index(c) for c in offered)]
    )
    chosen = columns[fit.choose_options(val_features)]
    rows_at = np.arange(len(val))
    strategies = {
        "network (no review)": val_errors[:, 0],
        "the review's first choice only (no cascade)": val_errors[
            rows_at, first_only.choose_options(val_features)
        ],
        "with the review": val_errors[rows_at, chosen],
        "oracle over the network and the routes": val_errors[:, : 1 + len(routes)].min(axis=1),
        "oracle over the offered options": val_errors[:, columns].min(axis=1),
    }
    table = choices_table(strategies, val, best, routed)
    names = [
        "network",
        *(f"σ{s:g} ×{p}" for s, p in routes),
        *(f"cascade σ{s:g} ×{p}" for s, p in cascades),
    ]
    taken = [
        f"{r[0]} {protocol.NoiseCondition(r[1], r[2]).label if r[1] != 'clean' else 'clean'}"
        f": {names[c]} ({val_errors[i, 0]:.2f} → {val_errors[i, c]:.2f}°)"
        for i, (r, c) in enumerate(zip(val, chosen, strict=True))
        if c
    ]
    clean = [i for i, r in enumerate(val) if r[1] == "clean"]
    second = fit.cascade_cv_regret or {}
    cv = markdown_table(
        [
            "neighbours",
            "first choice: cross-validated regret over its best option",
            "second choice (cascades)",
        ],
        [
            [
                f"{k}",
                f"{v:.4f}" + (" (chosen)" if k == fit.neighbours else ""),
                f"{second[k]:.4f}" + (" (chosen)" if k == fit.cascade_neighbours else "")
                if k in second
                else "",
            ]
            for k, v in fit.cv_regret.items()
        ],
    )
    train_features, train_errors = calibrate.review_arrays(train, n_options)
    train_errors = train_errors[:, columns]
    cv_first = cross_validated_choices(train, len(routes), cascades, ())
    cv_both = cross_validated_choices(train, len(routes), cascades, offered)
    train_note = (
        f"{len(train)} training cases where the learned choice runs the network "
        f"({len({r[0] for r in train})} meshes); regret: geometric mean of the chosen "
        "option's error over the best option's. Over every offered option (the network, "
        "the routes, the offered cascades), held-out meshes (the whole fit, neighbour "
        "counts included, repeated on the other folds): always the network "
        f"{calibrate.regret_of(train_errors, np.zeros(len(train), int)):.4f}, the first "
        f"choice only {calibrate.regret_of(train_errors, cv_first):.4f}, both choices "
        f"{calibrate.regret_of(train_errors, cv_both):.4f}."
    )
    clean_note = (
        f"{sum(1 for i in clean if chosen[i])} of {len(clean)} clean validation crops take a "
        "route or a cascade; their mean normal error from the clean surface: network "
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
