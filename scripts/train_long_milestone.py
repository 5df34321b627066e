"""Scores a milestone of the long run against the bundled weights, per shape, and decides.

A milestone (`dmd_jax.long_run.keep_milestone`: the run's weights at a multiple of 10,000
steps, exported with the bundled model's policy by `scripts/train_long_milestone.sh`) and
the bundled weights are both run, in this one process (the same code for both), on:

* the validation split (`sota_lite.py --sets val`) under every condition family of the
  quality benchmarks: Gaussian 0.1 / 0.2 / 0.3 / 0.6 and impulse 0.6 (cropped to 15,000
  faces, the other methods' rows reused from `benchmarks/results/sota_lite.csv`), scanner
  noise 0.3 / 0.5 / 0.8 and simulated scans 0.15 / 0.5 (cropped to 5,000 faces, rows
  reused from `benchmarks/results/sota_lite_scan.csv`), as `controller_val.md` ran them.
  The stress family has no validation variant (the run trains on its shapes), so it is
  not a family here;
* clean meshes, as `benchmarks/quality/no_harm.py` runs them (every shared mesh, the
  stress shapes and a noise-free scan of each shared mesh): the mean face-normal change,
  with CNR, BNF and Taubin run once for the best-other ratio.

Per condition and family: the geometric mean over meshes of milestone / bundled (errors
below 0.1° count as 0.1°), meshes better / worse by more than 2 %, the worst, and each
against the best other method. The rule (issue 62, fixed before any milestone was
scored): bundle when the milestone is better per shape in every family (geometric mean of
milestone / bundled below 1 over the family's meshes and levels) and no worse on clean
meshes (that geometric mean at most 1.02 in each clean set). Writes `<out>/milestone.md`
and the CSVs beside it; `--append` adds the section to a report.

    python scripts/train_long_milestone.py --weights M.msgpack --step 10000 \\
        --out runs/long/ft/milestones/step_010000/score --append benchmarks/results/train_long.md
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FLOOR = 0.1  # degrees: errors below count as this (sota_lite's per-shape tables)
BAND = 0.02  # a mesh is better / worse when the ratio leaves 1 by more than this
CLEAN_TOLERANCE = 1.02  # "no worse on clean": milestone / bundled at most this per set
BUNDLED = ROOT / "dmd_jax" / "weights" / "dmd_small.msgpack"
# (conditions, max faces, CSV of the other methods' rows): the two reports' splits.
NOISY_RUNS = {
    "noise": (
        ("0.1", "0.2", "0.3", "0.6", "impulse:0.6"),
        15000,
        ROOT / "benchmarks/results/sota_lite.csv",
    ),
    "scan": (
        ("scanner:0.3", "scanner:0.5", "scanner:0.8", "scan:0.15", "scan:0.5"),
        5000,
        ROOT / "benchmarks/results/sota_lite_scan.csv",
    ),
}
FAMILIES = ("gaussian", "impulse", "scanner", "scan")
NOT_COMPARED = {"noisy", "dmd", "dmd_x2", "meshlab_taubin", "meshlab_two_step"}
CLEAN_OTHERS = ("cnr", "bnf", "taubin")


def geomean(x) -> float:
    return float(np.exp(np.mean(np.log(np.asarray(x, np.float64)))))


def read_rows(path: Path) -> dict:
    """`{(noise, level): {mesh: {method: normal_deg}}}` of a sota-lite CSV's val rows."""
    out: dict = defaultdict(lambda: defaultdict(dict))
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            if r["set"] == "val":
                out[(r["noise"], float(r["level"]))][r["mesh"]][r["method"]] = float(
                    r["normal_deg"]
                )
    return out


def compare(old: dict, new: dict) -> list[dict]:
    """Per condition: the per-mesh milestone / bundled ratios and each run's ratios to the
    best other method of its report (`{cond, meshes, ratio, old_other, new_other}`)."""
    out = []
    for cond in sorted(new, key=lambda c: (FAMILIES.index(c[0]), c[1])):
        meshes = sorted(m for m in new[cond] if "dmd" in new[cond][m] and "dmd" in old[cond][m])
        if not meshes:
            continue

        def to_other(report, cond=cond, meshes=meshes):
            return [
                max(report[cond][m]["dmd"], FLOOR)
                / max(min(v for k, v in report[cond][m].items() if k not in NOT_COMPARED), FLOOR)
                for m in meshes
            ]

        out.append(
            {
                "cond": cond,
                "meshes": meshes,
                "ratio": [
                    max(new[cond][m]["dmd"], FLOOR) / max(old[cond][m]["dmd"], FLOOR)
                    for m in meshes
                ],
                "old_other": to_other(old),
                "new_other": to_other(new),
            }
        )
    return out


def summary_row(label: str, rows: list[dict]) -> list[str]:
    ratio = np.concatenate([r["ratio"] for r in rows])
    cases = [(m, r["cond"]) for r in rows for m in r["meshes"]]
    worst = int(np.argmax(ratio))
    mesh, cond = cases[worst]
    where = mesh if len(rows) == 1 else f"{mesh}, {cond[0]} {cond[1]:g}"
    return [
        label,
        str(len(ratio)),
        f"{geomean(ratio):.3f}",
        str(int(np.sum(ratio < 1 - BAND))),
        str(int(np.sum(ratio > 1 + BAND))),
        f"{ratio[worst]:.2f} ({where})",
        f"{geomean(np.concatenate([r['old_other'] for r in rows])):.3f}",
        f"{geomean(np.concatenate([r['new_other'] for r in rows])):.3f}",
    ]


def table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def score_noisy(tag: str, weights: Path, out: Path, *, max_meshes: int, echo) -> dict:
    """Runs sota-lite's val set for one weights file (`tag`: bundled or milestone) into
    `<out>/val_<part>_<tag>.csv` (an existing one is reused); returns `{part: path}`."""
    from benchmarks.quality import sota_lite
    from dmd_jax import protocol

    csvs = {}
    for part, (conditions, max_faces, reuse) in NOISY_RUNS.items():
        name = f"val_{part}_{tag}"
        csvs[part] = out / f"{name}.csv"
        if csvs[part].is_file():
            echo(f"reusing {csvs[part]} (delete it to rerun)")
            continue
        started = time.perf_counter()
        sota_lite.run(
            val_dir=protocol.validation_dir(),
            weights=str(weights),
            conditions=tuple(protocol.parse_condition(c) for c in conditions),
            name=name,
            out_dir=out,
            reuse_from=(reuse,),
            sets=("val",),
            max_faces=max_faces,
            max_meshes=max_meshes,
            echo=echo,
        )
        echo(f"{name}: {time.perf_counter() - started:.0f} s")
    return csvs


def by_family(old: dict, new: dict) -> dict:
    """`{family: [condition rows of compare]}` of the bundled and milestone CSVs."""
    out: dict = defaultdict(list)
    for part in NOISY_RUNS:
        for row in compare(read_rows(old[part]), read_rows(new[part])):
            out[row["cond"][0]].append(row)
    return out


def score_clean(tag: str, weights: Path, out: Path, *, max_meshes: int, echo) -> Path:
    """no_harm.py's clean meshes through one weights file (`tag`), and with the bundled
    weights also through the other methods (`CLEAN_OTHERS`); writes and returns
    `<out>/clean_<tag>.csv` (set, mesh, method, normal change, max move; reused)."""
    path = out / f"clean_{tag}.csv"
    if path.is_file():
        echo(f"reusing {path} (delete it to rerun)")
        return path
    import dmd_jax
    from benchmarks.quality import no_harm
    from dmd_jax import baselines, protocol
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.metrics import face_normal_errors_deg

    bundle = dmd_jax.load_weights(weights)
    methods = (tag, *CLEAN_OTHERS) if tag == "bundled" else (tag,)
    rows = []
    started = time.perf_counter()
    for mesh_set, name, v, f in no_harm.meshes(
        protocol.shared_meshes_dir(), no_harm.SETS, max_meshes
    ):
        h = mean_edge_length(v, f)
        for method in methods:
            if method == tag:
                moved = dmd_jax.denoise(v, f, bundle)
            else:
                moved = baselines.run_baseline(method, v, f)
            turn = float(np.mean(face_normal_errors_deg(moved, v, f)))
            move = float(np.abs(moved - v).max() / h)
            rows.append([mesh_set, name, method, f"{turn:.6g}", f"{move:.6g}"])
        done = "  ".join(f"{r[2]} {float(r[3]):.2f}°" for r in rows[-len(methods) :])
        echo(f"  clean {mesh_set} {name}: {done}")
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["set", "mesh", "method", "normal_change_deg", "max_move_edges"])
        w.writerows(rows)
    tmp.rename(path)
    echo(f"clean_{tag}: {time.perf_counter() - started:.0f} s")
    return path


def clean_rows(paths) -> tuple[list[list[str]], dict[str, float]]:
    """Per clean set: the summary row and `{set: geometric mean milestone / bundled}`."""
    turn: dict = defaultdict(lambda: defaultdict(dict))
    for path in paths:
        with open(path, newline="") as fh:
            for r in csv.DictReader(fh):
                turn[r["set"]][r["mesh"]][r["method"]] = float(r["normal_change_deg"])
    rows, means = [], {}
    for mesh_set, meshes in turn.items():
        names = sorted(meshes)
        ratio = np.array(
            [max(meshes[m]["milestone"], FLOOR) / max(meshes[m]["bundled"], FLOOR) for m in names]
        )

        def to_other(tag, meshes=meshes, names=names):
            return geomean(
                [
                    max(meshes[m][tag], FLOOR) / max(min(meshes[m][o] for o in CLEAN_OTHERS), FLOOR)
                    for m in names
                ]
            )

        worst = int(np.argmax(ratio))
        means[mesh_set] = geomean(ratio)
        rows.append(
            [
                f"clean {mesh_set}",
                str(len(names)),
                f"{means[mesh_set]:.3f}",
                str(int(np.sum(ratio < 1 - BAND))),
                str(int(np.sum(ratio > 1 + BAND))),
                f"{ratio[worst]:.2f} ({names[worst]})",
                f"{to_other('bundled'):.3f}",
                f"{to_other('milestone'):.3f}",
            ]
        )
    return rows, means


def _git(*args) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def _controller(weights: Path) -> bool:
    """Whether the weights' default call lets a stored smoothing controller choose
    (a milestone scored with the controller trained for its network)."""
    from dmd_jax.checkpoints import load_model

    bundle = load_model(weights)
    return bundle.controller is not None and bool(bundle.policy.controller)


def report(args, families: dict, clean_csvs, seconds: float, dirty: str) -> str:
    from benchmarks.common import file_sha256

    header = [
        "condition",
        "cases",
        "milestone / bundled (geometric mean)",
        "better",
        "worse",
        "worst (mesh)",
        "bundled / best other",
        "milestone / best other",
    ]
    per_condition, per_family, verdicts = [], [], {}
    for family in FAMILIES:
        rows = families.get(family, [])
        for r in rows:
            per_condition.append(summary_row(f"{family} {r['cond'][1]:g}", [r]))
        if rows:
            line = summary_row(f"**{family}**", rows)
            per_family.append(line)
            verdicts[family] = float(line[2]) < 1.0
    crow, cmeans = clean_rows(clean_csvs)
    clean_ok = all(v <= CLEAN_TOLERANCE for v in cmeans.values())
    missing = [f for f in FAMILIES if f not in verdicts]
    bundle = not missing and all(verdicts.values()) and clean_ok
    better = [f for f, ok in verdicts.items() if ok]
    worse = [f for f, ok in verdicts.items() if not ok]
    clean_text = ", ".join(f"{k} {v:.3f}" for k, v in cmeans.items())
    if bundle:
        decision = (
            f"**Decision by the rule: bundle.** Better per shape in every family "
            f"({', '.join(better)}) and no worse on clean meshes ({clean_text}; at most "
            f"{CLEAN_TOLERANCE})."
        )
    else:
        reasons = []
        if worse:
            reasons.append(f"not better per shape in {', '.join(worse)}")
        if missing:
            reasons.append(f"not scored in {', '.join(missing)}")
        if not clean_ok:
            reasons.append(f"worse on clean meshes ({clean_text}; the limit is {CLEAN_TOLERANCE})")
        decision = (
            "**Decision by the rule: not bundled** ("
            + "; ".join(reasons)
            + f"). Better per shape in: {', '.join(better) or 'no family'}; clean "
            f"milestone / bundled {clean_text}."
        )
    step = f"{args.step:,}"
    milestone = f"{args.milestone:,}" if args.milestone else step
    commit = _git("rev-parse", "--short=7", "HEAD")
    chooser = _controller(args.weights)
    lines = [
        f"### Milestone {milestone}{' with its controller' if chooser else ''} (step {step}): "
        f"{'bundle' if bundle else 'not bundled'}",
        "",
        f"Commit `{commit}`{' (uncommitted changes: ' + dirty + ')' if dirty else ''}; "
        f"milestone weights `{args.weights}` (SHA-256 `{file_sha256(args.weights)}`, the run's "
        f"step {step} exported with the bundled weights' policy"
        + (" and the smoothing controller trained for its network, switched on" if chooser else "")
        + ") against the bundled "
        f"`{args.baseline.name}` (SHA-256 `{file_sha256(args.baseline)}`), both run in one "
        f"process; {seconds / 60:.0f} min on one core. The 20 meshes of the validation split "
        "(cropped to 15,000 faces for Gaussian and impulse noise, 5,000 for scanner noise "
        "and scans, the other methods' rows reused from `sota_lite.csv` / "
        "`sota_lite_scan.csv`), and the clean meshes of `no_harm.py` (normal change; best "
        "other of CNR, BNF, Taubin). Ratios per case (a mesh at one level), geometric "
        "means, errors below 0.1° count as 0.1°; better / worse: by more than 2 %.",
        "",
        "```bash",
        args.command,
        "```",
        "",
        table(header, per_family + crow),
        "",
        "<details><summary>per condition</summary>",
        "",
        table(header, per_condition),
        "",
        "</details>",
        "",
        decision,
        "",
    ]
    if args.max_meshes:
        lines.insert(2, f"**A check on {args.max_meshes} mesh(es) per set, not a milestone.**\n")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, required=True, help="the milestone's weights")
    parser.add_argument("--baseline", type=Path, default=BUNDLED, help="default: bundled")
    parser.add_argument(
        "--step",
        type=int,
        default=0,
        help="the run's exact step (default: from milestone.json beside the weights)",
    )
    parser.add_argument("--milestone", type=int, default=0, help="the milestone it stands for")
    parser.add_argument("--out", type=Path, required=True, help="folder for reports and CSVs")
    parser.add_argument("--append", type=Path, help="markdown report to append the section to")
    parser.add_argument("--max-meshes", type=int, default=0, help="first N meshes (a check)")
    parser.add_argument("--command", default="", help="the command to quote in the report")
    parser.add_argument(
        "--wait",
        type=float,
        default=0.0,
        help="seconds to wait for the milestone's weights file after scoring the bundled "
        "weights (it may be exported while they run)",
    )
    args = parser.parse_args(argv)
    args.command = args.command or " ".join(["python", *sys.argv])
    args.out.mkdir(parents=True, exist_ok=True)
    status = subprocess.run(
        ["git", "status", "--porcelain", "--", "dmd_jax", "benchmarks"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout
    dirty = ", ".join(line[3:] for line in status.splitlines() if line.strip())
    started = time.perf_counter()

    def echo(line):
        print(line, flush=True)

    kw = {"max_meshes": args.max_meshes, "echo": echo}
    # The bundled weights first (with the other methods' clean rows), then the milestone,
    # in this one process: the same code scores both.
    old = score_noisy("bundled", args.baseline, args.out, **kw)
    clean_old = score_clean("bundled", args.baseline, args.out, **kw)
    waited = time.perf_counter()
    while not args.weights.is_file():
        if time.perf_counter() - waited > args.wait:
            print(f"error: no milestone weights at {args.weights}", file=sys.stderr)
            return 2
        time.sleep(10)
    waited = time.perf_counter() - waited
    if waited > 10:
        echo(f"waited {waited:.0f} s for {args.weights}")
    info = args.weights.parent / "milestone.json"
    if not args.step and info.is_file():
        kept = json.loads(info.read_text())
        args.step, args.milestone = int(kept["step"]), args.milestone or int(kept["milestone"])
    new = score_noisy("milestone", args.weights, args.out, **kw)
    clean_new = score_clean("milestone", args.weights, args.out, **kw)
    seconds = time.perf_counter() - started - waited
    text = report(args, by_family(old, new), (clean_old, clean_new), seconds, dirty)
    (args.out / "milestone.md").write_text(text)
    print(text)
    if args.append:
        old = args.append.read_text() if args.append.is_file() else ""
        args.append.write_text(old.rstrip("\n") + "\n\n" + text)
        print(f"appended to {args.append}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
