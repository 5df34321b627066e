"""The statistics of the ablation tables: what the paper's tables say (`PAPER`,
transcribed from `paper/dmd-net.tex`), the runs' records of a results directory
(`load_records`), per-row means and seed spreads, rank agreement with the paper
(`spearman`, `compare_with_paper`), paired bootstrap intervals over seeds and test
meshes, verdicts against the paper's orderings and what a sweep could have detected
(`study_intervals`, `detectable_difference`, `seeds_needed`).

No file is written here: `experiments.aggregate` turns these numbers into tables, CSVs,
READMEs and (through `experiments.plots`) figures.

Units follow the paper: Vertex is the per-coordinate mean squared error
(`vertex_per_coord`) ×10⁻⁴, Normal the mean face-normal angle in degrees, Chamfer the
symmetric chamfer distance ×10⁻⁴, all in the canonical frame of the clean mesh.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dmd_jax import protocol
from experiments import studies as st

SPLITS = ("test_intra", "test_inter")


METRICS = (("vertex_per_coord", 1e4, "Vertex (×10⁻⁴)"),) + (
    ("normal_deg", 1.0, "Normal (°)"),
    ("chamfer", 1e4, "Chamfer (×10⁻⁴)"),
)


TRAIN_COLUMNS = tuple(
    (f"{split}/{key}", scale, f"{split.replace('_', '-')} {label}")
    for split in SPLITS
    for key, scale, label in METRICS
)


NOISE_COLUMNS = tuple(
    (f"{which}/{key}", scale, f"{label} {name}")
    for key, scale, label in METRICS
    for which, name in (("denoised", "Loss"), ("reference", "Reference"))
)


ROTATION_COLUMNS = (
    ("re/vertex_per_coord", 1e4, "L_V^RE (×10⁻⁴)"),
    ("re/normal_deg", 1.0, "L_N^RE (°)"),
    ("re/chamfer", 1e4, "L_C^RE (×10⁻⁴)"),
    ("denoised/vertex_per_coord", 1e4, "denoised Vertex (×10⁻⁴)"),
    ("denoised/normal_deg", 1.0, "denoised Normal (°)"),
)


# The paper's tables, in table units: six columns (test-intra V, N, C, test-inter V, N, C)
# for the training studies; (vertex loss, vertex reference, normal loss, normal reference)
# for the noise table; (L_V^RE, L_N^RE, L_C^RE) for the rotation test.
_FGT8 = (3.917, 25.458, 2.028, 3.717, 25.184, 2.035)


_FINAL = (3.301, 25.37, 1.786, 3.271, 25.053, 1.815)


PAPER: dict[str, dict[str, tuple[float, ...]]] = {
    "scheme": {
        "Joint": _FGT8,
        "Alter": (5.112, 26.458, 2.46, 4.882, 26.056, 2.459),
        "2-Phase": (3.987, 26.216, 2.097, 3.937, 25.722, 2.155),
        "U-FE": (4.768, 25.767, 2.399, 5.007, 25.387, 2.544),
    },
    "dropout": {
        "Dr=0.0": _FGT8,
        "Dr=0.2": (101.777, 45.86, 17.912, 98.108, 46.778, 18.743),
        "Dr=0.35": (94.623, 47.578, 19.767, 95.461, 47.836, 21.056),
        "Dr=0.5": (220.129, 47.905, 33.388, 242.294, 49.462, 37.828),
    },
    "attention": {
        "With Attention": (27.881, 28.689, 6.845, 31.399, 28.493, 7.974),
        "Without Attention": _FGT8,
    },
    "structure": {
        "FGT-8": _FGT8,
        "FGT-3": (4.506, 26.396, 2.224, 4.306, 25.917, 2.14),
        "W/O T": (6.112, 26.328, 2.849, 5.588, 25.994, 2.696),
        "MT": (5.586, 26.366, 2.653, 5.521, 26.097, 2.643),
        "DO-2S": (5.398, 26.224, 2.649, 4.967, 25.878, 2.548),
        "DO-1S": (6.097, 27.356, 2.827, 6.02, 26.801, 2.888),
        "FGT-1S": (9.62, 28.368, 3.969, 9.101, 27.963, 3.654),
    },
    "loss": {
        "With All": (4.624, 25.98, 2.337, 4.353, 25.725, 2.264),
        "Without Vertex": (17.291, 26.214, 5.98, 14.282, 25.961, 5.188),
        "Without Normal": (1.923, 40.37, 1.037, 1.907, 39.985, 1.054),
        "Without Curvature": (4.585, 26.493, 2.342, 4.551, 25.966, 2.379),
        "Without Chamfer": (4.601, 26.086, 2.359, 4.406, 25.844, 2.286),
        "Without Vertex and Chamfer": (1.039e16, 25.302, 2.938e15, 9.449e15, 24.979, 3.113e15),
    },
    "depth": {
        "DMD-Net 1": (5.498, 26.12, 2.487, 4.968, 25.8, 2.369),
        "DMD-Net 2": _FINAL,
        "DMD-Net 3": (4.968, 26.004, 2.393, 4.755, 25.509, 2.362),
        "DMD-Net 4": (5.161, 25.98, 2.493, 4.812, 25.575, 2.246),
    },
    "stn": {
        "With STN": (5.233, 26.238, 2.471, 4.692, 25.927, 2.189),
        "Without STN": _FINAL,
    },
    "noise": {
        "0.03·Γ(2,2)": (3.995, 13.345, 33.239, 72.186),
        "0.04·Γ(2,2)": (4.699, 23.724, 37.331, 75.908),
        "0.05·Γ(2,2)": (5.587, 37.069, 40.88, 78.39),
        "N(0,0.025)": (3.285, 6.176, 26.692, 67.482),
        "N(0,0.05)": (3.952, 24.705, 34.372, 77.088),
        "N(0,0.1)": (6.478, 98.82, 45.334, 83.268),
        "0.05·δ(0.15,0.15)": (3.333, 7.408, 27.424, 47.756),
        "0.1·δ(0.15,0.15)": (4.118, 29.633, 35.377, 52.65),
        "0.2·δ(0.15,0.15)": (7.074, 118.531, 46.306, 55.351),
        "0.05·U(−1,1)": (3.366, 8.233, 28.158, 71.154),
        "0.1·U(−1,1)": (4.254, 32.932, 36.677, 79.704),
        "0.2·U(−1,1)": (7.698, 131.729, 48.307, 84.799),
    },
    "rotation": {
        "Rotation Augmentation": (0.704, 5.998, 0.501),
        "Rotation Augmentation + STN": (3.723, 5.711, 1.796),
    },
}


PAPER_COLUMNS = {
    st.TRAIN: [c[0] for c in TRAIN_COLUMNS],
    st.NOISE: [
        "denoised/vertex_per_coord",
        "reference/vertex_per_coord",
        "denoised/normal_deg",
        "reference/normal_deg",
    ],
    st.ROTATION: [c[0] for c in ROTATION_COLUMNS[:3]],
}


# Labels of `evaluation.CLASSIC_REFERENCES` in the tables: the protocol's, and the untrained
# network (not a method of the registry).
CLASSIC_LABELS = {
    **{m: protocol.label(m) for m in ("taubin", "bnf")},
    "untrained": "untrained base",
}


# --------------------------------------------------------------------------------------
# Collecting
# --------------------------------------------------------------------------------------


def load_records(out_dir) -> tuple[dict, dict[str, dict[str, list[dict]]]]:
    """`(plan, {study: {row: [metrics.json records, one per finished seed]}})`."""
    out_dir = Path(out_dir)
    plan_path = out_dir / "plan.json"
    if not plan_path.is_file():
        raise FileNotFoundError(f"{plan_path}: missing; run the sweep first")
    plan = json.loads(plan_path.read_text())
    out: dict[str, dict[str, list[dict]]] = {}
    for run in plan["runs"]:
        rows = out.setdefault(run["study"], {})
        recs = rows.setdefault(run["row"], [])
        path = out_dir / run["study"] / run["run_id"] / "metrics.json"
        if path.is_file():
            recs.append(json.loads(path.read_text()))
    return plan, out


def _stat(records: Sequence[dict], key: str) -> tuple[float | None, float | None]:
    vals = [r["metrics"].get(key) for r in records]
    vals = [float(v) for v in vals if v is not None]
    if not vals:
        return None, None
    return float(np.mean(vals)), (float(np.std(vals, ddof=1)) if len(vals) > 1 else None)


def study_rows(study: st.Study, rows: dict[str, list[dict]], columns) -> list[dict]:
    """One dict per row: name, seeds, status and `(mean, std)` per column key."""
    out = []
    for name in study.rows:
        recs = rows.get(name, [])
        out.append(
            {
                "row": name,
                "n_seeds": len(recs),
                "status": sorted({r["status"] for r in recs}),
                "values": {key: _stat(recs, key) for key, _, _ in columns},
            }
        )
    return out


def _columns(study: st.Study):
    return {st.TRAIN: TRAIN_COLUMNS, st.NOISE: NOISE_COLUMNS, st.ROTATION: ROTATION_COLUMNS}[
        study.kind
    ]


def _best(rows: list[dict], key: str) -> float | None:
    vals = [r["values"][key][0] for r in rows if r["values"][key][0] is not None]
    vals = [v for v in vals if math.isfinite(v)]
    return min(vals) if vals else None


# --------------------------------------------------------------------------------------
# Comparison with the paper
# --------------------------------------------------------------------------------------


def _rank(values: Sequence[float]) -> np.ndarray:
    order = np.argsort(np.asarray(values), kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(len(values))
    return ranks


def spearman(a: Sequence[float], b: Sequence[float]) -> float | None:
    """Spearman rank correlation (ties broken by order); `None` for fewer than 2 rows."""
    if len(a) < 2:
        return None
    ra, rb = _rank(a), _rank(b)
    if np.std(ra) == 0 or np.std(rb) == 0:
        return None
    return float(np.corrcoef(ra, rb)[0, 1])


def compare_with_paper(study: st.Study, rows: list[dict]) -> dict[str, Any]:
    """Winners, rank correlations and sign agreements against the paper's table."""
    if study.key not in PAPER:
        return {}
    keys = PAPER_COLUMNS[study.kind]
    cols = {k: (s, label) for k, s, label in _columns(study)}
    paper = PAPER[study.key]
    ours = {r["row"]: r["values"] for r in rows if r["row"] in paper}
    ours = {n: v for n, v in ours.items() if all(v[k][0] is not None for k in keys)}
    out: dict[str, Any] = {"columns": {}, "n_rows": len(ours)}
    if len(ours) < 2:
        return out
    names = [n for n in paper if n in ours]
    for i, key in enumerate(keys):
        scale = cols[key][0]
        p_vals = [paper[n][i] for n in names]
        o_vals = [ours[n][key][0] * scale for n in names]
        out["columns"][key] = {
            "label": cols[key][1],
            "paper_best": names[int(np.argmin(p_vals))],
            "ours_best": names[int(np.argmin(o_vals))],
            "spearman": spearman(p_vals, o_vals),
        }
    ref = study.reference
    if ref in ours and study.kind == st.TRAIN:
        agree, disagree = [], []
        for n in names:
            if n == ref:
                continue
            for i, key in enumerate(keys):
                p_sign = np.sign(paper[n][i] - paper[ref][i])
                o_sign = np.sign(ours[n][key][0] - ours[ref][key][0])
                (agree if p_sign == o_sign else disagree).append((n, key))
        out["reference"] = ref
        out["agree"] = agree
        out["disagree"] = disagree
    return out


# --------------------------------------------------------------------------------------
# Confidence intervals and verdicts
# --------------------------------------------------------------------------------------


BOOTSTRAP_RESAMPLES = 2000


CONFIDENCE = 0.95


BOOTSTRAP_SEED = 0  # fixed: rerunning the aggregation gives the same intervals


REPRODUCED, CONTRADICTED, UNDECIDED = "reproduced", "contradicted", "undecided"


BETTER, WORSE = "better", "worse"


def paired_bootstrap(
    diff,
    *,
    resamples: int = BOOTSTRAP_RESAMPLES,
    level: float = CONFIDENCE,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, float, float]:
    """Mean of paired differences and its percentile bootstrap interval.

    `diff[s, m]` is a row's error minus the reference row's on test mesh `m` for
    training seed `s`; both rows saw the same noisy mesh (the sweep's evaluation noise is
    fixed, `evaluation.EVAL_SEED`) and trained from the same seed, so the pairs share what
    the two rows have in common. Each resample draws seeds and meshes independently with
    replacement (a crossed bootstrap: the interval carries the seed-to-seed and the
    mesh-to-mesh spread) and takes the mean over the drawn grid. With one seed the
    interval speaks for the meshes only.

    Args:
      diff: `[n_seeds, n_meshes]` (a 1-D array is one seed).
      resamples: bootstrap resamples.
      level: coverage of the two-sided interval.
      seed: the resampling RNG's seed.

    Returns:
      `(mean, low, high)` of the mean difference.
    """
    d = np.atleast_2d(np.asarray(diff, np.float64))
    n_s, n_m = d.shape
    if d.size == 0:
        raise ValueError("paired_bootstrap needs at least one difference")
    rng = np.random.default_rng(seed)
    # A resample's mean over its grid of drawn seeds x drawn meshes is
    # counts_s @ d @ counts_m / (n_s n_m): no [resamples, n_s, n_m] array is built.
    cs = np.stack([np.bincount(r, minlength=n_s) for r in rng.integers(0, n_s, (resamples, n_s))])
    cm = np.stack([np.bincount(r, minlength=n_m) for r in rng.integers(0, n_m, (resamples, n_m))])
    stats = np.einsum("bs,sm,bm->b", cs, d, cm) / (n_s * n_m)
    alpha = (1.0 - level) / 2
    low, high = np.quantile(stats, [alpha, 1 - alpha])
    return float(d.mean()), float(low), float(high)


# Detectability: the power a difference must be found with, and the seed count called
# affordable (four times the 5-seed cpu-offset sweep, itself about 17 h of two CPU cores:
# more than that is a job for a device).
POWER = 0.8


AFFORDABLE_SEEDS = 20


def variance_components(diff) -> tuple[float, float, float]:
    """Seed, mesh and residual variances of paired differences (crossed random effects).

    `diff[s, m] = mu + a_s + b_m + e_sm` with independent seed effects `a` (what the
    training's randomness adds), mesh effects `b` (which test meshes a row helps) and a
    residual `e`; the method-of-moments (two-way ANOVA) estimates, clipped at 0. With one
    seed the seed effect cannot be told from the residual: both are returned as 0 and the
    whole spread goes to the meshes.

    Args:
      diff: `[n_seeds, n_meshes]` (a 1-D array is one seed).

    Returns:
      `(var_seed, var_mesh, var_residual)`.
    """
    d = np.atleast_2d(np.asarray(diff, np.float64))
    n_s, n_m = d.shape
    if d.size == 0:
        raise ValueError("variance_components needs at least one difference")
    if n_m < 2:
        return 0.0, 0.0, float(d.var(ddof=1)) if n_s > 1 else 0.0
    if n_s < 2:
        return 0.0, float(d[0].var(ddof=1)), 0.0
    seed_means, mesh_means = d.mean(1), d.mean(0)
    resid = d - seed_means[:, None] - mesh_means[None, :] + d.mean()
    ms_e = float((resid**2).sum() / ((n_s - 1) * (n_m - 1)))
    ms_s = n_m * float(seed_means.var(ddof=1))
    ms_m = n_s * float(mesh_means.var(ddof=1))
    return max(0.0, (ms_s - ms_e) / n_m), max(0.0, (ms_m - ms_e) / n_s), ms_e


def _z(level: float, power: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(1 - (1 - level) / 2) + NormalDist().inv_cdf(power)


def detectable_difference(
    components: tuple[float, float, float],
    n_seeds: int,
    n_meshes: int,
    *,
    level: float = CONFIDENCE,
    power: float = POWER,
) -> float:
    """The smallest true mean difference a sweep of `n_seeds` x `n_meshes` finds.

    A two-sided `level` interval excludes 0 with probability `power` when the true
    difference is `(z_{1-alpha/2} + z_power) * SE`, with the standard error of the grand
    mean under crossed random effects `SE^2 = v_s / S + v_m / M + v_e / (S M)`
    (`variance_components`). At 95 % and 80 % power the factor is 2.80.
    """
    v_s, v_m, v_e = components
    se2 = v_s / n_seeds + v_m / n_meshes + v_e / (n_seeds * n_meshes)
    return _z(level, power) * math.sqrt(se2)


def seeds_needed(
    components: tuple[float, float, float],
    n_meshes: int,
    difference: float,
    *,
    level: float = CONFIDENCE,
    power: float = POWER,
) -> float:
    """Seeds for `detectable_difference` to reach `|difference|` with `n_meshes` meshes.

    Returns:
      The smallest seed count (at least 1), or `math.inf` when the mesh-to-mesh spread of
      `n_meshes` test meshes alone keeps the detectable difference above it (more seeds
      cannot help; more test meshes could).
    """
    v_s, v_m, v_e = components
    target = (abs(float(difference)) / _z(level, power)) ** 2
    room = target - v_m / n_meshes
    if room <= 0:
        return math.inf
    return float(max(1, math.ceil((v_s + v_e / n_meshes) / room - 1e-12)))


def verdict(low: float, high: float, paper_sign: float | None) -> str:
    """What an interval of `row - reference` (lower error is better) says.

    Args:
      low, high: the interval.
      paper_sign: the sign of the same difference in the paper (+1: the paper's row is
        worse than its reference, -1: better), or None where the paper has no number.

    Returns:
      With a paper sign: `reproduced` (the interval excludes 0 on the paper's side),
      `contradicted` (it excludes 0 on the other side) or `undecided` (it contains 0);
      without: `better`, `worse` or `undecided`.
    """
    if low <= 0 <= high:
        return UNDECIDED
    observed = 1.0 if low > 0 else -1.0
    if paper_sign is None or paper_sign == 0:
        return WORSE if observed > 0 else BETTER
    return REPRODUCED if observed == np.sign(paper_sign) else CONTRADICTED


def _per_seed_matrix(records: Sequence[dict], key: str) -> dict[int, np.ndarray]:
    out = {}
    for r in records:
        vals = r.get("per_mesh", {}).get(key)
        if vals and r.get("status") == "ok":
            out[int(r["seed"])] = np.asarray(vals, np.float64)
    return out


def interval_keys(study: st.Study) -> list[tuple[str, float, str]]:
    """The columns that get intervals: the error metrics of the study's table."""
    if study.kind == st.TRAIN:
        return list(TRAIN_COLUMNS)
    if study.kind == st.ROTATION:
        return list(ROTATION_COLUMNS[:3])
    return []


def study_intervals(study: st.Study, records: dict[str, list[dict]]) -> list[dict]:
    """Every row's difference from the study's reference row, with its interval.

    For each row but the reference and each column of `interval_keys`: the per-mesh
    values of both rows at the seeds both have finished (paired by seed and mesh),
    `paired_bootstrap` of their difference in table units, the paper's sign of the same
    difference where it has both numbers, and the `verdict`.
    """
    ref = study.reference
    if ref is None or not records.get(ref):
        return []
    paper = PAPER.get(study.key, {})
    pcols = PAPER_COLUMNS.get(study.kind, [])
    out = []
    for row in study.rows:
        if row == ref or not records.get(row):
            continue
        for key, scale, label in interval_keys(study):
            a, b = _per_seed_matrix(records[row], key), _per_seed_matrix(records[ref], key)
            seeds = sorted(set(a) & set(b))
            if not seeds or any(a[s].shape != b[s].shape for s in seeds):
                continue
            diff = np.stack([a[s] - b[s] for s in seeds]) * scale
            if not np.all(np.isfinite(diff)):
                continue
            mean, low, high = paired_bootstrap(diff)
            comps = variance_components(diff)
            n_s, n_m = diff.shape
            sign = claim = None
            if row in paper and ref in paper and key in pcols:
                i = pcols.index(key)
                sign = float(np.sign(paper[row][i] - paper[ref][i]))
                # The paper's difference as a fraction of its reference row, applied to
                # ours: its meshes, noise and units are not ours, its relative claim is.
                ours = float(np.mean([b[s] for s in seeds])) * scale
                claim = (paper[row][i] - paper[ref][i]) / paper[ref][i] * ours
            out.append(
                {
                    "row": row,
                    "column": key,
                    "label": label,
                    "diff": mean,
                    "low": low,
                    "high": high,
                    "paper_sign": sign,
                    "verdict": verdict(low, high, sign),
                    "n_seeds": len(seeds),
                    "n_meshes": int(diff.shape[1]),
                    # With one seed the seed spread is unknown: no detectability.
                    "mdd": detectable_difference(comps, n_s, n_m) if n_s > 1 else None,
                    "claim": claim,
                    "seeds_needed": (
                        seeds_needed(comps, n_m, claim) if n_s > 1 and claim else None
                    ),
                }
            )
    return out


# --------------------------------------------------------------------------------------
# Training time
# --------------------------------------------------------------------------------------


def _timing(plan: dict, records: dict) -> dict[str, Any]:
    trained = {}
    for rows in records.values():
        for recs in rows.values():
            for r in recs:
                trained[r["trained_in"]] = r
    wall = sum(r["train"]["wall_s"] for r in trained.values())
    cpu = sum(r["train"]["cpu_s"] for r in trained.values())
    hosts = {
        f"{r['host'].get('processor', '?')}, {r['host']['cpu_count']} CPUs, "
        f"{r['host']['platform']}, jax {r['host'].get('jax', '?')}"
        for r in trained.values()
    }
    return {"trainings": len(trained), "train_wall_s": wall, "train_cpu_s": cpu, "hosts": hosts}
