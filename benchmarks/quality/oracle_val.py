"""The smoothing controller's grid oracle on the real validation split.

For every mesh of the validation split (`sota_lite.py --sets val`: the same files,
crops, noise and seeds, so each noisy mesh is exactly the one of
`benchmarks/results/sota_lite.csv` / `sota_lite_scan.csv`) and every condition, the
search of the controller's training set (`dmd_jax.data.smoothing_set.pass_errors`:
pre-smoothing 0/3/8/20 Laplacian steps, then one run of 8 network passes with each
vertex update, which gives every pass count) scores all 68 options of the
controller's grid (`controller.options`). One CSV row per mesh and condition holds
every option's mean face-normal error, the oracle's best option and error, and the
option the controller of `--controller-weights` picks on that noisy mesh (as
`denoise` reads it: consistently wound, in its normalised frame). Each row is
appended when its search ends, and a rerun skips the cases the CSV holds (resumable).

The report (`--report`) sets the oracle beside today's default call and the best
other library method (both from the sota_lite CSVs) and beside the controller's own
`denoise` rows (`runs/ctrl/*.csv` of `controller_val.md`; where those lack a case, the
grid's error at the controller's option): per condition and shape against the best
other method, the controller's capture of the oracle's gain, and which options each
picks.

```bash
python benchmarks/quality/oracle_val.py --conditions 0.2 impulse:0.6 scanner:0.5 scan:0.5
python benchmarks/quality/oracle_val.py --report-only   # the report from the CSV as it is
python benchmarks/quality/oracle_val.py --bounds        # what each controller design could reach
```
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    file_sha256,
    markdown_table,
    provenance,
    write_text,
)
from dmd_jax import comparison, protocol  # noqa: E402

# Every condition of controller_val.md, Gaussian / impulse first as sota_lite.csv, then
# those of sota_lite_scan.csv (cropped to SCAN_MAX_FACES there).
ALL_CONDITIONS = (
    "0.1",
    "0.2",
    "0.3",
    "0.6",
    "impulse:0.6",
    "scanner:0.3",
    "scanner:0.5",
    "scanner:0.8",
    "scan:0.15",
    "scan:0.5",
)
# The brief's first four, run first when the whole grid does not fit the time.
FIRST_CONDITIONS = ("0.2", "impulse:0.6", "scanner:0.5", "scan:0.5")
SCAN_KINDS = ("scanner", "scan")
SCAN_MAX_FACES = 5_000  # sota_lite_scan.csv's --max-faces
DEFAULT_CSV = REPO / "runs" / "oracle" / "oracle_val.csv"
DEFAULT_REPORT = RESULTS_DIR / "controller_oracle_val.md"
DEFAULT_CONTROLLER = REPO / "runs" / "dmd_controller.msgpack"
SOTA_CSVS = (RESULTS_DIR / "sota_lite.csv", RESULTS_DIR / "sota_lite_scan.csv")
CTRL_CSVS = (REPO / "runs" / "ctrl" / "val_ctrl.csv", REPO / "runs" / "ctrl" / "val_ctrl_scan.csv")


def grid_options():
    from dmd_jax.controller import options
    from dmd_jax.data.smoothing_set import PRESMOOTH_GRID, SEARCH_PASSES, UPDATES

    return options(PRESMOOTH_GRID, UPDATES, SEARCH_PASSES)


HEAD = (
    "set",
    "mesh",
    "noise",
    "level",
    "seed",
    "n_vertex",
    "n_face",
    "noisy_deg",
    "held_vertices",
    "controller_option",
    "oracle_option",
    "oracle_deg",
    "seconds",
)


def header() -> list[str]:
    return [*HEAD, *(o.label for o in grid_options())]


def case_key(noise: str, level, mesh: str) -> tuple:
    return (noise, round(float(level), 6), mesh)


def read_rows(path) -> list[dict]:
    path = Path(path)
    if not path.is_file():
        return []
    with open(path) as fh:
        return list(csv.DictReader(fh))


def as_denoise_reads(noisy, faces):
    """`(x, f, held)`: a noisy mesh as `denoise` reads it (referenced vertices,
    consistently wound, in its normalised frame) and the vertices it holds where they
    are (`smoothing_set.held_vertices`)."""
    from dmd_jax.consistency import oriented_faces
    from dmd_jax.data.smoothing_set import held_vertices
    from dmd_jax.inference import _prenormalised, _referenced

    v, f = np.asarray(noisy, np.float64), np.asarray(faces)
    if _referenced(v, f) is not None:
        raise ValueError("a mesh with unreferenced vertices (not in the validation split)")
    f, _ = oriented_faces(f, v.shape[0])
    x, _, _ = _prenormalised(v)
    return x, f, held_vertices(v, f)


def run(
    conditions,
    *,
    out_csv=DEFAULT_CSV,
    controller_weights=DEFAULT_CONTROLLER,
    val_dir=None,
    max_meshes: int = 0,
    only=(),
    network_weights=None,
    echo=print,
) -> int:
    """Searches the grid for every validation mesh and condition the CSV lacks; returns
    how many cases it added (condition by condition, in the order given). The network
    searched is `network_weights` (default: the bundled one)."""
    from dmd_jax.checkpoints import load_model
    from dmd_jax.controller import decide, option_errors
    from dmd_jax.data.smoothing_set import (
        PRESMOOTH_GRID,
        SEARCH_PASSES,
        UPDATES,
        pass_errors,
    )
    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import face_normal_errors_deg

    files = protocol.validation_files(val_dir)
    if only:
        files = [p for p in files if p.name in only]
    if max_meshes:
        files = files[:max_meshes]
    network = load_model(network_weights)  # default: the bundled, as the default call's
    # No controller: the grid alone (`--repick` adds a controller's picks later).
    params = None if controller_weights is None else load_model(controller_weights).controller
    if controller_weights is not None and params is None:
        raise ValueError(f"{controller_weights}: holds no smoothing controller")
    opts = grid_options()
    if params is not None and tuple(params.options) != tuple(opts):
        raise ValueError("the controller's options are not the search grid's")
    out_csv = Path(out_csv)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    head = header()
    done = {case_key(r["noise"], r["level"], r["mesh"]) for r in read_rows(out_csv)}
    if out_csv.is_file() and out_csv.stat().st_size:
        with open(out_csv) as fh:
            if next(csv.reader(fh)) != head:
                raise ValueError(f"{out_csv}: another layout; move it away")
    else:
        with open(out_csv, "w", newline="") as fh:
            csv.writer(fh).writerow(head)
    meshes = {}
    added = 0
    for text in conditions:
        condition = protocol.parse_condition(text)
        max_faces = SCAN_MAX_FACES if condition.kind in SCAN_KINDS else protocol.MAX_FACES
        for path in files:
            if case_key(condition.kind, condition.level, path.name) in done:
                continue
            if (path, max_faces) not in meshes:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    clean, faces = load_mesh(path)
                meshes = {(path, max_faces): protocol.crop(clean, faces, max_faces)}
            clean, faces = meshes[(path, max_faces)]
            seed = protocol.condition_seed(path.name, condition)
            target, noisy, tri = protocol.condition_mesh(clean, faces, condition, seed)
            start = time.perf_counter()
            noisy_deg = float(np.mean(face_normal_errors_deg(noisy, target, tri)))
            x, oriented, held = as_denoise_reads(noisy, tri)
            # The search as `denoise` runs each option (held vertices put back).
            mesh_faces = oriented if held.any() else tri
            errors, _ = pass_errors(noisy, target, mesh_faces, network, held)
            row_errors = option_errors(errors[None], PRESMOOTH_GRID, UPDATES, SEARCH_PASSES)[0]
            best = int(np.argmin(row_errors))
            chosen = decide(params, x, oriented).option if params is not None else opts[best]
            seconds = time.perf_counter() - start
            row = [
                "val",
                path.name,
                condition.kind,
                float(condition.level),
                int(seed),
                len(target),
                len(tri),
                f"{noisy_deg:.6f}",
                int(held.sum()),
                chosen.label if params is not None else "",
                opts[best].label,
                f"{row_errors[best]:.6f}",
                f"{seconds:.1f}",
                *(f"{e:.6f}" for e in row_errors),
            ]
            with open(out_csv, "a", newline="") as fh:
                csv.writer(fh).writerow(row)
            added += 1
            echo(
                f"{condition.label} {path.name} ({len(tri)} faces): oracle "
                f"{opts[best].label} {row_errors[best]:.2f}°, controller "
                f"{chosen.label} {row_errors[opts.index(chosen)]:.2f}°, noisy "
                f"{noisy_deg:.2f}° ({seconds:.0f} s)"
            )
    return added


# ----------------------------------------------------------------------------- report


def method_errors(paths) -> dict[tuple, dict[str, float]]:
    """`{(noise, level, mesh): {method: normal_deg}}` of the val rows of CSV reports."""
    out: dict[tuple, dict[str, float]] = {}
    for p in paths:
        for r in read_rows(p):
            if r["set"] != "val":
                continue
            key = case_key(r.get("noise", "gaussian"), r["level"], r["mesh"])
            out.setdefault(key, {})[r["method"]] = float(r["normal_deg"])
    return out


# The targets per shape against the best other method (issue 63, "done when").
TARGETS = {"gaussian": 0.95, "impulse": 0.95, "scanner": 1.0, "scan": 1.0}
# The sota_lite CSVs' noisy rows were partly reused from earlier runs: an input whose
# error differs by more than this is listed in the checks.
NOISY_TOLERANCE_DEG = 0.01


class Case(NamedTuple):
    """One mesh under one condition, every figure the report reads."""

    cond: str
    mesh: str
    default: float  # today's default call (sota_lite CSV `dmd`)
    other: float  # the best other library method there
    controller: float  # the controller's `denoise` row (or the grid at its option)
    grid_controller: float  # the grid's error at the controller's option
    oracle: float
    chosen: int  # the controller's option (index into the grid); -1: the CSV holds no pick
    errors: np.ndarray  # [68] every option's error
    noisy_diff: float  # our input's error minus the CSV's
    held: int
    from_grid: bool  # no `denoise` row of the controller: its grid error


def _geo(x) -> float:
    return comparison.geometric_mean(list(x))


def _per_shape(cases, field) -> tuple[float, float, str]:
    """Geometric mean over cases of `field / best other` (floored as sota_lite's per
    shape), the worst ratio and its mesh."""
    floor = comparison.RATIO_FLOOR_DEG
    ratios = {(c.cond, c.mesh): max(getattr(c, field), floor) / max(c.other, floor) for c in cases}
    s = comparison.summarise_ratios(ratios)
    return s.geometric_mean, s.worst, s.worst_case


def _capture(cases) -> tuple[float, float]:
    """The controller's share of the oracle's gain over the default: on the geometric
    means of the per-mesh errors (degrees), and as `controller.evaluate` reads it."""
    from dmd_jax.controller import evaluate

    g_def, g_ctl, g_orc = (
        _geo(getattr(c, f) for c in cases) for f in ("default", "controller", "oracle")
    )
    plain = (g_def - g_ctl) / (g_def - g_orc) if g_def > g_orc else float("nan")
    log = evaluate(
        np.array([c.chosen for c in cases]),
        np.array([c.errors for c in cases]),
        np.array([c.default for c in cases]),
    )["capture"]
    return plain, log


def stored_cases(rows, val_dir=None):
    """`(row, condition, noisy, faces)` for each row of the oracle's CSV, its noisy mesh
    made again (each cropped clean mesh loaded once) and checked against the row's noisy
    error, so a pick scored on the row's grid is a pick on the mesh that was searched.

    Raises:
      ValueError: a row whose regenerated noisy mesh is not the one searched.
    """
    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import face_normal_errors_deg

    files = {p.name: p for p in protocol.validation_files(val_dir)}
    meshes = {}
    for r in rows:
        condition = protocol.NoiseCondition(r["noise"], float(r["level"]))
        max_faces = SCAN_MAX_FACES if condition.kind in SCAN_KINDS else protocol.MAX_FACES
        key = (r["mesh"], max_faces)
        if key not in meshes:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                clean, faces = load_mesh(files[r["mesh"]])
            meshes[key] = protocol.crop(clean, faces, max_faces)
        clean, faces = meshes[key]
        target, noisy, tri = protocol.condition_mesh(clean, faces, condition, int(r["seed"]))
        noisy_deg = float(np.mean(face_normal_errors_deg(noisy, target, tri)))
        if abs(noisy_deg - float(r["noisy_deg"])) > NOISY_TOLERANCE_DEG:
            raise ValueError(f"{r['mesh']} {condition.label}: not the noisy mesh searched")
        yield r, condition, noisy, tri


def repick(src_csv, out_csv, controller_weights, *, val_dir=None, echo=print) -> int:
    """Copies the oracle's CSV `src_csv` to `out_csv` with `controller_option` chosen by
    the controller of `controller_weights` on each case's noisy mesh (`stored_cases`):
    another controller scored on the same grid without searching again (the grid's error
    at an option is `denoise`'s within 1 %, the report's checks). Returns how many cases
    it wrote."""
    from dmd_jax.checkpoints import load_model
    from dmd_jax.controller import decide

    params = load_model(controller_weights).controller
    if params is None:
        raise ValueError(f"{controller_weights}: holds no smoothing controller")
    if tuple(params.options) != tuple(grid_options()):
        raise ValueError("the controller's options are not the search grid's")
    rows = read_rows(src_csv)
    if not rows:
        raise ValueError(f"{src_csv}: no case to repick")
    out = []
    for r, _, noisy, tri in stored_cases(sorted(rows, key=lambda r: r["mesh"]), val_dir):
        x, oriented, _ = as_denoise_reads(noisy, tri)
        out.append({**r, "controller_option": decide(params, x, oriented).option.label})
    out_csv = Path(out_csv)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    with open(out_csv, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=header())
        w.writeheader()
        w.writerows(out)
    echo(f"repicked {len(out)} cases with {controller_weights} into {out_csv}")
    return len(out)


def _rel(path) -> str:
    path = Path(path).resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def _parse(label: str):
    """`(presmooth, update, passes)` of an option label."""
    parts = label[1:].split("_")
    return (int(parts[0]), None, 0) if len(parts) == 1 else (int(parts[0]), parts[1], int(parts[2]))


def _order(k):
    return (0, k, "") if isinstance(k, int) else (1, 0, str(k))


def _counts(labels, field) -> str:
    c = Counter(field(_parse(x)) for x in labels)
    return ", ".join(f"{k}: {n}" for k, n in sorted(c.items(), key=lambda kv: _order(kv[0])))


def _passes_bin(o) -> str:
    k = o[2]
    return "0" if k == 0 else "1" if k == 1 else "2" if k == 2 else "3-4" if k <= 4 else "5-8"


def _update(o) -> str:
    return o[1] or "none"


def read_cases(
    out_csv=DEFAULT_CSV, ctrl_csvs=CTRL_CSVS, sota_csvs=SOTA_CSVS
) -> dict[str, list[Case]]:
    """`{condition label: [Case]}` of the oracle's CSV joined with the sota_lite CSVs
    `sota_csvs` (default, best other) and the controller's rows, conditions in
    `ALL_CONDITIONS` order, meshes by name; a case the sota_lite CSVs lack is left out.
    A grid searched without a controller (no pick in the CSV) gives cases whose
    controller fields are NaN and `chosen` -1."""
    rows = read_rows(out_csv)
    labels = [o.label for o in grid_options()]
    sota, ctrl = method_errors(sota_csvs), method_errors(ctrl_csvs)
    out: dict[str, list[Case]] = {protocol.parse_condition(c).label: [] for c in ALL_CONDITIONS}
    for r in sorted(rows, key=lambda r: r["mesh"]):
        key = case_key(r["noise"], r["level"], r["mesh"])
        errs = sota.get(key, {})
        rivals = [e for m, e in errs.items() if protocol.is_rival(m)]
        if "dmd" not in errs or not rivals:
            continue
        e = np.array([float(r[k]) for k in labels])
        i = labels.index(r["controller_option"]) if r["controller_option"] else -1
        picked = float(e[i]) if i >= 0 else np.nan
        mine = ctrl.get(key, {}).get("dmd")
        label = protocol.NoiseCondition(r["noise"], float(r["level"])).label
        out.setdefault(label, []).append(
            Case(
                cond=label,
                mesh=r["mesh"],
                default=errs["dmd"],
                other=min(rivals),
                controller=picked if mine is None else mine,
                grid_controller=picked,
                oracle=float(r["oracle_deg"]),
                chosen=i,
                errors=e,
                noisy_diff=float(r["noisy_deg"]) - errs.get("noisy", np.nan),
                held=int(r["held_vertices"]),
                from_grid=mine is None,
            )
        )
    return {k: v for k, v in out.items() if v}


def report(
    out_csv=DEFAULT_CSV,
    path=DEFAULT_REPORT,
    controller_weights=DEFAULT_CONTROLLER,
    ctrl_csvs=CTRL_CSVS,
    network=None,
    source_csv=DEFAULT_CSV,
):
    """Writes the markdown report of the oracle's CSV (`path`); the controller's errors
    are its `denoise` rows of `ctrl_csvs` where they hold the case, else the grid's.
    `network`: the weights whose network the grid was searched for (`--network`), None
    for the bundled one; `source_csv`: the grid `--repick` read."""
    by_cond = read_cases(out_csv, ctrl_csvs)
    if not by_cond:
        raise ValueError(f"{out_csv}: no case to report")
    labels = [o.label for o in grid_options()]
    main, verdicts, picks, misses, checks = [], [], [], [], []
    groups = [*by_cond.items(), ("all run", [c for cs in by_cond.values() for c in cs])]
    for cond, cases in groups:
        d = _per_shape(cases, "default")
        c = _per_shape(cases, "controller")
        o = _per_shape(cases, "oracle")
        plain, log = _capture(cases)
        # The one option best for the condition's meshes together (least G).
        fixed = int(np.argmin(np.log(np.array([x.errors for x in cases])).mean(axis=0)))
        f = _per_shape([x._replace(oracle=float(x.errors[fixed])) for x in cases], "oracle")
        g = [_geo(getattr(x, f) for x in cases) for f in ("default", "controller", "oracle")]
        main.append(
            [
                cond,
                len(cases),
                f"{d[0]:.3f} / {d[1]:.2f} ({d[2][1]})",
                f"{c[0]:.3f} / {c[1]:.2f} ({c[2][1]})",
                f"{o[0]:.3f} / {o[1]:.2f} ({o[2][1]})",
                f"{f[0]:.3f} ({labels[fixed]})",
                " / ".join(f"{x:.2f}" for x in g),
                f"{100 * plain:.0f} %" if np.isfinite(plain) else "n/a",
                f"{100 * log:.0f} %" if np.isfinite(log) else "n/a",
                sum(x.default < 0.99 * x.oracle for x in cases),
            ]
        )
        if cond == "all run":
            continue
        target = TARGETS[protocol.parse_condition(cond).kind]
        meets = o[0] <= target
        either = _per_shape([x._replace(oracle=min(x.oracle, x.default)) for x in cases], "oracle")
        verdicts.append(
            [
                cond,
                f"≤ {target:.2f}",
                f"{d[0]:.3f}",
                f"{c[0]:.3f}" + (" (meets)" if c[0] <= target else ""),
                f"{o[0]:.3f}" + (" (meets)" if meets else " (misses)"),
                f"{either[0]:.3f}",
                "met already"
                if c[0] <= target
                else "the controller"
                if meets
                else "the network (the grid's best misses it too)",
            ]
        )
        orc = [labels[int(np.argmin(x.errors))] for x in cases]
        ctl = [labels[x.chosen] for x in cases]
        same = sum(a == b for a, b in zip(orc, ctl, strict=True))
        for who, lab in (("oracle", orc), ("controller", ctl)):
            picks.append(
                [
                    cond if who == "oracle" else "",
                    who,
                    _counts(lab, lambda opt: opt[0]),
                    _counts(lab, _passes_bin),
                    _counts(lab, _update),
                    same if who == "oracle" else "",
                ]
            )
        for x in sorted(cases, key=lambda x: x.grid_controller / x.oracle, reverse=True)[:3]:
            if x.grid_controller / x.oracle < 1.05:
                continue
            misses.append(
                [
                    cond,
                    x.mesh,
                    f"{labels[x.chosen]} {x.grid_controller:.2f}°",
                    f"{labels[int(np.argmin(x.errors))]} {x.oracle:.2f}°",
                    f"{x.default:.2f}°",
                    f"{x.other:.2f}°",
                    f"{x.grid_controller / x.oracle:.2f}",
                ]
            )
        diffs = {x.mesh: abs(x.controller - x.grid_controller) / x.controller for x in cases}
        off = [m for m, v in diffs.items() if v > 0.01]
        stale = [
            f"{x.mesh} ({x.noisy_diff:+.4f}°)"
            for x in cases
            if not abs(x.noisy_diff) <= NOISY_TOLERANCE_DEG
        ]
        held = [f"{x.mesh} ({x.held})" for x in cases if x.held]
        checks.append(
            f"{cond}: noisy input's error as the CSV's `noisy` row within "
            f"{NOISY_TOLERANCE_DEG:g}° on {len(cases) - len(stale)} of {len(cases)}"
            + (f" (not: {', '.join(stale)})" if stale else "")
            + "; the controller's `denoise` row equals the grid's error at its option "
            f"within 1 % on {len(cases) - len(off)}"
            + (f" (not: {', '.join(f'{m} {100 * diffs[m]:.0f} %' for m in off)})" if off else "")
            + (f"; held vertices: {', '.join(held)}" if held else "")
            + (
                f"; {sum(x.from_grid for x in cases)} controller errors from the grid"
                if any(x.from_grid for x in cases)
                else ""
            )
        )
    run_labels = list(by_cond)
    missing = [protocol.parse_condition(c).label for c in ALL_CONDITIONS]
    missing = [m for m in missing if m not in run_labels]
    n_meet = sum(v[4].endswith("(meets)") for v in verdicts)
    met = [v[0] for v in verdicts if v[4].endswith("(meets)")]
    missed = [f"{v[0]} {v[4].split()[0]}" for v in verdicts if not v[4].endswith("(meets)")]
    every = [c for cs in by_cond.values() for c in cs]
    o_all, c_all = _per_shape(every, "oracle"), _per_shape(every, "controller")
    capture_all = _capture(every)[0]
    no_pass = {
        cond: sum(labels[int(np.argmin(x.errors))].count("_") == 0 for x in cases)
        for cond, cases in by_cond.items()
    }
    summary = (
        f"The grid's per-mesh best meets them under {n_meet} of {len(verdicts)} "
        "conditions run"
        + (f" ({', '.join(met)})" if met else "")
        + (f"; it misses under {', '.join(missed)}" if missed else "")
        + ". Where it misses, no choice of pre-smoothing, passes and update from this "
        "grid meets the target with today's network: the network (or a grid without "
        "partial steps) is the limit there, whatever the controller learns; where it "
        "meets and the controller does not, the controller is. Over all "
        f"{len(every)} cases run: the oracle {o_all[0]:.3f} per shape (worst "
        f"{o_all[1]:.2f}, {o_all[2][1]} at {o_all[2][0]}; the issue wants none above "
        f"2.0), the controller {c_all[0]:.3f} (worst {c_all[1]:.2f}, {c_all[2][1]} at "
        f"{c_all[2][0]}); the controller captures {100 * capture_all:.0f} % of the "
        "oracle's gain over the default (the issue wants at least 60 %). The oracle's "
        "best option runs no network pass (none, or Laplacian pre-smoothing alone) on "
        + ", ".join(f"{n} of {len(by_cond[c])} at {c}" for c, n in no_pass.items() if n)
        + "."
    )
    parts = [
        "# The grid oracle of the smoothing controller on the validation split",
        "",
        provenance(controller_weights)
        + (
            " The network is the bundled one (`dmd_small.msgpack`, unchanged); the "
            "controller is the one in that file (not bundled)."
            if network is None
            else f" The grid was searched for the network of `{_rel(network)}` (SHA-256 "
            f"`{file_sha256(network)[:12]}`), not the bundled one; the controller is the one "
            "in the weights file above (not bundled); the `default` column stays the "
            "bundled network's default call (the sota_lite CSVs), so the capture is of "
            "the gain of this network's oracle over the bundled default."
        ),
        "",
        "The 20 meshes of the real validation split (`sota_lite.py --sets val`), cropped "
        f"to {protocol.MAX_FACES:,} faces (Gaussian, impulse) and {SCAN_MAX_FACES:,} "
        "(scanner, scans), with the noise and seeds of `sota_lite.csv` / "
        "`sota_lite_scan.csv`. The oracle picks, per mesh, the best of the controller's "
        "68 options (none; pre-smoothing 0/3/8/20 Laplacian steps alone or followed by "
        "1-8 network passes with the Jacobi or the solve update): "
        "`smoothing_set.pass_errors`, one 8-pass run per pre-smoothing level and update "
        "(where `denoise` holds vertices, `consistency.exact_vertices`: a CAD mesh's "
        "flat vertices under impulse noise, the same search holding them as `denoise` "
        "does). Default and best other method: the `dmd` rows and the best "
        "`protocol.is_rival` method of the sota_lite CSVs. Controller: its option read "
        "from the same noisy mesh as `denoise` reads it, and "
        + (
            "its error the grid's at that option (`--repick`: the grid of the search run "
            "for the first controller, its error at an option `denoise`'s within 1 %)"
            if not ctrl_csvs
            else "its error the `dmd` rows of `runs/ctrl/val_ctrl*.csv` "
            "(`controller_val.md`'s commands), or the grid's where those lack a case"
        )
        + ". Conditions run: "
        + ", ".join(run_labels)
        + (f"; not run: {', '.join(missing)}" if missing else "")
        + f". The per-mesh rows: `{_rel(out_csv)}` (not committed).",
        "",
        "```bash",
        "python benchmarks/quality/oracle_val.py "
        + (
            ""
            if network is None
            else f"--network {_rel(network)} --controller-weights none --csv {_rel(source_csv)} "
        )
        + "--conditions "
        + " ".join(c for c in ALL_CONDITIONS if protocol.parse_condition(c).label in run_labels)
        + (
            ""
            if ctrl_csvs
            else f"\npython benchmarks/quality/oracle_val.py --repick {_rel(source_csv)} "
            f"--csv {_rel(out_csv)} --controller-weights {_rel(controller_weights)}"
            + (
                ""
                if Path(out_csv).resolve() == DEFAULT_CSV.resolve()
                else f" --report {_rel(path)}"
            )
            + ("" if network is None else f" --network {_rel(network)}")
        ),
        "```",
        "",
        "## Can the targets be met over this grid?",
        "",
        "Issue 63's targets per shape against the best other method (geometric mean). "
        + summary
        + " `oracle or default`: per mesh the "
        "better of the grid's best and today's default call (which can run more passes "
        "or other pre-smoothing counts than the grid holds).",
        "",
        markdown_table(
            [
                "condition",
                "target",
                "default",
                "controller",
                "oracle",
                "oracle or default",
                "the limit",
            ],
            verdicts,
        ),
        "",
        "## Per shape against the best other method, and the controller's capture",
        "",
        "Default, controller and oracle per mesh over the best other library method: "
        "geometric mean / worst with its mesh (errors below "
        f"{comparison.RATIO_FLOOR_DEG:g}° count as {comparison.RATIO_FLOOR_DEG:g}°). "
        "G: the geometric mean over the meshes of the mean face-normal error (°). "
        "Capture = (G_default − G_controller) / (G_default − G_oracle): the share of the "
        "oracle's gain over the default call that the controller realises (negative: the "
        "controller is worse than the default). `capture (log, +0.5°)` is `controller.md`'s "
        "definition (`controller.evaluate`: differences of log geometric means of the "
        "errors plus 0.5°, the controller's error read from the grid), comparable with its "
        "67 % on the generated test split. `default < oracle`: meshes where the default "
        "call (passes while they move the mesh, pre-smoothing by its rule) beats every "
        "grid option by more than 1 %. `one option`: the "
        "single grid option of least geometric-mean error over the condition's meshes "
        "together (what knowing the condition, not the mesh, gives).",
        "",
        markdown_table(
            [
                "condition",
                "meshes",
                "default / best other",
                "controller / best other",
                "oracle / best other",
                "one option / best other",
                "G: default / controller / oracle (°)",
                "capture",
                "capture (log, +0.5°)",
                "default < oracle",
            ],
            main,
        ),
        "",
        "## What the oracle picks, against the controller",
        "",
        "Counts over the meshes: pre-smoothing steps, network passes, update (`none`: no "
        "network pass); `same`: meshes where the controller picks the oracle's option.",
        "",
        markdown_table(["condition", "who", "pre-smoothing", "passes", "update", "same"], picks),
        "",
        "## Where the controller errs most",
        "",
        "Per condition, up to three meshes where the controller's option is furthest from "
        "the oracle's (grid errors; shown when at least 5 % worse). Options: `pP` "
        "pre-smoothing alone (`p0`: the mesh as given), `pP_update_K`.",
        "",
        markdown_table(
            [
                "condition",
                "mesh",
                "controller",
                "oracle",
                "default",
                "best other",
                "controller / oracle",
            ],
            misses,
        ),
        "",
        "## Checks",
        "",
        "\n".join(f"- {c}" for c in checks),
        "",
    ]
    return write_text(Path(path), "\n".join(parts))


# Designs whose best per mesh `design_bounds` reads off the grid: the options each may
# choose from. A learned stop (issue 63's other design) runs today's network on the mesh
# as given and stops after some pass (or before the first): it chooses among these.
DESIGNS = (
    ("the grid oracle (all 68 options)", lambda o: True),
    ("a learned stop: none or 1-8 passes, either update", lambda o: o.presmooth == 0),
    ("a learned stop, Jacobi update only", lambda o: o.presmooth == 0 and o.update != "solve"),
    ("a learned stop, solve update only", lambda o: o.presmooth == 0 and o.update != "jacobi"),
)
DEFAULT_BOUNDS_REPORT = RESULTS_DIR / "controller_design_bounds.md"


def _design_table(out_csv, sota_csvs=SOTA_CSVS) -> tuple[list, Counter, int]:
    """The rows of one grid's design table, how many conditions' targets each design
    meets, and how many conditions the grid holds; the default call and the best other
    method are the `dmd` and best rival rows of `sota_csvs` (`read_cases`)."""
    by_cond = read_cases(out_csv, (), sota_csvs)
    if not by_cond:
        raise ValueError(f"{out_csv}: no case the sota_lite CSVs hold")
    subsets = [np.array([pick(o) for o in grid_options()]) for _, pick in DESIGNS]
    table, meets = [], Counter()
    every = [x for xs in by_cond.values() for x in xs]
    for cond, cases in [*by_cond.items(), ("all", every)]:
        cells = [_per_shape(cases, "default")[:2]] + [
            _per_shape([x._replace(oracle=float(x.errors[d].min())) for x in cases], "oracle")[:2]
            for d in subsets
        ]
        target = None if cond == "all" else TARGETS[protocol.parse_condition(cond).kind]
        if target is not None:
            for k, (g, _) in enumerate(cells[1:]):
                meets[k] += g <= target
        table.append(
            [
                cond,
                len(cases),
                "" if target is None else f"≤ {target:.2f}",
                *(
                    f"{g:.3f} / {w:.2f}" + (" ✓" if target is not None and g <= target else "")
                    for g, w in cells
                ),
            ]
        )
    return table, meets, len(by_cond)


def design_bounds(grids, path=DEFAULT_BOUNDS_REPORT):
    """Writes what a perfect chooser of each design in `DESIGNS` reaches on each grid,
    per condition and shape against the best other method: the bound on any controller
    of that design over that network (no controller needed).

    Args:
      grids: `[(weights, csv, rows)]`: the oracle CSV searched for each network
        (`weights` None: the bundled one), in the report's order, and the sota_lite
        CSVs whose `dmd` rows are that network's default call (empty: `SOTA_CSVS`, the
        bundled network's).
      path: the markdown report.
    """
    if not grids:
        raise ValueError("no grid to read")
    sections, commands = [], []
    for weights, out_csv, rows in grids:
        table, meets, n = _design_table(out_csv, tuple(rows) or SOTA_CSVS)
        name = "the bundled network" if weights is None else f"`{_rel(weights)}`"
        summary = "; ".join(f"{d}: {meets[k]} of {n}" for k, (d, _) in enumerate(DESIGNS))
        search = "--controller-weights none" + (
            "" if weights is None else f" --network {_rel(weights)}"
        )
        commands.append(f"python benchmarks/quality/oracle_val.py {search} --csv {_rel(out_csv)}")
        sections += [
            f"## The grid of {name}",
            "",
            (
                ""
                if weights is None
                else f"Weights SHA-256 `{file_sha256(weights)[:12]}`. The `default` column: "
                + (
                    "the bundled network's default call (the sota_lite CSVs). "
                    if not rows
                    else "this network's default call, the `dmd` rows of "
                    + ", ".join(f"`{_rel(r)}`" for r in rows)
                    + ". "
                )
            )
            + f"Grid `{_rel(out_csv)}` (not committed). Conditions whose target the "
            "column meets: " + summary + ".",
            "",
            markdown_table(
                ["condition", "meshes", "target", "default", *(d for d, _ in DESIGNS)],
                table,
            ),
            "",
        ]
    arg = " ".join(
        f"--csv {_rel(c)}"
        if w is None
        else f"--network-grid {_rel(w)}={_rel(c)}" + ("=" + ",".join(map(_rel, r)) if r else "")
        for w, c, r in grids
    )
    parts = [
        "# What each controller design could reach with the network it chooses for",
        "",
        provenance()
        + " 68 options per mesh and condition on the real validation split (the noise and "
        "seeds of the sota_lite CSVs, whose `dmd` rows, the default call, and best other "
        "method each grid is set against), searched by:",
        "",
        "```bash",
        *commands,
        f"python benchmarks/quality/oracle_val.py --bounds {arg}",
        "```",
        "",
        "Per condition, geometric mean / worst over the meshes of the error over the best "
        "other library method, for the default call and for a perfect chooser of each "
        "design: the best option per mesh among those the design may choose (✓: meets "
        "issue 63's target). A learned stop runs the network on the mesh as given and "
        "stops after the pass that leaves it best, or runs none; the grid oracle may also "
        "pre-smooth 3, 8 or 20 Laplacian steps first. No controller of a design over that "
        "network does better than its column.",
        "",
        *sections,
    ]
    return write_text(Path(path), "\n".join(parts))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--conditions",
        nargs="+",
        default=list(ALL_CONDITIONS),
        metavar="CONDITION",
        help="conditions to search, in this order (as sota_lite's --conditions)",
    )
    parser.add_argument("--csv", default=str(DEFAULT_CSV), help="the oracle's CSV (appended)")
    parser.add_argument(
        "--report",
        help=f"markdown report (default: {_rel(DEFAULT_REPORT)} for the default --csv; "
        "another --csv writes no report unless this names one, so that scoring another "
        "grid or controller never rewrites the committed report)",
    )
    parser.add_argument(
        "--controller-weights",
        default=str(DEFAULT_CONTROLLER),
        help="the controller whose picks the CSV records; 'none': the grid alone (then "
        "--repick a controller onto it), no report",
    )
    parser.add_argument("--max-meshes", type=int, default=0, help="first N meshes only")
    parser.add_argument("--only", nargs="+", default=[], help="these mesh files only")
    parser.add_argument("--report-only", action="store_true", help="no search: the report")
    parser.add_argument(
        "--bounds",
        nargs="?",
        const=str(DEFAULT_BOUNDS_REPORT),
        metavar="REPORT",
        help="no search: what a perfect chooser of each controller design reaches on --csv "
        f"(markdown report, default {_rel(DEFAULT_BOUNDS_REPORT)})",
    )
    parser.add_argument(
        "--network-grid",
        action="append",
        default=[],
        metavar="WEIGHTS=CSV[=ROWS,...]",
        help="with --bounds: also the grid searched for another network (--network), and "
        "the sota_lite CSVs whose `dmd` rows are its default call (a milestone's score/)",
    )
    parser.add_argument(
        "--repick",
        metavar="CSV",
        help="no search: copy this oracle CSV to --csv with the picks of --controller-weights "
        "(the controller's errors then come from the grid)",
    )
    parser.add_argument(
        "--network",
        help="search this weights file's network instead of the bundled one (a long run's "
        "milestone: how far a better network lifts the oracle); writes the CSV, no report. "
        "With --repick or --report-only: the network the CSV's grid was searched for",
    )
    args = parser.parse_args(argv)
    ctrl_csvs = CTRL_CSVS
    try:
        if args.bounds:
            grids = [(None, args.csv, ())]
            for spec in args.network_grid:
                parts = spec.split("=")
                if len(parts) not in (2, 3) or not all(parts):
                    raise ValueError(f"--network-grid {spec!r}: write WEIGHTS=CSV[=ROWS,...]")
                rows = parts[2].split(",") if len(parts) == 3 else []
                grids.append((parts[0], parts[1], rows))
            print(f"wrote {design_bounds(grids, args.bounds)}")
            return 0
        if args.repick:
            repick(args.repick, args.csv, args.controller_weights)
            ctrl_csvs = ()
        elif not args.report_only:
            no_controller = args.controller_weights == "none"
            run(
                args.conditions,
                out_csv=args.csv,
                controller_weights=None if no_controller else args.controller_weights,
                max_meshes=args.max_meshes,
                only=tuple(args.only),
                network_weights=args.network,
            )
        if args.network and not (args.repick or args.report_only):
            # A search: the report waits for a controller's picks (--repick).
            print(f"searched {args.network}'s grid into {args.csv}; no report")
            return 0
        if args.controller_weights == "none":
            print(f"searched the grid into {args.csv}; no controller, no report")
            return 0
        path = args.report
        if path is None and Path(args.csv).resolve() == DEFAULT_CSV.resolve():
            path = DEFAULT_REPORT
        if path is None:
            print(f"wrote {args.csv}; no report (--report names one)")
            return 0
        written = report(
            args.csv,
            path,
            args.controller_weights,
            ctrl_csvs,
            args.network,
            args.repick or DEFAULT_CSV,
        )
        print(f"wrote {written}")
    except (ValueError, FileNotFoundError) as exc:
        print(f"oracle_val: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
