"""A learned pre-smoothing choice in place of the roughness rule (issue 29).

The roughness rule (`dmd_jax.presmooth.steps_for`) reads one number of the noisy mesh, its
median angle between adjacent face normals, and cannot tell noise from the curvature of a
coarse mesh: on the validation split it smooths coarse meshes at light noise (a knot and
a decimated knight end worse than their noisy input) and under-smooths heavy noise. The
learned choice reads eleven scale-free numbers (`presmooth.noise_features`: the angle
quartiles, how fast a few Laplacian steps lower them, how far they move the vertices) and
picks, from `calibrate.LEARN_GRID`, the count whose predicted regret is least
(`calibrate.fit_learned_presmooth`: the mean regret over its nearest training examples).

What this script does:

1. **measures** on the *training* split of `shared/meshes/train` (crops of
   `LEARN_MAX_FACES` faces; Gaussian noise along the normals at 0.05-0.6 edges, impulsive
   noise at 0.3 and 0.6 edges, and the clean mesh) the network's error after every count
   of the grid, with the weights' own pass rule (`presmooth_learn_train.csv`; about 40 min
   on one core for the 93 meshes);
2. **fits** the choice there, the number of neighbours by cross-validation over whole
   meshes;
3. **scores** it on the validation split from the rows of `policy_headroom.py` (the same
   grid, crops, conditions and seeds as `make sota-lite`, made with the same weights),
   beside the rule and the per-case oracle: mean normal error / per-shape geometric mean
   over the best other library method (`sota_lite.csv`) / share within 5 %; and counts
   the clean validation meshes it would smooth;
4. with `--out`, writes the weights with the learned choice in their policy.

```bash
python benchmarks/quality/presmooth_learn.py                  # measure, fit, report
python benchmarks/quality/presmooth_learn.py --reuse          # refit from the CSV
python benchmarks/quality/presmooth_learn.py --reuse --out dmd_jax/weights/dmd_small.msgpack
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
from dmd_jax import calibrate, comparison, protocol  # noqa: E402


def validation_rows(headroom_csv, grid):
    """`{case: (rule error, {count: error})}` from `policy_headroom.py`'s CSV, where a
    case is `(mesh, noise, level, seed)`; counts with the weights' pass rule."""
    cases: dict[tuple, dict] = {}
    with open(headroom_csv, newline="") as fh:
        for r in csv.DictReader(fh):
            key = (r["mesh"], r["noise"], float(r["level"]), int(r["seed"]))
            case = cases.setdefault(key, {"counts": {}})
            if r["passes"] != "rule":
                continue
            if r["presmooth"] == "rule":
                case["rule"] = float(r["normal_deg"])
            else:
                case["counts"][int(r["presmooth"])] = float(r["normal_deg"])
    missing = [k for k, c in cases.items() if "rule" not in c or set(grid) - set(c["counts"])]
    if missing:
        raise ValueError(
            f"{headroom_csv}: {len(missing)} case(s) lack the rule or a count of {list(grid)}, "
            f"e.g. {missing[0]}: run policy_headroom.py with these pre-smoothing counts"
        )
    return cases


def validation_noisy(cases) -> dict[tuple, tuple]:
    """`{case: (noisy, clean, faces)}`: each validation case's noisy crop, the noise remade
    from its seed, as `make sota-lite` draws it."""
    crops = {c.name: c for c in calibrate.validation_cases()}
    out = {}
    for mesh, kind, level, seed in cases:
        case = crops[mesh]
        noisy = protocol.condition_noise(
            case.clean, case.faces, protocol.NoiseCondition(kind, level), seed
        )
        out[(mesh, kind, level, seed)] = (noisy, case.clean, case.faces)
    return out


def validation_choices(noisy, policy) -> dict[tuple, tuple[int, int | None]]:
    """`{case: (steps, route)}` the policy gives each noisy validation crop
    (`policy.presmooth_plan`, as `denoise` runs it)."""
    from dmd_jax.policy import presmooth_plan

    out = {}
    for key, (v, _, faces) in noisy.items():
        plan = presmooth_plan(policy, v, faces, None)
        out[key] = (plan.steps, plan.route)
    return out


def route_table(path, keys, routes, compute, reuse: bool) -> dict[tuple, list[float]]:
    """`{case: [error of each route]}` read from `path` (columns: the case, then one per
    route) with `reuse` where it exists, else measured by `compute(key)` and written (the
    routes run on the host in seconds a case, so `--reuse` measures a missing table)."""
    names = [f"route_{s:g}_{p}" for s, p in routes]
    header = ("mesh", "noise", "level", "seed", *names)
    if reuse and Path(path).exists():
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            if tuple(reader.fieldnames or ()) != header:
                raise ValueError(f"{path}: expected the columns {list(header)}")
            table = {
                (r["mesh"], r["noise"], float(r["level"]), int(r["seed"])): [
                    float(r[n]) for n in names
                ]
                for r in reader
            }
        missing = [k for k in keys if k not in table]
        if missing:
            raise ValueError(f"{path} has no row for {missing[0]}: rerun without --reuse")
        return table
    table = {k: compute(k) for k in keys}
    write_csv(path, header, [[*k, *table[k]] for k in keys])
    return table


# Every count the rule may run: the per-coordinate validation rows are measured at each.
ISOTROPIC_GRID = tuple(range(21))


def isotropic_table(rows, learned, grid=ISOTROPIC_GRID) -> str:
    """Per-coordinate noise on the validation split (`learn_rows` of its crops at every
    count of `grid`, which `make sota-lite` does not have): mean error and regret of the
    rule, the learned choice (`policy.presmooth_plan`) and the oracle over `grid`."""
    from dmd_jax.policy import presmooth_plan

    crops = {c.name: c for c in calibrate.validation_cases(max_faces=calibrate.LEARN_MAX_FACES)}
    _, errors = calibrate._split_rows(rows, grid)
    routes = list(zip(learned.route_sigmas, learned.route_passes, strict=True))
    chosen_rule, chosen_learned = [], []
    for r in rows:
        case = crops[r[0]]
        noisy = protocol.benchmark_noise(case.clean, case.faces, r[2], r[3], "isotropic")
        plan = presmooth_plan(learned, noisy, case.faces, None)
        rule = presmooth_plan(learned.with_presmooth_rule(), noisy, case.faces, None).steps
        if plan.route is not None:
            # A route is no count of the grid: its error replaces the chosen cell's.
            s, p = routes[plan.route]
            errors_route = calibrate.route_errors(noisy, case.clean, case.faces, [(s, p)])[0]
            chosen_learned.append(("route", errors_route))
            chosen_rule.append(grid.index(rule))
            continue
        if plan.steps not in grid or rule not in grid:
            raise ValueError(f"{r[0]} isotropic {r[2]:g}: a count outside {grid}")
        chosen_learned.append(grid.index(plan.steps))
        chosen_rule.append(grid.index(rule))
    out = []
    for level in sorted({r[2] for r in rows}):
        sel = np.array([r[2] == level for r in rows])
        cells = [f"isotropic {level:g}", int(sel.sum())]
        e = errors[sel]
        for chosen in (chosen_rule, chosen_learned, list(errors.argmin(axis=1))):
            picked = np.array(
                [c[1] if isinstance(c, tuple) else errors[i, c] for i, c in enumerate(chosen)]
            )[sel]
            regret = np.exp(np.mean(np.log(picked / e.min(axis=1))))
            cells.append(f"{picked.mean():.2f} / {regret:.3f}")
        out.append(cells)
    return markdown_table(["condition", "meshes", "rule", "learned choice", "oracle"], out)


def score_table(strategies: dict[str, dict], best: dict[tuple, float]) -> str:
    """Per strategy and condition: mean error / geometric-mean ratio / share within 5 %."""
    cases = sorted(next(iter(strategies.values())))
    conds = list(dict.fromkeys((c[1], c[2]) for c in cases))
    headers = ["choice", *(protocol.NoiseCondition(*c).label for c in conds), "all"]
    rows = []
    for name, errs in strategies.items():
        row = [name]
        for group in [*([c] for c in conds), conds]:
            chosen = [c for c in cases if (c[1], c[2]) in group]
            ratios = np.array([errs[c] / best[c] for c in chosen])
            row.append(
                f"{np.mean([errs[c] for c in chosen]):.2f} / "
                f"{np.exp(np.mean(np.log(ratios))):.3f} / "
                f"{np.mean(ratios <= comparison.WITHIN):.0%}".replace("%", " %")
            )
        rows.append(row)
    return markdown_table(headers, rows)


def counts_table(chosen: dict[tuple, tuple], rule_best: dict[tuple, tuple[int, int]]) -> str:
    """Per condition: the mean steps of the rule, of the learned choice (over the cases it
    gave the network) and of the oracle over counts; the cases routed past the network."""
    conds = list(dict.fromkeys((c[1], c[2]) for c in sorted(chosen)))
    rows = []
    for cond in conds:
        keys = [c for c in sorted(chosen) if (c[1], c[2]) == cond]
        net = [c for c in keys if chosen[c][1] is None]
        rows.append(
            [
                protocol.NoiseCondition(*cond).label,
                len(keys),
                f"{np.mean([rule_best[c][0] for c in keys]):.1f}",
                f"{np.mean([chosen[c][0] for c in net]):.1f}" if net else "-",
                f"{np.mean([rule_best[c][1] for c in keys]):.1f}",
                f"{sum(chosen[c][0] == rule_best[c][1] for c in net)} / {len(net)}",
                f"{len(keys) - len(net)}",
            ]
        )
    return markdown_table(
        [
            "condition",
            "meshes",
            "rule steps",
            "learned steps",
            "oracle steps",
            "learned = oracle",
            "routed",
        ],
        rows,
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, help="weights file (default: bundled)")
    parser.add_argument("--reuse", action="store_true", help="refit from the training CSV")
    parser.add_argument("--limit", type=int, help="measure only the first N training meshes")
    parser.add_argument(
        "--headroom",
        type=Path,
        default=RESULTS_DIR / "policy_headroom.csv",
        help="policy_headroom.py's validation rows, made with the same weights",
    )
    parser.add_argument("--reference", type=Path, default=RESULTS_DIR / "sota_lite.csv")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--name", default="presmooth_learn")
    parser.add_argument(
        "--routes",
        default=",".join(f"{s:g}:{p}" for s, p in calibrate.LEARN_ROUTES),
        help="network-free routes the choice may take, sigma:passes,... ('' for none; "
        "default: calibrate.LEARN_ROUTES)",
    )
    parser.add_argument("--out", type=Path, help="write the weights with the learned choice")
    parser.add_argument("--force", action="store_true", help="let --out replace a file")
    args = parser.parse_args(argv)

    import dmd_jax
    from dmd_jax.checkpoints import save_weights

    grid = calibrate.LEARN_GRID
    try:
        routes = [
            (float(item.split(":")[0]), int(item.split(":")[1]))
            for item in args.routes.split(",")
            if item.strip()
        ]
    except (ValueError, IndexError):
        parser.error(f"--routes: expected sigma:passes,..., got {args.routes!r}")
    train_csv = args.out_dir / f"{args.name}_train.csv"
    bundle = dmd_jax.load_weights(args.weights) if args.weights else dmd_jax.load_pretrained()
    # The rows are measured, and the choice written, over the roughness rule the weights
    # keep as their fallback (`--out` on weights that already learn it replaces the fit).
    bundle = bundle._replace(policy=bundle.policy.with_presmooth_rule())
    start = time.perf_counter()
    try:
        if args.reuse:
            rows = calibrate.read_learn_csv(train_csv, grid)
        else:
            cases = calibrate.training_cases()[: args.limit]
            rows = calibrate.learn_rows(cases, bundle, grid=grid, echo=print)
            write_csv(train_csv, calibrate.learn_header(grid), rows)
        train_keys = [(r[0], r[1], float(r[2]), int(r[3])) for r in rows]
        if routes:
            cases = {}

            def measure(key):
                if not cases:
                    cases.update({c.name: c for c in calibrate.training_cases()})
                case = cases[key[0]]
                cond = None if key[1] == "clean" else protocol.NoiseCondition(key[1], key[2])
                noisy = calibrate.learn_draw(case.name, case.clean, case.faces, cond)[3]
                return calibrate.route_errors(noisy, case.clean, case.faces, routes)

            route_train = route_table(
                args.out_dir / f"{args.name}_routes_train.csv",
                train_keys,
                routes,
                measure,
                args.reuse,
            )
        fit_counts = calibrate.fit_learned_presmooth(rows, grid)
        fit = (
            calibrate.fit_learned_presmooth(
                rows,
                grid,
                routes=routes,
                route_errors=[route_train[k] for k in train_keys],
            )
            if routes
            else fit_counts
        )
        iso_csv = args.out_dir / f"{args.name}_val_isotropic.csv"
        if args.reuse:
            iso_rows = calibrate.read_learn_csv(iso_csv, ISOTROPIC_GRID)
        else:
            iso_cases = calibrate.validation_cases(max_faces=calibrate.LEARN_MAX_FACES)
            iso_conds = [
                c
                for c in calibrate.LEARN_CONDITIONS
                if c is not None and c.kind == calibrate.ISOTROPIC
            ]
            iso_rows = calibrate.learn_rows(
                iso_cases, bundle, iso_conds, grid=ISOTROPIC_GRID, echo=print
            )
            write_csv(iso_csv, calibrate.learn_header(ISOTROPIC_GRID), iso_rows)
        val = validation_rows(args.headroom, grid)
        best = best_others(args.reference, "val")
        missing = [c for c in val if c not in best]
        if missing:
            raise ValueError(f"{args.reference} has no rival row for {missing[0]}")
    except (ValueError, FileNotFoundError) as exc:
        print(f"presmooth_learn: error: {exc}", file=sys.stderr)
        return 2
    keys = sorted(val)
    learned = bundle.policy.replace(**fit.policy_fields())
    counts_only = bundle.policy.replace(**fit_counts.policy_fields())
    noisy = validation_noisy(keys)
    picked = validation_choices(noisy, learned)
    picked_counts = validation_choices(noisy, counts_only)
    unmeasured = [
        k
        for k in keys
        for steps, route in (picked[k], picked_counts[k])
        if route is None and steps not in val[k]["counts"]
    ]
    if unmeasured:
        print(
            f"presmooth_learn: error: {len(unmeasured)} validation case(s) get a count "
            f"outside {list(grid)}, e.g. {unmeasured[0]}: {picked[unmeasured[0]]}",
            file=sys.stderr,
        )
        return 2
    route_val = {}
    if routes:
        route_val = route_table(
            args.out_dir / f"{args.name}_routes_val.csv",
            keys,
            routes,
            lambda k: calibrate.route_errors(*noisy[k], routes),
            args.reuse,
        )

    def error_of(k, choice):
        steps, route = choice
        return val[k]["counts"][steps] if route is None else route_val[k][route]

    oracle = {k: min(val[k]["counts"], key=val[k]["counts"].get) for k in keys}
    rule_steps = {}
    with open(args.headroom, newline="") as fh:
        for r in csv.DictReader(fh):
            key = (r["mesh"], r["noise"], float(r["level"]), int(r["seed"]))
            rule_steps[key] = int(r["rule_presmooth"])
    strategies = {
        "roughness rule": {k: val[k]["rule"] for k in keys},
        "learned choice of counts": {k: error_of(k, picked_counts[k]) for k in keys},
    }
    if routes:
        strategies["learned choice of counts and routes"] = {
            k: error_of(k, picked[k]) for k in keys
        }
    strategies["oracle over counts (ground truth, per case)"] = {
        k: val[k]["counts"][oracle[k]] for k in keys
    }
    if routes:
        strategies["oracle over counts and routes"] = {
            k: min(val[k]["counts"][oracle[k]], *route_val[k]) for k in keys
        }
    # Do no harm: the steps each clean validation crop would get.

    from dmd_jax.policy import presmooth_plan

    clean_plans = {
        c.name: presmooth_plan(learned, c.clean, c.faces, None)
        for c in calibrate.validation_cases()
    }
    clean_steps = {n: p.steps for n, p in clean_plans.items()}
    smoothed = {n: s for n, s in clean_steps.items() if s}
    clean_routed = sorted(n for n, p in clean_plans.items() if p.route is not None)
    train_features, train_errors = calibrate._split_rows(rows, grid)
    rule_index = [
        min(range(len(grid)), key=lambda i: abs(grid[i] - r[-len(grid) - 1])) for r in rows
    ]
    fit_table = markdown_table(
        ["neighbours", "counts: cross-validated regret (over the best count)"]
        + (["counts and routes: cross-validated regret (over the best option)"] if routes else []),
        [
            [
                f"{a:g}" + (" (chosen)" if a == fit.neighbours else ""),
                f"{v:.4f}",
                *([f"{fit.cv_regret[a]:.4f}"] if routes else []),
            ]
            for a, v in fit_counts.cv_regret.items()
        ],
    )
    train_note = (
        f"{len(rows)} training cases ({len({r[0] for r in rows})} meshes). Regret: the "
        "geometric mean over cases of the chosen option's error over the best count's "
        "(with routes: over the best option's). "
        "The rule's own regret on these cases (its steps rounded to the grid): "
        f"{calibrate.regret_of(train_errors, np.array(rule_index)):.4f}; the oracle's: 1."
    )
    if routes:
        train_all = np.concatenate(
            [train_errors, np.array([route_train[k] for k in train_keys])], axis=1
        )
        n_routed = int(np.sum(train_all.argmin(axis=1) >= len(grid)))
        # The counts-only choice's regret over the best option, comparable to the routes'.
        gap = float(np.exp(np.mean(np.log(train_errors.min(axis=1) / train_all.min(axis=1)))))
        train_note += (
            f" A route ({', '.join(learned.route_label(i) for i in range(len(routes)))}) "
            f"is the best option in {n_routed} of {len(rows)} training cases; over the best "
            f"option, the counts-only choice's cross-validated regret is "
            f"{fit_counts.cv_regret[fit_counts.neighbours] * gap:.4f} "
            f"({fit_counts.neighbours} neighbours)."
        )
    weights = args.weights or BUNDLED
    write_report(
        args.out_dir / f"{args.name}.md",
        title="A learned pre-smoothing choice (and route) against the roughness rule",
        env=environment() | {"weights": str(weights)},
        intro=(
            f"Fitted on the training split, counts {list(grid)}"
            + (
                ", routes past the network "
                + ", ".join(learned.route_label(i) for i in range(len(routes)))
                + " (`dmd_jax.routes`)"
                if routes
                else ""
            )
            + ", "
            f"{len(calibrate.LEARN_CONDITIONS)} conditions per mesh "
            f"(`dmd_jax.calibrate.LEARN_CONDITIONS`); scored on the validation split "
            f"({len({k[0] for k in keys})} meshes) from `{args.headroom.name}` and "
            f"`{args.reference.name}`. A cell is the mean normal error (°) / the geometric "
            "mean over meshes of DMD-Net's error over the best other library denoiser's / "
            "meshes where DMD-Net is best or within 5 %."
            + ("" if args.reuse else f" {time.perf_counter() - start:.0f} s.")
        ),
        sections=[
            ("Validation split", score_table(strategies, best)),
            (
                "Steps chosen on the validation split",
                counts_table(picked, {k: (rule_steps[k], oracle[k]) for k in keys}),
            ),
            (
                "Per-coordinate noise on the validation split",
                "Gaussian noise per coordinate, crops of "
                f"{calibrate.LEARN_MAX_FACES:,} faces (`{args.name}_val_isotropic.csv`); a "
                "cell is the mean normal error (°) / the regret (the chosen count's error "
                "over the best count's, geometric mean):\n\n" + isotropic_table(iso_rows, learned),
            ),
            (
                "Clean validation meshes",
                (
                    f"{len(smoothed)} of {len(clean_steps)} clean crops would get steps"
                    + (
                        ": " + ", ".join(f"{n} ({s})" for n, s in sorted(smoothed.items()))
                        if smoothed
                        else ""
                    )
                    + f"; {len(clean_routed)} would take a route"
                    + (": " + ", ".join(clean_routed) if clean_routed else "")
                    + "."
                ),
            ),
            ("Fit (training split)", train_note + "\n\n" + fit_table),
        ],
        weights=weights,
    )
    print(f"wrote {args.out_dir / (args.name + '.md')}")
    if args.out:
        policy = learned
        meta = {**bundle.meta, "presmooth_learned_by": "benchmarks/quality/presmooth_learn.py"}
        save_weights(
            args.out, bundle.params, bundle.config, meta, policy=policy, overwrite=args.force
        )
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
