"""The paper's ablation studies (appendix D) as config edits: study -> row -> edits.

`experiments.studies` turns every row into runs at a preset (`ablation_config`); the
tables of `experiments.aggregate` name their rows after these keys. The structure
variants' display names (`FGT-8`, `FGT-3`, ...) are model vocabulary and live with the
model config (`dmd_jax.config.VARIANTS`).
"""

from __future__ import annotations

import re
from typing import Any

from dmd_jax.config import VARIANTS, ExperimentConfig

_ALL_ONES = {"vertex": 1.0, "normal": 1.0, "curvature": 1.0, "chamfer": 1.0, "feature": 1.0}


def _loss_row(vertex, normal, curvature, chamfer) -> dict[str, Any]:
    return {
        "loss": {
            "vertex": vertex,
            "normal": normal,
            "curvature": curvature,
            "chamfer": chamfer,
            "feature": 1.0,
        }
    }


# Every ablation study of appendix D: study -> row name -> ExperimentConfig edits. All
# studies except "loss" and "scheme" use all-ones loss weights (paper, appendix D).
ABLATIONS: dict[str, dict[str, dict[str, Any]]] = {
    "structure": {
        name: {"model": edit, "loss": dict(_ALL_ONES)} for name, edit in VARIANTS.items()
    },
    "depth": {
        f"DMD-Net {d}": {"model": {"depth": d}, "loss": dict(_ALL_ONES)} for d in (1, 2, 3, 4)
    },
    "dropout": {
        f"Dr={r}": {"model": {"dropout": r}, "loss": dict(_ALL_ONES)} for r in (0.0, 0.2, 0.35, 0.5)
    },
    "attention": {
        "With Attention": {"model": {"attention": True}, "loss": dict(_ALL_ONES)},
        "Without Attention": {"model": {"attention": False}, "loss": dict(_ALL_ONES)},
    },
    "stn": {
        "With STN": {"model": {"stn": True}, "loss": dict(_ALL_ONES)},
        "Without STN": {"model": {"stn": False}, "loss": dict(_ALL_ONES)},
    },
    # Scheme rows: the paper states all weights 1 for Joint; Alter, 2-Phase and U-FE
    # switch the feature-extractor term on and off inside the training loop.
    "scheme": {
        "Joint": {"train": {"scheme": "joint"}, "loss": dict(_ALL_ONES)},
        "Alter": {"train": {"scheme": "alter"}, "loss": dict(_ALL_ONES)},
        "2-Phase": {"train": {"scheme": "two_phase"}, "loss": dict(_ALL_ONES)},
        "U-FE": {"train": {"scheme": "u_fe"}, "loss": dict(_ALL_ONES)},
    },
    # Not in the paper: how the network sees a mesh (dmd_jax.encoding) and what it outputs,
    # one change at a time on the preset's recipe. "xyz (paper)" is the paper's reading.
    "encoding": {
        "xyz (paper)": {"model": {"encoding": "xyz", "head": "offset"}},
        "local": {"model": {"encoding": "local", "head": "offset"}},
    },
    "head": {
        "offset": {"model": {"encoding": "local", "head": "offset"}},
        "normal-first": {"model": {"encoding": "local", "head": "normal"}},
        # The bundled recipe: Taubin-smoothed meshes join the candidates (issue 14).
        "normal-first + Taubin candidates": {
            "model": {"encoding": "local", "head": "normal", "taubin_iterations": 10}
        },
    },
    # Loss table columns λ_V, λ_N, λ_κ, λ_C; λ_FE stays 1.
    "loss": {
        "With All": _loss_row(1.0, 1.0, 1.0, 1.0),
        "Without Vertex": _loss_row(0.0, 1.0, 1.0, 1.0),
        "Without Normal": _loss_row(1.0, 0.0, 1.0, 1.0),
        "Without Curvature": _loss_row(1.0, 1.0, 0.0, 1.0),
        "Without Chamfer": _loss_row(1.0, 1.0, 1.0, 0.0),
        "Without Vertex and Chamfer": _loss_row(0.0, 1.0, 1.0, 0.0),
    },
}


def ablation_config(base: ExperimentConfig, study: str, row: str) -> ExperimentConfig:
    """`base` with the edits of one row of one ablation study of `ABLATIONS`."""
    if study not in ABLATIONS:
        raise ValueError(f"unknown ablation study {study!r}; choose one of {list(ABLATIONS)}")
    rows = ABLATIONS[study]
    if row not in rows:
        raise ValueError(f"unknown row {row!r} of study {study!r}; choose one of {list(rows)}")
    slug = re.sub(r"[^a-z0-9.]+", "_", row.lower()).strip("_")
    return base.with_edits(rows[row]).with_edits({"name": f"{base.name}-{study}-{slug}"})
