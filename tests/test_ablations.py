"""The ablation tables of `experiments.ablations`, checked against the paper's appendix D."""

from __future__ import annotations

import pytest

from dmd_jax.config import LossConfig, preset
from experiments.ablations import ABLATIONS, ablation_config


def test_ablation_tables_follow_the_paper():
    # The paper's seven studies; the sweep may hold studies of its own besides.
    paper = {"structure", "depth", "dropout", "attention", "stn", "scheme", "loss"}
    assert paper <= set(ABLATIONS)
    base = preset("test")
    depths = [ablation_config(base, "depth", r).model.depth for r in ABLATIONS["depth"]]
    assert depths == [1, 2, 3, 4]
    rates = [ablation_config(base, "dropout", r).model.dropout for r in ABLATIONS["dropout"]]
    assert rates == [0.0, 0.2, 0.35, 0.5]
    schemes = [ablation_config(base, "scheme", r).train.scheme for r in ABLATIONS["scheme"]]
    assert schemes == ["joint", "alter", "two_phase", "u_fe"]
    # Appendix D: every study but loss and scheme uses all-ones weights.
    for study in ("structure", "depth", "dropout", "attention", "stn"):
        for row in ABLATIONS[study]:
            # The preset's own settings that are not weights of the paper's table (how
            # curvature targets are expressed, the normal-first head's term) stay.
            assert ablation_config(base, study, row).loss == LossConfig.all_ones(
                chamfer_block=base.loss.chamfer_block,
                feature_curvature=base.loss.feature_curvature,
                face_normal=base.loss.face_normal,
            )
    # Loss table: λ_V, λ_N, λ_κ, λ_C per row, λ_FE = 1.
    table = {
        "With All": (1, 1, 1, 1),
        "Without Vertex": (0, 1, 1, 1),
        "Without Normal": (1, 0, 1, 1),
        "Without Curvature": (1, 1, 0, 1),
        "Without Chamfer": (1, 1, 1, 0),
        "Without Vertex and Chamfer": (0, 1, 1, 0),
    }
    assert list(ABLATIONS["loss"]) == list(table)
    for row, weights in table.items():
        loss = ablation_config(base, "loss", row).loss
        assert (loss.vertex, loss.normal, loss.curvature, loss.chamfer) == weights
        assert loss.feature == 1.0
    names = {ablation_config(base, s, r).name for s in ABLATIONS for r in ABLATIONS[s]}
    assert len(names) == sum(len(rows) for rows in ABLATIONS.values())
    assert all("/" not in n and " " not in n for n in names)
    with pytest.raises(ValueError, match="unknown ablation study"):
        ablation_config(base, "width", "x")
    with pytest.raises(ValueError, match="unknown row"):
        ablation_config(base, "depth", "DMD-Net 5")
