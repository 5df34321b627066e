"""The tables of the sota-lite report, from its rows (`sota_lite.run` computes them).

A row is a list in `CSV_HEADER` order (`COL` names the columns): one method on one mesh
under one condition. `tables` gives the summary, the ratio table and the timing table;
`per_shape_table`, `region_table` and `metric_means` the per-mesh ratios, the
crease/flat errors of CAD meshes and the three metrics per method.
`benchmarks/quality/sota_lite.py` re-exports every name defined here.
"""

from __future__ import annotations

import numpy as np

from benchmarks.common import markdown_table
from dmd_jax import comparison, protocol
from dmd_jax.protocol import QUALITY_CONDITIONS

CONDITIONS = (*QUALITY_CONDITIONS, *protocol.SCANNER_CONDITIONS, *protocol.SCAN_CONDITIONS)
STRESS_CONDITIONS = protocol.STRESS_CONDITIONS
REFERENCE = protocol.REFERENCE_METHODS
CSV_HEADER = (
    "set",
    "mesh",
    "n_vertex",
    "n_face",
    "level",
    "seed",
    "method",
    "normal_deg",
    "vertex",
    "chamfer",
    "seconds",
    "noise",
    "cad",
    "normal_crease_deg",
    "normal_flat_deg",
)
# The layout of reports before the noise kind and the crease/flat split were recorded:
# still read (`read_cached`), as Gaussian rows without a region split.
OLD_CSV_HEADER = CSV_HEADER[:11]
# Row fields by name (rows are lists in `CSV_HEADER` order).
COL = {name: i for i, name in enumerate(CSV_HEADER)}


_label = protocol.label


def _best(errs: dict[str, float], methods: list[str]) -> str:
    """The library denoiser(s) with the lowest error (not the input, not MeshLab's)."""
    own = [m for m in methods if m != "noisy" and m not in REFERENCE]
    low = min(errs[m] for m in own)
    return ", ".join(_label(m) for m in own if errs[m] == low)


def _margin(errs: dict[str, float], methods: list[str]) -> str:
    """DMD-Net's error minus the best other library denoiser's (negative: DMD-Net wins)."""
    others = _others(methods)
    if "dmd" not in methods or not others:
        return ""
    return f"{errs['dmd'] - min(errs[m] for m in others):+.2f}"


def condition_label(row) -> str:
    """The noise condition of a row as the tables name it: `0.1` (Gaussian σ along the
    normals, in mean edges, as before), `impulse 0.6`."""
    return protocol.NoiseCondition(row[COL["noise"]], row[COL["level"]]).label


def _condition_order(labels) -> list[str]:
    known = [c.label for c in (*CONDITIONS, *STRESS_CONDITIONS)]
    return sorted(set(labels), key=lambda x: (known.index(x) if x in known else len(known), x))


def _others(methods) -> list[str]:
    """The library denoisers DMD-Net is rated against (not the input, MeshLab or itself)."""
    return [m for m in methods if protocol.is_rival(m)]


def tables(rows: list[list]) -> tuple[str, str, str]:
    """Markdown tables of the mean normal error, per mesh set: per mesh and noise
    condition, means per condition, and the median run time of each method.

    The `best` column names the library denoiser with the lowest error (the noisy input
    and MeshLab's reference filters never count); `DMD-Net margin` is DMD-Net's error
    minus the best other library denoiser's, so negative means DMD-Net wins.
    """
    by_case: dict[tuple, dict[str, float]] = {}
    n_face = {}
    seconds: dict[tuple, list[float]] = {}
    for row in rows:
        mesh_set, mesh, method = row[COL["set"]], row[COL["mesh"]], row[COL["method"]]
        case = (mesh_set, mesh, condition_label(row))
        by_case.setdefault(case, {})[method] = row[COL["normal_deg"]]
        n_face[case] = row[COL["n_face"]]  # a scan's own size
        seconds.setdefault((mesh_set, method), []).append(row[COL["seconds"]])
    methods = list(dict.fromkeys(r[6] for r in rows))
    sets = list(dict.fromkeys(r[0] for r in rows))
    labels = [_label(m) for m in methods]

    detail = [
        [mesh_set, mesh, n_face[(mesh_set, mesh, cond)], cond]
        + [f"{errs[m]:.2f}" for m in methods]
        + [_best(errs, methods), _margin(errs, methods)]
        for (mesh_set, mesh, cond), errs in by_case.items()
    ]
    headers = ["set", "mesh", "faces", "noise", *labels, "best", "DMD-Net margin"]
    means = []
    for mesh_set in sets:
        conds = _condition_order(c for (st, _, c) in by_case if st == mesh_set)
        for cond in [*conds, None]:
            cases = [
                e
                for (st, _, c), e in by_case.items()
                if st == mesh_set and (cond is None or c == cond)
            ]
            mean = {m: float(np.mean([e[m] for e in cases])) for m in methods}
            means.append(
                [mesh_set, "all" if cond is None else cond, len(cases)]
                + [f"{mean[m]:.2f}" for m in methods]
                + [_best(mean, methods), _margin(mean, methods)]
            )
    mean_headers = ["set", "noise", "cases", *labels, "best", "DMD-Net margin"]
    timing = [
        [mesh_set]
        + [
            f"{np.median(seconds[(mesh_set, m)]):.3f}" if (mesh_set, m) in seconds else ""
            for m in methods
            if m != "noisy"
        ]
        for mesh_set in sets
    ]
    timing_headers = ["set", *[_label(m) for m in methods if m != "noisy"]]
    return (
        markdown_table(headers, detail),
        markdown_table(mean_headers, means),
        markdown_table(timing_headers, timing),
    )


def per_shape_table(rows: list[list]) -> str:
    """DMD-Net rated per mesh against the best other library denoiser of each case.

    Per set and noise condition: the geometric mean over meshes of DMD-Net's normal
    error divided by the lowest error of every other library denoiser (below 1: DMD-Net
    wins the typical mesh), how many meshes DMD-Net is best on or within 5 % of the
    best (`comparison.share_within`), and its worst ratio with the mesh it comes from
    (`comparison.summarise_ratios`). Errors below `comparison.RATIO_FLOOR_DEG` count as
    it, so a clean mesh that every method leaves alone rates 1.
    """
    methods = list(dict.fromkeys(r[COL["method"]] for r in rows))
    if "dmd" not in methods or not _others(methods):
        return "(no DMD-Net rows or no other library denoiser)"
    by_case: dict[tuple, dict[str, float]] = {}
    for row in rows:
        case = (row[COL["set"]], condition_label(row), row[COL["mesh"]])
        by_case.setdefault(case, {})[row[COL["method"]]] = row[COL["normal_deg"]]
    ratios = comparison.ratios_to_best_other(
        by_case, "dmd", _others(methods), floor=comparison.RATIO_FLOOR_DEG
    )
    out = []
    for mesh_set in dict.fromkeys(r[COL["set"]] for r in rows):
        conds = _condition_order(c for (st, c, _) in ratios if st == mesh_set)
        for cond in [*conds, None]:
            group = {
                k: v
                for k, v in ratios.items()
                if k[0] == mesh_set and (cond is None or k[1] == cond)
            }
            summary = comparison.summarise_ratios(group)
            worst = summary.worst_case
            out.append(
                [
                    mesh_set,
                    "all" if cond is None else cond,
                    summary.n,
                    f"{summary.geometric_mean:.3f}",
                    f"{summary.within} ({100 * summary.within / summary.n:.0f} %)",
                    summary.best,
                    f"{summary.worst:.2f} ({worst[2]}{'' if cond else ', ' + worst[1]})",
                ]
            )
    headers = [
        "set",
        "noise",
        "cases",
        "DMD-Net / best other (geometric mean)",
        "best or within 5 %",
        "best",
        "worst ratio (mesh)",
    ]
    return markdown_table(headers, out)


def region_table(rows: list[list]) -> str:
    """Crease-face and flat-face normal errors on the CAD meshes (`comparison.is_cad`).

    Per set and noise condition, the mean over the CAD meshes of each region's error for
    DMD-Net and for the best other library denoiser of that region (the one with the
    lowest mean).
    """
    methods = list(dict.fromkeys(r[COL["method"]] for r in rows))
    others = _others(methods)
    cad_rows = [r for r in rows if r[COL["cad"]] in (True, "True")]
    if "dmd" not in methods or not others or not cad_rows:
        return "(no CAD mesh, no DMD-Net rows or no other library denoiser)"
    values: dict[tuple, list[tuple[float, float]]] = {}
    meshes: dict[str, set] = {}
    for row in cad_rows:
        key = (row[COL["set"]], condition_label(row), row[COL["method"]])
        values.setdefault(key, []).append(
            (row[COL["normal_crease_deg"]], row[COL["normal_flat_deg"]])
        )
        meshes.setdefault(row[COL["set"]], set()).add(row[COL["mesh"]])
    out = []
    for mesh_set in dict.fromkeys(r[COL["set"]] for r in cad_rows):
        for cond in _condition_order(c for (st, c, _) in values if st == mesh_set):
            cells = [mesh_set, cond, len(meshes[mesh_set])]
            for region in (0, 1):

                def mean(method, region=region, cond=cond, mesh_set=mesh_set):
                    got = [x[region] for x in values.get((mesh_set, cond, method), [])]
                    return float(np.nanmean(got)) if got else np.inf

                best = min(others, key=mean)
                mine, theirs = mean("dmd"), mean(best)
                cells += [f"{mine:.2f}", f"{theirs:.2f} ({_label(best)})", f"{mine - theirs:+.2f}"]
            out.append(cells)
    headers = [
        "set",
        "noise",
        "CAD meshes",
        "DMD-Net crease",
        "best other crease",
        "crease margin",
        "DMD-Net flat",
        "best other flat",
        "flat margin",
    ]
    listing = "; ".join(f"`{st}`: {', '.join(sorted(names))}" for st, names in meshes.items())
    return markdown_table(headers, out) + f"\n\nCAD meshes: {listing}."


def metric_means(rows: list[list]) -> str:
    """All three metrics per method, means over meshes and levels, in the vocabulary of
    `dmd-jax evaluate` (`dmd_jax.metrics.metrics_table`, legend line included)."""
    from dmd_jax.metrics import metrics_table

    by_method: dict[str, list[list]] = {}
    for row in rows:
        by_method.setdefault(row[6], []).append(row)
    means = {}
    for method, group in by_method.items():
        m = {key: float(np.mean([r[CSV_HEADER.index(key)] for r in group])) for key in _KEYS}
        means[_label(method)] = {**m, "vertex_per_coord": m["vertex"] / 3.0}
    return metrics_table(means, label="method")


_KEYS = ("normal_deg", "vertex", "chamfer")
