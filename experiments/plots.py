"""The ablation tables' figures: per study a bar plot of every row against the paper's and
the reference rows, with the paired bootstrap intervals and their verdicts
(`write_plot`). Called by `experiments.aggregate`; the numbers come from
`experiments.stats`."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from experiments import studies as st
from experiments.stats import (
    BETTER,
    CLASSIC_LABELS,
    CONFIDENCE,
    CONTRADICTED,
    METRICS,
    REPRODUCED,
    ROTATION_COLUMNS,
    SPLITS,
    UNDECIDED,
    WORSE,
)


def write_plot(
    path: Path,
    study: st.Study,
    rows: list[dict],
    reference: dict | None,
    intervals: Sequence[dict] = (),
    classic: dict | None = None,
) -> None:
    """Bars of every column (mean ± std over seeds); with `intervals`, a second row of
    panels shows each row's difference from the reference and its interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["row"] for r in rows]
    x = np.arange(len(names))
    if study.kind == st.TRAIN:
        panels = [
            (label, [(f"{s}/{key}", s.replace("_", "-")) for s in SPLITS], scale, key)
            for key, scale, label in METRICS
        ]
    elif study.kind == st.NOISE:
        panels = [
            (label, [(f"denoised/{key}", "denoised"), (f"reference/{key}", "noisy input")], s, key)
            for key, s, label in METRICS
        ]
    else:
        panels = [(label, [(key, "")], scale, key) for key, scale, label in ROTATION_COLUMNS[:3]]
    n_rows = 2 if intervals else 1
    fig, axes = plt.subplots(
        n_rows,
        len(panels),
        figsize=(4.2 * len(panels), n_rows * (3.6 + 0.12 * max(map(len, names)))),
        squeeze=False,
    )
    if intervals:
        _plot_intervals(axes[1], study, panels, intervals)
    for ax, (title, series, scale, metric) in zip(axes[0], panels, strict=True):
        width = 0.8 / len(series)
        top = []
        for i, (key, label) in enumerate(series):
            vals = [r["values"][key][0] for r in rows]
            errs = [r["values"][key][1] for r in rows]
            y = [np.nan if v is None else v * scale for v in vals]
            e = [0.0 if v is None else v * scale for v in errs]
            ax.bar(x + (i - (len(series) - 1) / 2) * width, y, width, yerr=e, label=label or None)
            top += [v for v in y if np.isfinite(v)]
        if reference is not None and study.kind == st.TRAIN:
            v = reference.get(f"test_intra/noisy_{metric}")
            if v is not None:
                ax.axhline(v * scale, color="k", ls="--", lw=1, label="noisy input (intra)")
                top.append(v * scale)
            for (method, values), style in zip((classic or {}).items(), (":", "-."), strict=False):
                v = values.get(f"test_intra/{metric}")
                if v is not None:
                    label = f"{CLASSIC_LABELS.get(method, method)} (intra)"
                    ax.axhline(v * scale, color="0.4", ls=style, lw=1, label=label)
                    top.append(v * scale)
        positive = [v for v in top if v > 0]
        if positive and max(positive) / min(positive) > 200:
            ax.set_yscale("log")
        ax.set_title(title)
        ax.set_xticks(x, names, rotation=35, ha="right", fontsize=8)
        if any(label for _, label in series) or study.kind == st.TRAIN:
            ax.legend(fontsize=7, loc="best", framealpha=0.6)
    seeds = max((r["n_seeds"] for r in rows), default=0)
    fig.suptitle(
        f"{study.title}: "
        + ("mean ± std over {seeds} seeds" if seeds > 1 else "one seed per row").format(seeds=seeds)
        + (
            f"; below, each row minus {study.reference} with its {CONFIDENCE:.0%} paired "
            "bootstrap interval over seeds × meshes"
            if intervals
            else ""
        )
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


VERDICT_COLOURS = {
    REPRODUCED: "tab:green",
    CONTRADICTED: "tab:red",
    UNDECIDED: "0.5",
    BETTER: "tab:blue",
    WORSE: "tab:orange",
}


def _plot_intervals(axes, study: st.Study, panels, intervals: Sequence[dict]) -> None:
    """Differences from the reference with their intervals, one panel per metric,
    coloured by verdict."""
    rows = [r for r in study.rows if r != study.reference]
    x = np.arange(len(rows))
    by = {(iv["row"], iv["column"]): iv for iv in intervals}
    for ax, (title, series, _, _) in zip(axes, panels, strict=True):
        width = 0.8 / len(series)
        for i, (key, _) in enumerate(series):
            for j, row in enumerate(rows):
                iv = by.get((row, key))
                if iv is None:
                    continue
                xj = x[j] + (i - (len(series) - 1) / 2) * width
                err = [[iv["diff"] - iv["low"]], [iv["high"] - iv["diff"]]]
                ax.errorbar(
                    xj,
                    iv["diff"],
                    yerr=err,
                    fmt="os"[i % 2],
                    color=VERDICT_COLOURS[iv["verdict"]],
                    capsize=3,
                    ms=4,
                )
        ax.axhline(0, color="k", lw=0.8)
        ax.set_title(f"{title}: row − {study.reference}", fontsize=9)
        ax.set_xticks(x, rows, rotation=35, ha="right", fontsize=8)
    handles = [
        _legend_line(colour, name)
        for name, colour in VERDICT_COLOURS.items()
        if any(iv["verdict"] == name for iv in intervals)
    ]
    if len(panels[0][1]) > 1:
        handles += [
            _legend_line("k", f"{label} ({'os'[i % 2]})", marker="os"[i % 2], ls="none")
            for i, (_, label) in enumerate(panels[0][1])
        ]
    axes[0].legend(handles=handles, fontsize=7, loc="best", framealpha=0.6)
    axes[0].set_ylabel(f"{CONFIDENCE:.0%} paired bootstrap interval")


def _legend_line(colour: str, label: str, **kwargs):
    """A legend handle."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color=colour, label=label, **kwargs)
