"""How much could a better per-mesh policy buy? DMD-Net at every pre-smoothing and pass count.

The denoising policy (`dmd_jax.policy`) decides, per mesh, how many uniform Laplacian steps
run before the network and how many network passes run. Today two fitted rules decide
(roughness → pre-smoothing steps, pass tolerance); a learned policy would replace them.
This script measures the most any per-mesh policy could buy *with the same network*: for
every mesh of a set and every quality condition (`protocol.QUALITY_CONDITIONS`) it runs
the weights under their own policy, under each fixed pre-smoothing count (the policy's
pass rule) and under each fixed pass count (the policy's pre-smoothing), and reports per
condition:

* `policy`: the weights' own rules;
* `best constant`: the one setting that is best over every mesh and condition of the set
  together (what refitting a setting that reads nothing of the mesh could give);
* `oracle pre-smoothing`, `oracle passes`, `oracle both`: for each case the setting with
  the lowest error *against the ground truth*, which no policy can see. These bound from
  above what a learned (or fitted) per-mesh policy could reach with this network.

Each is given as the mean normal error (°), the geometric mean over meshes of DMD-Net's
error over the best other library denoiser's (read from a `sota_lite` CSV made with the
same protocol: the noise seeds must match) and the share of meshes where DMD-Net is best
or within 5 %. Run it on the validation split (the default): choices are made there.

```bash
python benchmarks/quality/policy_headroom.py                 # val split, bundled weights
python benchmarks/quality/policy_headroom.py --reuse         # tables again from the CSV
python benchmarks/quality/policy_headroom.py --weights run.msgpack --name headroom_run
```
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    best_others,
    environment,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax import comparison, protocol  # noqa: E402

PRESMOOTH = (0, 1, 2, 3, 4, 6, 8, 11)
PASSES = (1, 2, 3)
# A setting: (pre-smoothing steps or "rule", passes or "rule").
RULE = "rule"
CSV_HEADER = (
    "mesh",
    "noise",
    "level",
    "seed",
    "presmooth",
    "passes",
    "normal_deg",
    "rule_presmooth",
    "rule_passes",
)


def run_mesh(path, bundle, conditions, presmooth, passes, *, max_faces, echo=print):
    """The CSV rows of one mesh: every condition, the policy and each fixed setting."""
    import numpy as np

    from dmd_jax.inference import denoise
    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import mesh_metrics

    clean, faces = protocol.crop(*load_mesh(path), max_faces)
    rows = []
    for cond in conditions:
        seed = protocol.condition_seed(path.name, cond)
        noisy = protocol.condition_noise(clean, faces, cond, seed)
        start = time.perf_counter()
        v, info = denoise(noisy, faces, bundle, return_info=True)
        settings = [(None, None)] + [(p, None) for p in presmooth] + [(None, k) for k in passes]
        case = []
        for p, k in settings:
            if (p, k) != (None, None):
                v = denoise(noisy, faces, bundle, presmooth=p, iterations=k)
            err = mesh_metrics(np.asarray(v, np.float64), clean, faces)["normal_deg"]
            case.append(
                [
                    path.name,
                    cond.kind,
                    float(cond.level),
                    int(seed),
                    RULE if p is None else p,
                    RULE if k is None else k,
                    err,
                    info.presmooth_steps,
                    info.passes,
                ]
            )
        rows += case
        echo(
            f"  {path.name} {cond.label}: policy {case[0][6]:.2f}° "
            f"(presmooth {info.presmooth_steps}, {info.passes} passes), best fixed "
            f"{min(r[6] for r in case):.2f}°, {time.perf_counter() - start:.1f} s"
        )
    return rows


def read_rows(path) -> list[list]:
    """This script's CSV back as rows (numbers parsed, `rule` kept)."""

    def count(x):
        return x if x == RULE else int(x)

    with open(path) as fh:
        return [
            [
                r["mesh"],
                r["noise"],
                float(r["level"]),
                int(r["seed"]),
                count(r["presmooth"]),
                count(r["passes"]),
                float(r["normal_deg"]),
                int(r["rule_presmooth"]),
                int(r["rule_passes"]),
            ]
            for r in csv.DictReader(fh)
        ]


def _label(kind: str, level: float) -> str:
    return protocol.NoiseCondition(kind, level).label


def strategies(rows: Sequence[Sequence]) -> dict[str, dict[tuple, float]]:
    """`{strategy: {case: normal error}}` for the policy, the best constant and the oracles.

    A case is `(mesh, noise, level, seed)`. The best constant is the fixed setting with the
    lowest mean error over every case; the oracles pick per case.
    """
    by_case: dict[tuple, dict[tuple, float]] = {}
    for r in rows:
        by_case.setdefault(tuple(r[:4]), {})[(r[4], r[5])] = r[6]
    fixed = sorted({s for errs in by_case.values() for s in errs if s != (RULE, RULE)}, key=str)
    common = [s for s in fixed if all(s in errs for errs in by_case.values())]
    out = {"policy": {c: errs[(RULE, RULE)] for c, errs in by_case.items()}}
    if common:
        const = min(common, key=lambda s: sum(errs[s] for errs in by_case.values()))
        out[f"best constant {_setting(const)}"] = {c: e[const] for c, e in by_case.items()}
    out["oracle pre-smoothing"] = {
        c: min(e for (p, k), e in errs.items() if k == RULE) for c, errs in by_case.items()
    }
    out["oracle passes"] = {
        c: min(e for (p, k), e in errs.items() if p == RULE) for c, errs in by_case.items()
    }
    out["oracle both"] = {c: min(errs.values()) for c, errs in by_case.items()}
    return out


def _setting(s) -> str:
    p, k = s
    return f"(presmooth {p}, passes {k})"


def summary_table(results: Mapping[str, Mapping[tuple, float]], best: Mapping[tuple, float]):
    """Per strategy and condition: mean error / geometric-mean ratio / share within 5 %."""
    cases = sorted(next(iter(results.values())))
    missing = [c for c in cases if c not in best]
    if missing:
        raise ValueError(
            f"the reference CSV has no other denoiser's row for {len(missing)} case(s), e.g. "
            f"{missing[0]}: make it with the same meshes, conditions and protocol"
        )
    conds = list(dict.fromkeys((c[1], c[2]) for c in cases))
    headers = ["strategy", *(_label(*c) for c in conds), "all"]
    table = []
    for name, errs in results.items():
        row = [name]
        for group in [*([c] for c in conds), conds]:
            chosen = [c for c in cases if (c[1], c[2]) in group]
            ratios = [errs[c] / best[c] for c in chosen]
            mean = sum(errs[c] for c in chosen) / len(chosen)
            within = sum(r <= comparison.WITHIN for r in ratios) / len(ratios)
            row.append(
                f"{mean:.2f} / {comparison.geometric_mean(ratios):.3f} / {100 * within:.0f} %"
            )
        table.append(row)
    return markdown_table(headers, table)


def chosen_table(rows: Sequence[Sequence]) -> str:
    """Per condition: the policy's mean pre-smoothing and passes against the oracle's."""
    by_case: dict[tuple, list] = {}
    for r in rows:
        by_case.setdefault(tuple(r[:4]), []).append(r)
    conds = list(dict.fromkeys((c[1], c[2]) for c in by_case))
    out = []
    for cond in conds:
        group = [v for c, v in by_case.items() if (c[1], c[2]) == cond]
        rule_p = [v[0][7] for v in group]
        rule_k = [v[0][8] for v in group]
        best_p = [min((r for r in v if r[5] == RULE), key=lambda r: r[6]) for v in group]
        best_p = [r[7] if r[4] == RULE else r[4] for r in best_p]
        best_k = [min((r for r in v if r[4] == RULE), key=lambda r: r[6]) for v in group]
        best_k = [r[8] if r[5] == RULE else r[5] for r in best_k]
        agree = sum(a == b for a, b in zip(rule_p, best_p, strict=True))
        out.append(
            [
                _label(*cond),
                len(group),
                f"{sum(rule_p) / len(group):.1f}",
                f"{sum(best_p) / len(group):.1f}",
                f"{agree} / {len(group)}",
                f"{sum(rule_k) / len(group):.1f}",
                f"{sum(best_k) / len(group):.1f}",
            ]
        )
    headers = [
        "condition",
        "meshes",
        "policy pre-smoothing",
        "oracle pre-smoothing",
        "same count",
        "policy passes",
        "oracle passes",
    ]
    return markdown_table(headers, out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", default="val", choices=("val", "shared"), dest="mesh_set")
    p.add_argument("--meshes", type=Path, help="mesh folder (default: the set's own)")
    p.add_argument("--weights", type=Path, help="DMD-Net weights file (default: bundled)")
    p.add_argument(
        "--reference",
        type=Path,
        default=RESULTS_DIR / "sota_lite.csv",
        help="a sota_lite CSV with the other denoisers' rows for the same cases",
    )
    p.add_argument("--conditions", nargs="+", help="noise conditions (sota_lite's syntax)")
    p.add_argument("--presmooth", type=int, nargs="+", default=list(PRESMOOTH))
    p.add_argument("--passes", type=int, nargs="+", default=list(PASSES))
    p.add_argument("--max-faces", type=int, default=protocol.MAX_FACES)
    p.add_argument("--reuse", action="store_true", help="tables from an existing CSV, no runs")
    p.add_argument("--name", default="policy_headroom", help="report file stem")
    p.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = p.parse_args(argv)
    csv_path = args.out_dir / f"{args.name}.csv"
    try:
        conditions = (
            tuple(protocol.parse_condition(c) for c in args.conditions)
            if args.conditions
            else protocol.QUALITY_CONDITIONS
        )
        if not args.reference.is_file():
            raise FileNotFoundError(f"{args.reference}: no reference CSV (run sota_lite first)")
        best = best_others(args.reference, args.mesh_set)
        start = time.perf_counter()
        if args.reuse:
            if not csv_path.is_file():
                raise FileNotFoundError(f"{csv_path}: nothing to reuse")
            rows = read_rows(csv_path)
        else:
            import dmd_jax

            if args.meshes is not None:
                files = protocol.mesh_files(args.meshes)
            elif args.mesh_set == "val":
                files = protocol.validation_files()
            else:
                files = protocol.mesh_files()
            if not files:
                raise FileNotFoundError("no mesh files to run")
            if args.weights:
                bundle = dmd_jax.load_weights(args.weights)
            else:
                bundle = dmd_jax.load_pretrained()
            rows = []
            for path in files:
                rows += run_mesh(
                    path, bundle, conditions, args.presmooth, args.passes, max_faces=args.max_faces
                )
            write_csv(csv_path, CSV_HEADER, rows)
        results = strategies(rows)
        summary = summary_table(results, best)
    except (ValueError, FileNotFoundError) as exc:
        print(f"policy_headroom: error: {exc}", file=sys.stderr)
        return 2
    meshes = len({r[0] for r in rows})
    write_report(
        args.out_dir / f"{args.name}.md",
        title="What a per-mesh policy could buy: DMD-Net at every pre-smoothing and pass count",
        env=environment() | {"weights": str(args.weights or "bundled"), "set": args.mesh_set},
        intro=(
            f"Set `{args.mesh_set}` ({meshes} meshes, crops of at most {args.max_faces:,} faces), "
            f"pre-smoothing counts {sorted({r[4] for r in rows if r[4] != RULE})} (with the "
            f"policy's pass rule) and pass counts {sorted({r[5] for r in rows if r[5] != RULE})} "
            "(with the policy's pre-smoothing). A cell is the mean normal error (°) / the "
            "geometric mean over meshes of DMD-Net's error over the best other library "
            f"denoiser's (from `{args.reference.name}`) / meshes where DMD-Net is best or "
            "within 5 %. The oracles choose per case with the ground truth: no policy can do "
            "better with this network."
            + ("" if args.reuse else f" {time.perf_counter() - start:.0f} s.")
        ),
        sections=[
            ("Per condition", summary),
            ("Counts chosen: the policy against the oracle", chosen_table(rows)),
        ],
        weights=args.weights or BUNDLED,
    )
    print(f"wrote {args.out_dir / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
