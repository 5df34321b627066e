"""The ablation tables of `experiments.ablations`, checked against the paper's appendix D,
and the train-step programs the sweep's rows share (`train.shared_train_step`)."""

from __future__ import annotations

import jax
import numpy as np
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


# --------------------------------------------------------------------------------------
# Shared train-step programs (issue 32 item 3)
# --------------------------------------------------------------------------------------


def _tiny(**edits):
    """The test preset cut down to compile quickly: depth 1, offset head, no STN, no
    Taubin candidates; dropout, non-trivial weights and the `alter` scheme (both phases)."""
    cfg = preset("test").with_edits(
        {
            "model": {"depth": 1, "head": "offset", "taubin_iterations": 0, "stn": False},
            "loss": {
                "vertex": 0.7,
                "normal": 0.3,
                "chamfer": 0.05,
                "feature": 0.5,
                "face_normal": 0.0,
            },
            "train": {"steps": 4, "batch_size": 1, "scheme": "alter", "log_every": 0},
        }
    )
    return cfg.with_edits(edits)


@pytest.fixture(scope="module")
def tiny_examples():
    from conftest import icosphere

    from dmd_jax.pipeline import make_examples

    v, f = icosphere(1)
    rng = np.random.default_rng(0)
    return make_examples([(v + 0.03 * rng.standard_normal(v.shape), f) for _ in range(2)])


class _Compiles:
    """Counts XLA compilations of functions named `name` (`jax.monitoring` events)."""

    def __init__(self, name: str):
        self.name, self.count = name, 0

    def __call__(self, event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration" and kwargs.get("fun_name") in (
            self.name,
            f"jit({self.name})",
            f"jit_{self.name}",
        ):
            self.count += 1

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self)


def _init_states(cfgs, examples):
    from dmd_jax.train import Trainer
    from experiments import multiseed

    first = multiseed.seeds_batch(examples, cfgs, 0)
    states = [Trainer(c).init(jax.tree.map(lambda x, i=i: x[i], first)) for i, c in enumerate(cfgs)]
    return multiseed.stack_trees(states)


def test_the_program_key_keeps_what_changes_the_program(monkeypatch):
    from dmd_jax.train import shared_terms, step_program_key, step_values
    from experiments import multiseed

    cfg = _tiny(model={"dropout": 0.2})
    key = step_program_key(cfg)
    # Weight values (a term switched off too), dropout rate, scheme, phase and seed are
    # traced or host-side: one key.
    for edits in (
        {"loss": {"vertex": 1.0, "normal": 0.9}},
        {"loss": {"chamfer": 0.0}},
        {"model": {"dropout": 0.5}},
        {"train": {"seed": 3, "scheme": "joint"}},
        {"train": {"scheme": "u_fe"}},
        # The batches' rotation and noise are drawn on the host (`training_batch`).
        {"train": {"rotate": not cfg.train.rotate, "log_every": 7, "ckpt_keep": 9}},
        {"noise": {"p_clean": 0.5}},
    ):
        assert step_program_key(cfg.with_edits(edits)) == key, edits
    # Every phase of a scheme gets the one program (built, not compiled, here).
    monkeypatch.setattr(multiseed, "_SEEDS_PROGRAMS", {})
    programs = {
        id(multiseed.seeds_step(cfg, ph, n_seeds=1).program) for ph in ("all", "fe", "rest")
    }
    assert len(programs) == 1
    # Dropout switched off, another model, optimiser or loss setting: new program.
    for edits in (
        {"model": {"dropout": 0.0}},
        {"model": {"width": 16}},
        {"train": {"lr": 2e-3}},
        {"loss": {"crease_weight": 2.0}},
    ):
        assert step_program_key(cfg.with_edits(edits)) != key, edits
    # The offset head has no face-normal term; the extractor gives the feature term.
    terms = ("vertex", "normal", "curvature", "chamfer", "feature")
    assert shared_terms(cfg) == terms
    no_fe = cfg.with_edits({"model": {"variant": "do_2s"}})
    assert "feature" not in shared_terms(no_fe)
    assert "face_normal" in shared_terms(cfg.with_edits({"model": {"head": "normal"}}))
    # Alter's "rest" phase: every term but the FE's on, the FE's weight 0.
    v = step_values(cfg, "rest")
    assert set(v["weights"]) == set(terms)
    assert {n for n, w in v["weights"].items() if w > 0} == {"vertex", "normal", "chamfer"}
    assert {n for n, w in step_values(cfg, "fe")["weights"].items() if w > 0} == {"feature"}
    assert (bool(v["train"]["fe"]), bool(v["train"]["rest"])) == (False, True)
    assert v["keep_prob"] == 0.8


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_rows_differing_in_weights_dropout_and_scheme_compile_one_program(
    tiny_examples, monkeypatch
):
    from dmd_jax.train import step_values
    from experiments import multiseed

    monkeypatch.setattr(multiseed, "_SEEDS_PROGRAMS", {})
    rows = [
        _tiny(model={"dropout": 0.2}, loss={"chamfer": 0.0}, train={"scheme": "u_fe"}),
        _tiny(model={"dropout": 0.35}, loss={"vertex": 1.0, "normal": 1.0}),
        _tiny(model={"dropout": 0.5}, loss={"feature": 0.0}),
    ]
    # U-FE's phase (the chamfer term off), Alter's two phases (the FE's term alone, then
    # every term but it).
    phases = ["all", "fe", "rest"]
    with _Compiles("step") as compiles:
        for cfg, phase in zip(rows, phases, strict=True):
            state = _init_states([cfg], tiny_examples)
            batch = multiseed.seeds_batch(tiny_examples, [cfg], 1)
            step = multiseed.seeds_step(cfg, phase)
            _, out = step(
                state, batch.noisy, batch.clean, batch.graph, multiseed.step_rngs([cfg], 1)
            )
            assert np.isfinite(np.asarray(out["loss"])).all()
            # The program computes every term; a row reports its own terms only.
            on = {n for n, w in step_values(cfg, phase)["weights"].items() if w > 0}
            assert set(out) == {"loss", "grad_norm"} | on
    assert compiles.count == 1
    assert len(multiseed._SEEDS_PROGRAMS) == 1


# Four train-step compiles (two phases, both ways): ~80 s of CPU, so `make test-slow`.
@pytest.mark.slow
def test_a_row_trained_through_the_shared_program_follows_its_own_program(tiny_examples):
    """Two steps of `alter` (phase "fe", then "rest") with dropout: the shared program
    gives the per-config program's losses and params."""
    from dmd_jax import parallel
    from dmd_jax.train import make_train_step, phase_of
    from experiments import multiseed

    cfg = _tiny(model={"dropout": 0.35})
    cfgs = [cfg, cfg.with_edits({"train": {"seed": 4}})]
    mesh = parallel.batch_mesh(jax.devices()[:1])
    shared = own = _init_states(cfgs, tiny_examples)
    t = cfg.train
    for step in range(2):
        phase = phase_of(t.scheme, step, t.two_phase_fe_steps, t.alter_period)
        batch = multiseed.seeds_batch(tiny_examples, cfgs, step)
        args = (batch.noisy, batch.clean, batch.graph, multiseed.step_rngs(cfgs, step))
        own, m_own = jax.jit(jax.vmap(make_train_step(cfg, phase, mesh)))(own, *args)
        shared, m_shared = multiseed.seeds_step(cfg, phase)(shared, *args)
        assert set(m_own) == set(m_shared)
        for k in m_own:
            np.testing.assert_allclose(m_shared[k], m_own[k], rtol=1e-5, atol=1e-7, err_msg=k)
    assert phase == "rest"
    for a, b in zip(jax.tree.leaves(shared), jax.tree.leaves(own), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
