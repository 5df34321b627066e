"""The loss curve of a training run, drawn from its `log.jsonl` (`train` writes it)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def plot_curves(log_path: Path, png_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # A killed run can leave a cut-off last line, and its resumed run logs the steps after
    # the last checkpoint again: skip unreadable lines, keep the latest row of each step.
    train_rows, eval_rows = {}, {}
    for line in log_path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if row.get("kind") == "train":
            train_rows[row["step"]] = row["loss"]
        elif row.get("kind") == "eval" and "test_intra/normal_deg" in row:
            eval_rows[row["step"]] = row["test_intra/normal_deg"]
    steps, loss = sorted(train_rows), [train_rows[s] for s in sorted(train_rows)]
    ev_steps, ev = sorted(eval_rows), [eval_rows[s] for s in sorted(eval_rows)]
    if not steps:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(steps, loss, lw=0.6, alpha=0.5, label="loss")
    if len(loss) >= 20:
        w = max(len(loss) // 50, 5)
        ax[0].plot(steps[w - 1 :], np.convolve(loss, np.ones(w) / w, "valid"), label=f"mean of {w}")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("step")
    ax[0].legend()
    ax[0].set_title("training loss")
    if ev:
        ax[1].plot(ev_steps, ev, "o-")
    ax[1].set_xlabel("step")
    ax[1].set_title("test-intra normal error (deg)")
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
