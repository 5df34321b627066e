"""Result tables in the paper's layout, CSVs, bar plots and a README comparing orderings.

Everything here is computed from the `metrics.json` files of a results directory (the
runs listed in its `plan.json`); the only numbers written by hand are the paper's own
tables (`PAPER`), transcribed from `paper/dmd-net.tex` (appendix D, E and the noise
table; `tests/test_experiments.py` checks the transcription against the source).

This module writes: the markdown tables and verdict texts, the CSVs, each preset's
README and the results root's index. The numbers (records, means, intervals, verdicts)
come from `experiments.stats`, the figures from `experiments.plots`.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from experiments import studies as st
from experiments.ablations import ABLATIONS
from experiments.plots import write_plot
from experiments.stats import (
    AFFORDABLE_SEEDS,
    BETTER,
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    CLASSIC_LABELS,
    CONFIDENCE,
    CONTRADICTED,
    PAPER,
    PAPER_COLUMNS,
    POWER,
    REPRODUCED,
    ROTATION_COLUMNS,
    SPLITS,
    TRAIN_COLUMNS,
    UNDECIDED,
    WORSE,
    _best,
    _columns,
    _timing,
    compare_with_paper,
    interval_keys,
    load_records,
    study_intervals,
    study_rows,
)

# --------------------------------------------------------------------------------------
# Formatting
# --------------------------------------------------------------------------------------


def fmt(x: float | None, std: float | None = None) -> str:
    """3 decimals like the paper; scientific for huge values; `–` when missing."""
    if x is None:
        return "–"
    if not math.isfinite(x):
        return str(x)

    def one(v):
        return f"{v:.3e}" if abs(v) >= 1e5 else f"{v:.3f}"

    return one(x) if std is None else f"{one(x)} ± {one(std)}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def load_classic(out_dir) -> dict[str, dict]:
    """`evaluation.classic_references` of a sweep (`{}` when the sweep predates them)."""
    path = Path(out_dir) / "references.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def study_markdown(
    study: st.Study, rows: list[dict], reference: dict | None, classic: dict | None = None
) -> str:
    """The study as a markdown table in the paper's layout (best per column in bold).

    Training studies end with reference rows: the noisy input and each classic denoiser
    of `classic` (`load_classic`), on the same noisy test meshes.
    """
    cols = _columns(study)
    header = ["Model" if study.kind != st.NOISE else "Noise"]
    if study.key == "loss":
        header += ["λ_V", "λ_N", "λ_κ", "λ_C"]
    header += [label for _, _, label in cols]
    body = []
    bold_keys = {k for k, _, _ in cols if not k.startswith("reference/")}
    if study.kind == st.ROTATION:
        bold_keys = {k for k, _, _ in cols if k.startswith("re/")}
    best = {k: _best(rows, k) for k in bold_keys}
    for r in rows:
        cells = [r["row"] + ("" if r["status"] in ([], ["ok"]) else f" ({', '.join(r['status'])})")]
        if study.key == "loss":
            w = ABLATIONS["loss"][r["row"]]["loss"]
            cells += [f"{w[k]:g}" for k in ("vertex", "normal", "curvature", "chamfer")]
        for key, scale, _ in cols:
            mean, std = r["values"][key]
            text = fmt(None if mean is None else mean * scale, None if std is None else std * scale)
            if mean is not None and key in best and best[key] is not None and mean == best[key]:
                text = f"**{text}**"
            cells.append(text)
        body.append(cells)
    if reference is not None and study.kind == st.TRAIN:
        cells = ["*noisy input*"] + (["", "", "", ""] if study.key == "loss" else [])
        for key, scale, _ in cols:
            split, metric = key.split("/")
            v = reference.get(f"{split}/noisy_{metric}")
            cells.append(fmt(None if v is None else v * scale))
        body.append(cells)
        for method, values in (classic or {}).items():
            cells = [f"*{CLASSIC_LABELS.get(method, method)}*"]
            cells += ["", "", "", ""] if study.key == "loss" else []
            for key, scale, _ in cols:
                v = values.get(key)
                cells.append(fmt(None if v is None else v * scale))
            body.append(cells)
    return _table(header, body)


def paper_markdown(study: st.Study) -> str:
    """The paper's table for the study, same layout."""
    if study.key not in PAPER:
        return ""
    header = ["Model" if study.kind != st.NOISE else "Noise"]
    if study.kind == st.TRAIN:
        header += [label for _, _, label in TRAIN_COLUMNS]
    elif study.kind == st.NOISE:
        header += ["Vertex (×10⁻⁴) Loss", "Vertex Reference", "Normal (°) Loss", "Normal Reference"]
    else:
        header += [label for _, _, label in ROTATION_COLUMNS[:3]]
    body = [[name, *(fmt(v) for v in vals)] for name, vals in PAPER[study.key].items()]
    return _table(header, body)


# --------------------------------------------------------------------------------------
# Confidence intervals and verdicts
# --------------------------------------------------------------------------------------


MARK = {REPRODUCED: "✓", CONTRADICTED: "✗", UNDECIDED: "·", BETTER: "▼", WORSE: "▲"}


def _short(key: str) -> str:
    return SHORT.get(key, key)


def verdict_text(study: st.Study, intervals: list[dict]) -> str:
    """The study's verdict in one paragraph, derived from `study_intervals`."""
    if not intervals:
        return ""
    ref = study.reference
    n_s = min(iv["n_seeds"] for iv in intervals)
    n_m = min(iv["n_meshes"] for iv in intervals)
    head = (
        f"*{study.title}*, verdict ({CONFIDENCE:.0%} paired bootstrap intervals of each row "
        f"minus **{ref}**, {n_s} seed{'s' if n_s > 1 else ''} × {n_m} test meshes, "
        f"{BOOTSTRAP_RESAMPLES} resamples): "
    )

    def listing(kind):
        by_row: dict[str, list[str]] = {}
        for iv in intervals:
            if iv["verdict"] == kind:
                by_row.setdefault(iv["row"], []).append(_short(iv["column"]))
        return "; ".join(f"{r} ({', '.join(c)})" for r, c in by_row.items())

    with_paper = [iv for iv in intervals if iv["paper_sign"]]
    without = [iv for iv in intervals if not iv["paper_sign"]]
    parts = []
    if with_paper:
        n = len(with_paper)
        count = {k: sum(iv["verdict"] == k for iv in with_paper) for k in MARK}
        parts.append(
            f"of the paper's {n} orderings against {ref}, {count[REPRODUCED]} reproduced with "
            f"confidence, {count[CONTRADICTED]} contradicted with confidence, "
            f"{count[UNDECIDED]} undecided."
        )
        for kind, name in ((REPRODUCED, "Reproduced"), (CONTRADICTED, "Contradicted")):
            text = listing(kind) if count[kind] else ""
            if text:
                parts.append(f"{name}: {text}.")
    if without:
        n = len(without)
        count = {k: sum(iv["verdict"] == k for iv in without) for k in MARK}
        parts.append(
            f"{'Where the paper has no number, ' if with_paper else ''}of {n} (row, column) "
            f"differences from {ref}, {count[BETTER]} better with confidence, "
            f"{count[WORSE]} worse with confidence, {count[UNDECIDED]} undecided."
        )
        for kind, name in ((BETTER, "Better than " + ref), (WORSE, "Worse than " + ref)):
            text = listing(kind) if count[kind] else ""
            if text:
                parts.append(f"{name}: {text}.")
    return head + " ".join(parts) + "\n"


def detectability_text(study: st.Study, intervals: list[dict]) -> str:
    """What the study's sweep could have found, in one paragraph (`study_intervals`).

    The smallest detectable difference per column (median over the study's rows) and,
    for the paper's claimed differences scaled to our errors, how many are within reach
    of the seeds run, of `AFFORDABLE_SEEDS`, of more, or of no seed count at all.
    """
    ivs = [iv for iv in intervals if iv.get("mdd") is not None]
    if not ivs:
        return ""
    n_s = min(iv["n_seeds"] for iv in ivs)
    n_m = min(iv["n_meshes"] for iv in ivs)
    per_col = []
    for key, _, _ in interval_keys(study):
        values = [iv["mdd"] for iv in ivs if iv["column"] == key]
        if values:
            per_col.append(f"{_short(key)} {fmt(float(np.median(values)))}")
    text = (
        f"*{study.title}*, smallest detectable differences (found by a {CONFIDENCE:.0%} "
        f"interval with {POWER:.0%} power, from the seed-to-seed and mesh-to-mesh spread "
        f"of {n_s} seeds × {n_m} test meshes; median over the rows, table units): "
        f"{', '.join(per_col)}."
    )
    claims = [iv for iv in ivs if iv.get("seeds_needed") is not None]
    if claims:
        need = [iv["seeds_needed"] for iv in claims]
        now = sum(n <= iv["n_seeds"] for n, iv in zip(need, claims, strict=True))
        afford = sum(
            iv["n_seeds"] < n <= AFFORDABLE_SEEDS for n, iv in zip(need, claims, strict=True)
        )
        more = sum(AFFORDABLE_SEEDS < n < math.inf for n in need)
        never = sum(n == math.inf for n in need)
        finite = [n for n in need if n < math.inf]
        # The interval excludes the paper's own size of effect (in its direction).
        ruled_out = sum(
            (iv["high"] < iv["claim"]) if iv["claim"] > 0 else (iv["low"] > iv["claim"])
            for iv in claims
        )
        text += (
            f" The paper's {len(claims)} differences, each as a fraction of its reference "
            f"row applied to ours: {now} detectable with the {n_s} seeds run, {afford} with "
            f"at most {AFFORDABLE_SEEDS}, {more} only with more, {never} with no seed count "
            f"on these {n_m} test meshes (their mesh-to-mesh spread alone exceeds the "
            "difference)"
            + (f"; median seeds needed where finite: {int(np.median(finite))}" if finite else "")
            + f". {ruled_out} of {len(claims)} intervals exclude the paper's size of effect: "
            "a difference that large is ruled out on this recipe."
        )
    return text + "\n"


def detectability_markdown(study: st.Study, intervals: list[dict]) -> str:
    """Per (row, column): the detectable difference and the seeds the paper's claim needs."""
    ivs = [iv for iv in intervals if iv.get("mdd") is not None]
    if not ivs:
        return ""
    cols = [(k, label) for k, _, label in interval_keys(study)]
    cells: dict[tuple[str, str], str] = {}
    for iv in ivs:
        cell = fmt(iv["mdd"])
        if iv.get("seeds_needed") is not None:
            n = iv["seeds_needed"]
            cell += f" / {fmt(abs(iv['claim']))}: " + ("∞" if n == math.inf else f"{int(n)}")
        cells[(iv["row"], iv["column"])] = cell
    rows = [r for r in study.rows if any((r, k) in cells for k, _ in cols)]
    body = [[r, *(cells.get((r, k), "–") for k, _ in cols)] for r in rows]
    n_s = min(iv["n_seeds"] for iv in ivs)
    legend = (
        f"Detectable difference from **{study.reference}** with {n_s} seeds "
        f"({CONFIDENCE:.0%} two-sided, {POWER:.0%} power, table units); where the paper "
        "has both numbers, `/ claim: seeds`: the paper's difference scaled to our "
        "reference row and the seeds that would detect it with these test meshes (∞: no "
        "seed count would).\n\n"
    )
    return legend + _table(["Model", *(label for _, label in cols)], body)


def intervals_markdown(study: st.Study, intervals: list[dict]) -> str:
    """Table of the differences from the reference row with their intervals and marks."""
    if not intervals:
        return ""
    cols = [(k, label) for k, _, label in interval_keys(study)]
    cells: dict[tuple[str, str], str] = {}
    for iv in intervals:
        cells[(iv["row"], iv["column"])] = (
            f"{fmt(iv['diff'])} [{fmt(iv['low'])}, {fmt(iv['high'])}] {MARK[iv['verdict']]}"
        )
    rows = [r for r in study.rows if any((r, k) in cells for k, _ in cols)]
    body = [[r, *(cells.get((r, k), "–") for k, _ in cols)] for r in rows]
    legend = (
        f"Difference from **{study.reference}** (row − {study.reference}, table units; "
        f"negative = lower error), mean over seeds × meshes and its {CONFIDENCE:.0%} paired "
        f"bootstrap interval. ✓ the paper's ordering reproduced with confidence, ✗ "
        "contradicted with confidence, · undecided (the interval contains 0); where the "
        "paper has no number: ▼ better, ▲ worse with confidence.\n\n"
    )
    return legend + _table(["Model", *(label for _, label in cols)], body)


SHORT = {
    f"{split}/{key}": f"{split[5:]} {name}"
    for split in SPLITS
    for key, name in (("vertex_per_coord", "V"), ("normal_deg", "N"), ("chamfer", "C"))
}


def _versus_noisy(rows: list[dict], reference: dict | None, classic: dict | None = None) -> str:
    """How many rows beat the noisy input, per test-intra metric, and Taubin (normal)."""
    if not reference:
        return ""
    parts = []
    for key, name in (
        ("vertex_per_coord", "vertex"),
        ("normal_deg", "normal"),
        ("chamfer", "chamfer"),
    ):
        noisy = reference.get(f"test_intra/noisy_{key}")
        vals = [r["values"][f"test_intra/{key}"][0] for r in rows]
        vals = [v for v in vals if v is not None]
        if noisy is None or not vals:
            continue
        parts.append(f"{sum(v < noisy for v in vals)}/{len(vals)} on {name}")
    text = (
        ("Rows better than the noisy input (test-intra): " + ", ".join(parts) + ".")
        if parts
        else ""
    )
    for method, values in (classic or {}).items():
        beats = []
        for split in ("test_intra", "test_inter"):
            bar = values.get(f"{split}/normal_deg")
            vals = [r["values"][f"{split}/normal_deg"][0] for r in rows]
            vals = [v for v in vals if v is not None]
            if bar is not None and vals:
                beats.append(f"{sum(v < bar for v in vals)}/{len(vals)} on {split}")
        if beats:
            label = CLASSIC_LABELS.get(method, method)
            text += f" Rows with a lower normal error than {label}: {', '.join(beats)}."
    return text


def comparison_text(
    study: st.Study,
    rows: list[dict],
    cmp: dict[str, Any],
    reference: dict | None = None,
    classic: dict | None = None,
) -> str:
    """Plain-language comparison of our ordering with the paper's."""
    if study.key not in PAPER:
        return ""  # no paper table: the verdict line says all there is
    if not cmp or not cmp.get("columns"):
        return f"*{study.title}*: not enough finished rows to compare with the paper.\n"
    lines = []
    if study.kind == st.TRAIN:
        ref = study.reference
        p_wins = sum(1 for c in cmp["columns"].values() if c["paper_best"] == ref)
        o_wins = sum(1 for c in cmp["columns"].values() if c["ours_best"] == ref)
        rhos = [c["spearman"] for c in cmp["columns"].values() if c["spearman"] is not None]
        lines.append(
            f"*{study.title}*: the paper's choice **{ref}** is best in {p_wins}/6 columns of "
            f"the paper's table and in {o_wins}/6 of ours. "
            + (
                f"Rank correlation of the {cmp['n_rows']} rows with the paper's, mean over "
                f"the six columns: ρ = {np.mean(rhos):+.2f}."
                if rhos
                else ""
            )
        )
        intra_n = cmp["columns"].get("test_intra/normal_deg")
        if intra_n:
            lines.append(
                f"Best test-intra normal error: paper {intra_n['paper_best']}, "
                f"ours {intra_n['ours_best']}."
            )
        if "agree" in cmp:
            n_all = len(cmp["agree"]) + len(cmp["disagree"])
            by_row: dict[str, list[str]] = {}
            for n, key in cmp["disagree"]:
                by_row.setdefault(n, []).append(SHORT[key])
            lines.append(
                f"Against {ref}, the sign of the difference (better/worse) agrees with the "
                f"paper in {len(cmp['agree'])}/{n_all} (row, column) pairs."
            )
            if by_row:
                lines.append(
                    "Rows whose difference from it has the other sign than in the paper "
                    "(intra/inter V, N, C): "
                    + "; ".join(f"{n} ({', '.join(v)})" for n, v in by_row.items())
                    + "."
                )
        lines.append(_versus_noisy(rows, reference, classic))
    elif study.kind == st.NOISE:
        by = {r["row"]: r["values"] for r in rows}
        ratios_p, ratios_o = [], []
        for name, vals in PAPER["noise"].items():
            v = by.get(name)
            if v is None or v["denoised/vertex_per_coord"][0] is None:
                continue
            ratios_p.append((vals[0] / vals[1], vals[2] / vals[3]))
            ratios_o.append(
                (
                    v["denoised/vertex_per_coord"][0] / v["reference/vertex_per_coord"][0],
                    v["denoised/normal_deg"][0] / v["reference/normal_deg"][0],
                )
            )
        if ratios_o:
            p, o = np.asarray(ratios_p), np.asarray(ratios_o)
            lines.append(
                f"*{study.title}*: denoised / noisy-input error, over the {len(o)} noise "
                f"settings: vertex paper {p[:, 0].min():.2f}–{p[:, 0].max():.2f}, ours "
                f"{o[:, 0].min():.2f}–{o[:, 0].max():.2f}; normal paper "
                f"{p[:, 1].min():.2f}–{p[:, 1].max():.2f}, ours {o[:, 1].min():.2f}–"
                f"{o[:, 1].max():.2f} (below 1: the network removes noise)."
            )
        c = cmp["columns"]
        lines.append(
            "Rank correlation of the twelve settings with the paper's: "
            + ", ".join(
                f"{c[k]['label']} ρ = {c[k]['spearman']:+.2f}"
                for k in ("denoised/vertex_per_coord", "denoised/normal_deg")
                if c.get(k) and c[k]["spearman"] is not None
            )
            + "."
        )
    else:
        c = cmp["columns"]
        lines.append(
            f"*{study.title}*: lower is more equivariant. "
            + "; ".join(
                f"{v['label']}: paper {v['paper_best']}, ours {v['ours_best']}" for v in c.values()
            )
            + "."
        )
    return " ".join(lines) + "\n"


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def write_csv(path: Path, study: st.Study, rows: list[dict]) -> None:
    cols = _columns(study)
    paper = PAPER.get(study.key, {})
    pcols = PAPER_COLUMNS[study.kind]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        header = ["study", "row", "n_seeds", "status"]
        for key, _, _ in cols:
            header += [key, f"{key} std"]
        header += [f"paper {k} (table units)" for k in pcols]
        w.writerow(header)
        for r in rows:
            line = [study.key, r["row"], r["n_seeds"], "/".join(r["status"])]
            for key, _, _ in cols:
                mean, std = r["values"][key]
                line += ["" if mean is None else repr(mean), "" if std is None else repr(std)]
            line += [repr(v) for v in paper.get(r["row"], ())] or [""] * len(pcols)
            w.writerow(line)


def aggregate(out_dir) -> dict[str, Any]:
    """Writes `<study>.md/.csv/.png`, `summary.json` and `README.md` into `out_dir`."""
    out_dir = Path(out_dir)
    plan, records = load_records(out_dir)
    classic = {
        m: {k: v for k, v in d.items() if k != "per_mesh"} for m, d in load_classic(out_dir).items()
    }
    summary: dict[str, Any] = {"preset": plan["preset"]["name"], "studies": {}, "classic": classic}
    sections, comparisons = [], []
    for study in st.STUDIES:
        if study.key not in records:
            continue
        rows = study_rows(study, records[study.key], _columns(study))
        finished = [r for r in rows if r["n_seeds"]]
        if not finished:
            summary["studies"][study.key] = {"finished_rows": 0, "rows": len(rows)}
            continue
        ref_recs = records[study.key].get(study.reference or "", []) or next(
            (recs for recs in records[study.key].values() if recs), []
        )
        reference = ref_recs[0]["metrics"] if ref_recs else None
        table = study_markdown(study, rows, reference, classic)
        cmp = compare_with_paper(study, rows)
        intervals = study_intervals(study, records[study.key])
        verdict_line = verdict_text(study, intervals) + detectability_text(study, intervals)
        text = verdict_line + comparison_text(study, rows, cmp, reference, classic)
        if intervals:
            table += "\n" + intervals_markdown(study, intervals)
            detect = detectability_markdown(study, intervals)
            table += ("\n" + detect) if detect else ""
        paper = (
            f"The paper's table (`{study.paper_table}`):\n\n{paper_markdown(study)}\n"
            if study.paper_table
            else "Not a study of the paper (no paper table to compare with).\n\n"
        )
        (out_dir / f"{study.key}.md").write_text(
            f"# {study.title} (preset {summary['preset']})\n\n{table}\n{paper}{text}"
        )
        write_csv(out_dir / f"{study.key}.csv", study, rows)
        write_plot(out_dir / f"{study.key}.png", study, rows, reference, intervals, classic)
        summary["studies"][study.key] = {
            "finished_rows": len(finished),
            "rows": len(rows),
            "seeds_finished": sorted({r["n_seeds"] for r in finished}),
            "table": {r["row"]: {k: v[0] for k, v in r["values"].items()} for r in rows},
            "comparison": cmp,
            "intervals": intervals,
            "verdict": verdict_line,
        }
        sections.append(
            f"### {study.title} ({len(finished)}/{len(rows)} rows)\n\n{table}\n"
            f"![{study.key}]({study.key}.png)\n\n{text}"
        )
        comparisons.append(text)
    timing = _timing(plan, records)
    summary["timing"] = {**timing, "hosts": sorted(timing["hosts"])}
    # A preset that runs only some studies (cpu-quick) is complete without the others.
    chosen = plan["preset"].get("studies") or st.STUDY_KEYS
    summary["missing"] = [
        s.key
        for s in st.STUDIES
        if s.key in chosen
        and summary["studies"].get(s.key, {}).get("finished_rows", 0) < len(s.rows)
    ]
    summary["comparisons"] = comparisons
    homes = {r["train_hash"] for r in plan["runs"] if r["study"] in chosen}
    if timing["trainings"]:
        per = timing["train_cpu_s"] / timing["trainings"]
        remaining = max(0, len(homes) - timing["trainings"])
        sessions = [x for x in _sessions(out_dir) if x.get("jobs")]
        jobs = sum(x["jobs"] for x in sessions)
        summary["estimate"] = {
            "distinct_trainings": len(homes),
            "remaining": remaining,
            "cpu_per_training_s": per,
            "remaining_cpu_s": per * remaining,
            "remaining_session_wall_s": (
                sum(x["wall_s"] for x in sessions) / jobs * remaining if jobs else None
            ),
        }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    (out_dir / "README.md").write_text(_preset_readme(out_dir, plan, summary, sections))
    return summary


def _sessions(out_dir: Path) -> list[dict]:
    path = out_dir / "sessions.json"
    return json.loads(path.read_text()) if path.is_file() else []


def _preset_readme(out_dir: Path, plan: dict, summary: dict, sections: list[str]) -> str:
    p = plan["preset"]
    base = plan["base_config"]
    cal = plan.get("calibration")
    sessions = _sessions(out_dir)
    t = summary["timing"]
    lines = [
        f"# Ablation sweep, preset `{p['name']}`",
        "",
        "Generated by `python -m experiments aggregate` from the `metrics.json` files; do "
        "not edit by hand.",
        "",
        f"* Preset: {p['description']}.",
        f"* Base config: width {base['model']['width']}, denoiser depth "
        f"{base['model']['depth']}, {base['train']['steps']} steps of batch "
        f"{base['train']['batch_size']}, lr {base['train']['lr']:g} ({base['train']['schedule']}), "
        f"seeds {p['seeds']}.",
        f"* Dataset: procedural, {p['per_category']} shapes per category, "
        f"{p['min_vertices']}–{p['max_vertices']} vertices, test-inter "
        f"{', '.join(p['test_inter'])}; {p['eval_meshes'] or 'all'} test meshes per split.",
    ]
    if cal:
        lines.append(
            f"* Curvature-loss scales calibrated on the training set: γ_H = {cal['gamma_h']:g}, "
            f"γ_G = {cal['gamma_g']:g} (paper: 10⁻⁶ and 1; median unweighted L_H = "
            f"{cal['median_l_h']:.3g}, L_G = {cal['median_l_g']:.3g}, normal loss "
            f"{cal['median_l_n']:.3g} rad over {cal['n_meshes']} noisy training meshes); "
            f"feature-extractor curvature targets: `{base['loss']['feature_curvature']}`."
        )
    lines.append(
        f"* Compute: {t['trainings']} distinct trainings, {t['train_wall_s'] / 60:.1f} min wall "
        f"and {t['train_cpu_s'] / 60:.1f} min CPU summed over runs (several run in parallel; "
        f"the sessions below give the elapsed time), on "
        f"{', '.join(sorted(t['hosts'])) or '–'}."
    )
    for s in sessions:
        lines.append(
            f"  * session {s['start']}"
            + (f" (`{s['command']}`)" if s.get("command") else "")
            + f": studies {', '.join(s['studies'])}; {s['jobs']} jobs, "
            f"{s['wall_s'] / 60:.1f} min wall, {s['cpu_s'] / 60:.1f} min CPU, {s['workers']} "
            f"workers, load average at the end {', '.join(f'{x:.1f}' for x in s['load_average'])}"
        )
    if summary["missing"]:
        lines.append(f"* Not (fully) run at this preset: {', '.join(summary['missing'])}.")
        est = summary.get("estimate")
        if est:
            lines.append(
                f"* Estimated cost of the {est['remaining']} trainings still to run: "
                f"{est['remaining_cpu_s'] / 3600:.1f} h of CPU at the measured "
                f"{est['cpu_per_training_s'] / 60:.1f} min per training (about "
                f"{est['remaining_cpu_s'] / 3600 / max(1, p['workers']):.1f} h wall with "
                f"{p['workers']} workers on free cores"
                + (
                    f"; {est['remaining_session_wall_s'] / 3600:.1f} h at the load of the "
                    "sessions above"
                    if est.get("remaining_session_wall_s")
                    else ""
                )
                + ")."
            )
    # Seeds finished per row, by study: "5", or "2–5" when rows differ.
    done = [
        (k, str(n[0]) if len(n) == 1 else f"{n[0]}–{n[-1]}")
        for k, v in summary["studies"].items()
        if (n := v.get("seeds_finished"))
    ]
    lines.append(
        f"* Seeds and intervals: the preset has {len(p['seeds'])} seed(s) per row; finished "
        f"per row: {', '.join(f'{k} {n}' for k, n in done) or 'none'}; a cell is the mean over "
        "seeds and test meshes ± the standard deviation of the per-seed means; each row's "
        f"difference from the study's reference row has a {CONFIDENCE:.0%} paired bootstrap "
        f"interval over seeds and test meshes ({BOOTSTRAP_RESAMPLES} resamples, RNG seed "
        f"{BOOTSTRAP_SEED}), and its verdict (✓ reproduced, ✗ contradicted with confidence, "
        "· undecided) is derived from it."
    )
    if summary.get("classic"):
        names = ", ".join(CLASSIC_LABELS.get(m, m) for m in summary["classic"] if m != "untrained")
        lines.append(
            f"* Reference rows (italic, under the noisy input), on the same noisy test meshes "
            f"as every row (`references.json`): {names} at their defaults "
            "(`dmd_jax.api.denoise_with`)"
            + (
                "; *untrained base*: the base config at initialisation, whose zero head "
                "averages the candidate normals (the noisy one and the bilateral pre-filtered "
                "ones) before the vertex update, i.e. what the model gives before any "
                "training (`experiments.evaluation.untrained_reference`)."
                if "untrained" in summary["classic"]
                else "."
            )
        )
    lines += ["", "## Verdicts and comparison with the paper", ""]
    lines += [c.rstrip() + "\n" for c in summary["comparisons"]]
    lines += ["## Tables", ""] + sections
    return "\n".join(lines) + "\n"


NOTES = """`cpu/` is `make ablate`: every study on the resolution-free, normal-first `small`
recipe (width 32, 1,000 steps), 3 seeds per row, all 34 procedural test meshes, with
Taubin, BNF and the untrained base as reference rows. `cpu-quick/` is `make
ablate-quick`: four studies (encoding, head, attention, STN) at 300 steps, 3 seeds per
row, 8 test meshes per split, a first look. `cpu-recipe/` holds the encoding and head
studies at one seed from before the multi-seed sweeps (`python -m experiments run --preset
cpu --studies encoding head --out experiments/results/cpu-recipe`).

How to read the training studies: the normal-first head averages ten fixed candidate
normals (the noisy one and bilateral pre-filtered ones) before any training (the
*untrained base* row), and the learnt network only re-weights and corrects them. Most
of the error reduction is therefore already in the untrained row (`cpu/`, test-intra
normal error: noisy 20.6°, untrained 14.2°, trained base 11.5°), and rows that change
only the learnt network's shape (attention, STN, depth, structure) differ by tenths or
hundredths of a degree: an *undecided* verdict there means "no effect this sweep can
resolve", not a failed run. Each verdict paragraph is followed by what the sweep could
have found: the smallest detectable difference (95 % interval, 80 % power) and the seeds
the paper's own difference, scaled to our reference row, would need; on `cpu/` most of
the paper's structure, depth, attention and STN differences were within reach of 3 seeds
and their intervals exclude a difference of the paper's size (docs/ablations.md).

`cpu-offset/` is the second base recipe, where the network does the work: `cpu` with the
direct-offset head (the identity before training), 3,000 steps at lr 1e-3, 5 seeds per
row (`make ablate ABLATE_PRESET=cpu-offset`). About 17 hours of two cores: it is filled
over several sessions, seed-major, and its README says which studies and seeds are done.

## How these sweeps differ from the paper, and how to read them

* Every training-study row is `experiments.ablations.ABLATIONS` applied to the preset's base
  config, so all of them use λ = 1 for every loss, as the paper's appendix D says, the
  depth and STN studies included. (The paper's depth and STN tables repeat its final
  model's numbers, 3.301 / 25.37 / 1.786, which suggests those two were trained with the
  final weights; we follow the text.) The noise model and the rotation-test models use the
  base config's final weights (λ_V 1, λ_N 0.2, λ_κ 0.01, λ_C 0.05, λ_FE 1).
* Curvature-loss scales: with the paper's γ_H = 10⁻⁶, γ_G = 1 the curvature term of our
  meshes is 10⁶–10⁹ (mostly L_G, at sharp CAD corners) against a normal loss near 0.6
  rad, so every λ = 1 run would train on curvature spikes alone. The paper chose its γ
  "based on distribution of objects in our dataset"; we do the same, computing γ so that
  each curvature term equals half the normal loss on the median noisy training mesh
  (`experiments.runner.calibrate_curvature`; the values are in each preset's README).
* The feature extractor learns `asinh` of the curvatures (`feature_curvature`), not the
  raw values whose tail reaches 10⁵.
* DO-2S and DO-1S have no feature extractor, so their λ_FE is 0.
* Noise levels are lengths in the canonical frame (longest side 1), as in the paper. The
  vertex reference errors match the paper's (they are level² · E[X²]); the normal reference
  errors do not have to, because the normal error a given noise amplitude causes grows as
  edges get shorter, and our meshes are small (see the dataset line of each preset).
* Rotation test: `G_i` is the noisy test mesh in its canonical frame, rotated about its
  centre; the three losses are taken in that frame, vertex per coordinate like the other
  tables. A network that changes nothing is exactly equivariant, so the table also gives
  each model's denoising error.
* Seeds and intervals: the `cpu` and `cpu-quick` presets train every row at 3 seeds,
  `cpu-offset` at 5 (parameter init, data order, noise and dropout keys), a row's seeds
  side by side as one program (`experiments.multiseed`; `cpu-offset` one seed after the
  other, `AblatePreset.seeds_together`). Every model is scored on the same noisy test
  meshes (one fixed evaluation key), so a table cell, the mean over seeds and test
  meshes ± the standard deviation of the per-seed means, shows the training's spread.
  Each row's difference from the paper's chosen variant gets a 95 % paired bootstrap
  interval (2,000 resamples, fixed RNG) that resamples seeds and test meshes; the
  paper's ordering of the pair is *reproduced with confidence* when the interval lies on
  the paper's side of 0, *contradicted with confidence* when it lies on the other side,
  and *undecided* when it contains 0. Each interval is a 95 % statement on its own:
  among dozens of (row, column) pairs a few confident verdicts are expected by chance
  alone. `cpu-recipe/` holds one seed per row and no per-mesh values, so it has no
  intervals.
* Even the `cpu` preset's 1,000 steps are far from the paper's 60 epochs of 10⁴ meshes:
  the verdicts are about these short trainings.
"""


def write_index(results_root, presets: Sequence[str] | None = None) -> Path:
    """`results_root/README.md`: every preset directory's headline and comparison."""
    results_root = Path(results_root)
    dirs = sorted(d for d in results_root.iterdir() if (d / "summary.json").is_file())
    if presets is not None:
        dirs = [d for d in dirs if d.name in presets]
    lines = [
        "# Ablation results",
        "",
        "Generated by `python -m experiments index` from the per-preset `summary.json` "
        "files. Each preset directory holds one table, CSV and bar plot per study "
        "(`<study>.md/.csv/.png`), a README with every table, and `plan.json`, the "
        "preset and base config that reproduce it; the runs' own folders "
        "(`<study>/<run-id>/config.json, metrics.json, run.log`) stay on the machine "
        "that ran them, not in git. How to run: "
        "`make ablate` (preset `cpu`), `make ablate-quick` (preset `cpu-quick`), "
        "`make ablate ABLATE_PRESET=paper` on a GPU, `make ablate-smoke`. The speed of "
        "training a row's seeds together: [seed_speedup.md](seed_speedup.md).",
        "",
    ]
    lines += [NOTES, ""]
    for d in dirs:
        summary = json.loads((d / "summary.json").read_text())
        # A study with some rows but not all is "not (fully) run", not finished.
        done = [
            k
            for k, v in summary["studies"].items()
            if v.get("finished_rows") and k not in summary["missing"]
        ]
        lines += [
            f"## `{d.name}/`: preset `{summary['preset']}` ([README]({d.name}/README.md))",
            "",
            f"Finished studies: {', '.join(done) or 'none'}. "
            + (
                f"Not (fully) run: {', '.join(summary['missing'])}."
                if summary["missing"]
                else "All studies complete."
            ),
            "",
        ]
        lines += [c.rstrip() + "\n" for c in summary["comparisons"]]
    path = results_root / "README.md"
    path.write_text("\n".join(lines) + "\n")
    return path
