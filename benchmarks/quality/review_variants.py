"""Other learners for the review's choice, scored on the committed review CSVs (issue 29).

The bundled review (`dmd_jax.review`, fitted by `review_learn.py`) chooses in two
stages by nearest neighbours over its eight output features. Between its validation
score (per shape 0.991 of the best other library method over all levels) and the oracle
over the same options (0.930) lies what a better learner could still buy. This refits,
on the training rows of `review_learn_train.csv` (no re-measuring: seconds), choices
that read more or fit differently, and scores each on `review_learn_val.csv` as
`review_learn.py` scores the review:

* one stage over all eight options (network, two routes, five cascades) by nearest
  neighbours, reading the output features, the first stage's noise features, or both;
* ridge regression of each option's log regret on the features (linear, and with squares
  of the standardised features), the option of least predicted regret taken.

```bash
python benchmarks/quality/review_variants.py
```
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    best_others,
    choices_table,
    environment,
    routed_cases,
    write_report,
)
from dmd_jax import calibrate  # noqa: E402


def _arrays(rows, n_options: int, read: str):
    """`(features, errors)`: the output features (`calibrate.review_arrays`), the first
    stage's noise features, or both."""
    from dmd_jax.presmooth import FEATURE_NAMES

    output, errors = calibrate.review_arrays(rows, n_options)
    if read == "output":
        return output, errors
    noise = np.array([r[4 : 4 + len(FEATURE_NAMES)] for r in rows], np.float64)
    return (noise if read == "noise" else np.concatenate([noise, output], 1)), errors


def _ridge_choice(x, errors, v, lam: float, squares: bool) -> np.ndarray:
    mu, sd = x.mean(0), x.std(0) + 1e-9

    def design(a):
        z = (a - mu) / sd
        parts = [z, np.ones((len(a), 1))] + ([z**2] if squares else [])
        return np.concatenate(parts, axis=1)

    z = design(x)
    regret = np.log(errors / errors.min(1, keepdims=True))
    w = np.linalg.solve(z.T @ z + lam * np.eye(z.shape[1]), z.T @ regret)
    return (design(v) @ w).argmin(1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", type=Path, default=RESULTS_DIR / "sota_lite.csv")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    import dmd_jax

    policy = dmd_jax.load_pretrained().policy
    routes = list(zip(policy.route_sigmas, policy.route_passes, strict=True))
    cascades = list(calibrate.REVIEW_CASCADES)
    n_options = 1 + len(routes) + len(cascades)
    train = calibrate.read_review_csv(RESULTS_DIR / "review_learn_train.csv", routes, cascades)
    val = calibrate.read_review_csv(RESULTS_DIR / "review_learn_val.csv", routes, cascades)
    best = best_others(args.reference, "val")
    routed = routed_cases(args.reference, val, best)
    at = np.arange(len(val))
    v, val_errors = calibrate.review_arrays(val, n_options)
    fit = calibrate.fit_review(train, len(routes), cascades)
    strategies = {
        "bundled review (two stages, nearest neighbours, output features)": val_errors[
            at, fit.choose_options(v)
        ],
        "oracle over the eight options": val_errors.min(1),
    }
    meshes = [r[0] for r in train]
    for read in ("output", "noise", "both"):
        x, errors = _arrays(train, n_options, read)
        v, _ = _arrays(val, n_options, read)
        table = calibrate._fit_nearest(
            x, errors, meshes, calibrate.LEARN_NEIGHBOURS, calibrate.LEARN_FOLDS
        )
        chosen = calibrate._choose(
            n_options,
            np.array(table.center),
            np.array(table.scale),
            np.array(table.examples),
            np.array(table.regrets),
            table.neighbours,
            v,
        )
        name = f"one stage, nearest neighbours ({table.neighbours}), {read} features"
        strategies[name] = val_errors[at, chosen]
    for read in ("output", "both"):
        x, errors = _arrays(train, n_options, read)
        v, _ = _arrays(val, n_options, read)
        for squares in (False, True):
            for lam in (1.0, 10.0, 100.0):
                name = f"ridge{' + squares' if squares else ''} λ {lam:g}, {read} features"
                strategies[name] = val_errors[at, _ridge_choice(x, errors, v, lam, squares)]
    path = write_report(
        args.out_dir / "review_variants.md",
        title="Other learners for the review's choice (validation split)",
        env=environment(),
        intro=__doc__.split("\n\n")[1] + "\n\n" + __doc__.split("\n\n")[2],
        sections=[
            (
                "Mean normal error / per-shape geometric mean over the best other library "
                "method / share within 5 %",
                choices_table(strategies, val, best, routed, first="choice"),
            )
        ],
    )
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
