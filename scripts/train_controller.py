"""Trains the smoothing controller on a built smoothing set and reports it.

    python -m dmd_jax.data.smoothing_set --out data/smoothing --examples 2000   # the set
    python scripts/train_controller.py data/smoothing --out runs/controller.npz \\
        --report benchmarks/results/controller.md

Examples are split by their source mesh (SHA-1 of `source:mesh`): 60 % train, 20 %
validation (chooses the width and weight decay), 20 % test (reported once). The report
gives, per split and per noise kind, the chosen option's error against the per-example
oracle of the grid and against today's default call (geometric means of ratios, worst),
and the share of the oracle's gain over the default it captures; fixed settings beside
it. Deterministic for a set and a seed.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
from pathlib import Path

import numpy as np

from dmd_jax import controller
from dmd_jax.data import smoothing_set

WIDTHS = (16, 32, 64)
DECAYS = (1e-4, 1e-3, 1e-2)
# How the MLP learns (`controller.fit`): a softmax policy over the expected relative
# regret, or a regression of each option's log relative regret (choice: least predicted).
OBJECTIVES = ("softmax", "regret")


def split_of(spec: dict) -> str:
    """`train`, `val` or `test` for an example, by its source mesh."""
    key = f"{spec['source']}:{spec['mesh']}".encode()
    u = int(hashlib.sha1(key).hexdigest()[:8], 16) / 2**32
    return "test" if u < 0.2 else "val" if u < 0.4 else "train"


def inputs(data: dict, first_pass: bool = False) -> np.ndarray:
    """The controller's statistics: the mesh's (`controller_features`), and with
    `first_pass` how much the first network pass changed it (a comparison only:
    `denoise` reads the mesh's statistics alone)."""
    if not first_pass:
        return data["features"]
    return np.concatenate([data["features"], data["first_pass"]], axis=1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--out", type=Path, required=True, help="controller params (.npz)")
    parser.add_argument("--report", type=Path, help="markdown report to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-whole",
        action="store_true",
        help="train and choose without the whole-mesh examples (an ablation; the test "
        "split's whole meshes are still reported)",
    )
    args = parser.parse_args(argv)

    data = smoothing_set.load(args.data)
    opts = controller.options(
        smoothing_set.PRESMOOTH_GRID, smoothing_set.UPDATES, smoothing_set.SEARCH_PASSES
    )
    errors = controller.option_errors(
        data["errors"],
        smoothing_set.PRESMOOTH_GRID,
        smoothing_set.UPDATES,
        smoothing_set.SEARCH_PASSES,
    )
    x = inputs(data)
    # What the controller reads of each mesh: its crops (one, the mesh, when it is small).
    xc, mc = data["crop_features"], data["crop_mask"]
    split = np.array([split_of(s) for s in data["specs"]])
    kinds = np.array([s["kind"] for s in data["specs"]])
    tri = np.array([s.get("triangulation", {"kind": "given"})["kind"] for s in data["specs"]])
    whole = np.array([bool(s.get("whole")) for s in data["specs"]])
    tr, va, te = (split == "train"), (split == "val"), (split == "test")
    if args.no_whole:
        tr, va = tr & ~whole, va & ~whole
    print(
        f"{len(x)} examples ({whole.sum()} whole meshes): train {tr.sum()}, val {va.sum()}, "
        f"test {te.sum()}"
    )

    def fit(rows, **kw):
        return controller.fit(xc[rows], errors[rows], opts, crop_mask=mc[rows], **kw)

    def choose_all(params, rows):
        return np.argmax(controller.crop_scores(params, xc[rows], mc[rows]), axis=1)

    best, best_score = None, np.inf
    grid = []
    for objective in OBJECTIVES:
        for width in WIDTHS:
            for decay in DECAYS:
                params = fit(tr, hidden=width, l2=decay, seed=args.seed, objective=objective)
                r = controller.evaluate(
                    choose_all(params, va), errors[va], data["default_error"][va]
                )
                grid.append((objective, width, decay, r))
                print(
                    f"{objective} width {width} decay {decay:g}: val to oracle {r['to_oracle']:.3f}"
                )
                if r["to_oracle"] < best_score:
                    best, best_score = (objective, width, decay), r["to_oracle"]
    objective, width, decay = best
    # Would the first pass's change, as a further statistic, choose better? (The mesh's
    # statistics read whole here: the first pass is one per mesh.)
    xf = inputs(data, first_pass=True)
    pf = controller.fit(
        xf[tr], errors[tr], opts, hidden=width, l2=decay, seed=args.seed, objective=objective
    )
    chosen = np.argmax(controller.scores(pf, xf[va]), axis=1)
    with_first = controller.evaluate(chosen, errors[va], data["default_error"][va])["to_oracle"]
    # Would the statistics read as computed (no log1p) choose better?
    pr = fit(tr, hidden=width, l2=decay, seed=args.seed, kind="identity", objective=objective)
    raw = controller.evaluate(choose_all(pr, va), errors[va], data["default_error"][va])
    params = fit(tr | va, hidden=width, l2=decay, seed=args.seed, objective=objective)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **{k: np.asarray(v) for k, v in params.to_dict().items()})

    # Fixed settings, chosen on train: the best single option, and a few named ones.
    mean_regret = controller.relative_regret(errors[tr]).mean(axis=0)
    fixed = {"best fixed (train)": int(np.argmin(mean_regret))}
    for name, o in (
        ("none", controller.Option(0, None, 0)),
        ("1 pass jacobi", controller.Option(0, "jacobi", 1)),
        ("4 passes solve", controller.Option(0, "solve", 4)),
    ):
        fixed[name] = opts.index(o)

    rows = []
    for name, mask in (
        ("test", te),
        *((f"test {k}", te & (kinds == k)) for k in sorted(set(kinds))),
        ("test, whole meshes", te & whole),
        ("test, small crops", te & ~whole),
        ("test, own triangulation", te & (tri == "given")),
        ("test, re-triangulated", te & (tri != "given")),
        *((f"test {t} triangulation", te & (tri == t)) for t in sorted(set(tri) - {"given"})),
    ):
        if not mask.any():
            continue
        d = data["default_error"][mask]
        r = controller.evaluate(choose_all(params, mask), errors[mask], d)
        fx = {
            k: controller.evaluate(np.full(mask.sum(), i), errors[mask], d)["to_oracle"]
            for k, i in fixed.items()
        }
        dflt = controller.geomean(
            (d + controller.REGRET_FLOOR_DEG) / (errors[mask].min(1) + controller.REGRET_FLOOR_DEG)
        )
        rows.append((name, int(mask.sum()), r, dflt, fx))

    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    lines = [
        "# The learned smoothing controller",
        "",
        f"Commit `{commit}`; set `{args.data}` ({len(x)} examples, "
        f"grid: pre-smoothing {smoothing_set.PRESMOOTH_GRID}, updates {smoothing_set.UPDATES}, "
        f"1-{smoothing_set.SEARCH_PASSES} passes, or none: {len(opts)} options); network: "
        + (
            "the bundled weights (`dmd_small.msgpack`)"
            if data["network"] == smoothing_set.BUNDLED_NETWORK
            else f"the weights of SHA-256 `{data['network']}` (the set searched again for "
            "them, `smoothing_set --network`)"
        )
        + ". Reproduce: "
        f"`python scripts/train_controller.py {args.data} --out {args.out} "
        f"--report {args.report}{' --no-whole' if args.no_whole else ''}`."
        + (
            " Trained and chosen without the whole-mesh examples (an ablation)."
            if args.no_whole
            else ""
        ),
        "",
        f"Chosen on validation: objective {objective}, width {width}, weight decay {decay:g} "
        f"(validation, chosen / oracle, objective/width/decay: "
        + ", ".join(f"{o}/{w}/{d:g}: {r['to_oracle']:.3f}" for o, w, d, r in grid)
        + f"); with the first pass's change as two more statistics {with_first:.3f} at that "
        "setting (not used: `denoise` reads the mesh's statistics alone); with the statistics "
        f"read as computed instead of `log1p` {raw['to_oracle']:.3f}. Errors floored at "
        f"{controller.REGRET_FLOOR_DEG}° in every ratio.",
        "",
        "Test split (source meshes never seen in training or selection), geometric means "
        "of per-example ratios of the mean face-normal error:",
        "",
        "| examples | n | controller / oracle | worst | controller / default | default / oracle "
        "| capture of the oracle's gain | " + " | ".join(f"{k} / oracle" for k in fixed) + " |",
        "|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(fixed),
    ]
    for name, n, r, dflt, fx in rows:
        lines.append(
            f"| {name} | {n} | {r['to_oracle']:.3f} | {r['worst_to_oracle']:.2f} | "
            f"{r['to_default']:.3f} | {dflt:.3f} | {r['capture']:.0%} | "
            + " | ".join(f"{v:.3f}" for v in fx.values())
            + " |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.report:
        args.report.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
