"""dmd_jax.calibrate on tiny synthetic data: the fits find known rules, the measuring
functions call the denoiser as `denoise` would be called (no network: a stub)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere

from dmd_jax import calibrate as cal
from dmd_jax import protocol
from dmd_jax.checkpoints import ModelBundle
from dmd_jax.policy import DenoisePolicy
from dmd_jax.presmooth import MAX_STEPS, steps_for


class StubDenoiser:
    """Half a uniform Laplacian step per call (a pass moves a noisy mesh, less a smooth
    one), recording the keywords `denoise` was called with."""

    def __init__(self):
        self.calls = []

    def __call__(self, vertices, faces, bundle, **kw):
        from dmd_jax.presmooth import laplacian_steps

        self.calls.append(kw)
        v = np.asarray(vertices, np.float64)
        return 0.5 * (v + laplacian_steps(v, faces, 1))


@pytest.fixture(scope="module")
def cases():
    v, f = icosphere(1)
    return [cal.Case("a.obj", v, f), cal.Case("b.obj", 1.5 * v, f)]


def test_fit_pass_tolerance_finds_where_a_second_pass_helps():
    # A second pass helps exactly where the first moved the mesh more than 0.15.
    rows = []
    for i, (level, move1) in enumerate([(0.1, 0.08), (0.2, 0.12), (0.2, 0.16), (0.3, 0.2)]):
        one, two = (10.0, 8.0) if move1 > 0.15 else (5.0, 6.0)
        rows.append([f"m{i}.obj", 100, level, 0, one, two, move1, 0.0])
    # Every tolerance in [0.12, 0.16) runs it exactly there; the smallest wins the tie.
    assert cal.fit_pass_tolerance(rows) == 0.12
    assert cal.simulate_passes(rows, 0.12, 0.2) == pytest.approx((5.0 + 8.0) / 2)
    assert cal.simulate_passes(rows, 1.0, 0.3) == 10.0  # no second pass
    with pytest.raises(ValueError, match="no measurement"):
        cal.fit_pass_tolerance(rows, levels=(0.5,))


def test_pass_rows_measure_one_and_two_passes(cases):
    stub = StubDenoiser()
    rows = cal.pass_rows(cases, None, levels=(0.1, 0.3), denoise=stub)
    assert len(rows) == 4 and all(kw == {"iterations": 1} for kw in stub.calls)
    assert [r[:4] for r in rows[:2]] == [
        ["a.obj", 80, 0.1, protocol.noise_seed("a.obj", 0.1)],
        ["a.obj", 80, 0.3, protocol.noise_seed("a.obj", 0.3)],
    ]
    for r in rows:
        assert np.isfinite(r[4:]).all() and min(r[6:]) > 0
    # Heavier noise, a bigger first move: what the pass rule reads.
    assert rows[1][6] > rows[0][6]


def test_fit_presmooth_finds_a_known_rule_and_spares_clean_meshes():
    # The best step count of a mesh is round((roughness - 30) / 5); errors grow from it.
    conditions = (("normal", 0.2), ("isotropic", 1.0))
    rows = []
    for i, rough in enumerate([31.0, 36.0, 41.0, 46.0, 52.0, 61.0, 69.0, 78.0]):
        cond = cal.condition_name(*conditions[i % 2])
        target = steps_for(rough, 30.0, 5.0)
        errs = [abs(k - target) + 1.0 for k in range(MAX_STEPS + 1)]
        rows.append([f"m{i}", 100, cond, 0, rough, 9.0, *errs])
    start, per_step, errs = cal.fit_presmooth(rows, {"clean": 20.0}, conditions=conditions)
    assert errs == {"normal 0.2": 1.0, "isotropic 1": 1.0}  # every mesh at its best count
    assert all(steps_for(r[4], start, per_step) == r[6:].index(1.0) for r in rows)
    assert steps_for(20.0, start, per_step) == 0
    with pytest.raises(ValueError, match="clean"):
        cal.fit_presmooth(rows, {"rough clean": 179.0}, conditions=conditions)


def test_presmooth_rows_measure_every_step_count(cases):
    stub = StubDenoiser()
    conditions = (("normal", 0.3), ("isotropic", 2.0))
    rows, clean = cal.presmooth_rows(cases[:1], None, conditions, denoise=stub)
    assert set(clean) == {"a.obj"} and clean["a.obj"] < rows[0][4] < rows[1][4]
    assert [r[2] for r in rows] == ["normal 0.3", "isotropic 2"]
    assert all(len(r) == len(cal.PRESMOOTH_HEADER) + MAX_STEPS + 1 for r in rows)
    assert len(stub.calls) == 2 * (MAX_STEPS + 1)
    assert all(kw == {"presmooth": 0} for kw in stub.calls)


def test_calibrate_returns_a_policy_with_both_rules(cases):
    bundle = ModelBundle(params=None, config=None, meta={}, policy=DenoisePolicy())
    fit = cal.calibrate(
        bundle, denoise=StubDenoiser(), pass_cases=cases[:1], presmooth_cases=cases[:1]
    )
    policy = fit.policy
    assert isinstance(policy, DenoisePolicy)
    assert policy.pass_tolerance in cal.TOLERANCES
    assert policy.max_passes == cal.DEFAULT_MAX_PASSES  # a tolerance needs passes to stop
    assert (policy.presmooth_start, policy.presmooth_per_step) in {
        (s, p) for s in cal.STARTS for p in cal.PER_STEPS
    }
    assert len(fit.pass_rows) == len(cal.PASS_LEVELS)
    assert len(fit.presmooth_rows) == len(cal.PRESMOOTH_CONDITIONS)
    assert set(fit.presmooth_errors) == {cal.condition_name(*c) for c in cal.PRESMOOTH_CONDITIONS}
    # A policy that already runs several passes keeps its cap.
    kept = cal.fitted_policy(DenoisePolicy(max_passes=3), pass_tolerance=0.2)
    assert kept.max_passes == 3 and kept.pass_tolerance == 0.2


def test_csv_round_trip(tmp_path, cases):
    from benchmarks.common import write_csv
    from benchmarks.quality.calibrate import PRESMOOTH_CSV_HEADER

    rows = cal.pass_rows(cases[:1], None, levels=(0.2,), denoise=StubDenoiser())
    write_csv(tmp_path / "p.csv", cal.PASS_HEADER, rows)
    assert cal.read_pass_csv(tmp_path / "p.csv") == rows
    s_rows, clean = cal.presmooth_rows(cases[:1], None, (("normal", 0.2),), denoise=StubDenoiser())
    blank = [""] * (len(PRESMOOTH_CSV_HEADER) - 5)
    write_csv(
        tmp_path / "s.csv",
        PRESMOOTH_CSV_HEADER,
        s_rows + [[m, "", "clean", "", r, *blank] for m, r in clean.items()],
    )
    assert cal.read_presmooth_csv(tmp_path / "s.csv") == (s_rows, clean)


def test_a_cascade_keeps_its_trained_passes(cases):
    """Weights trained with `train.passes = 2` get only the pre-smoothing rule fitted:
    no pass rows are measured and the policy keeps its two passes, no tolerance."""
    from dmd_jax.config import preset

    cfg = preset("test").with_edits({"train": {"passes": 2}})
    bundle = ModelBundle(params=None, config=cfg, meta={}, policy=DenoisePolicy(max_passes=2))
    stub = StubDenoiser()
    fit = cal.calibrate(bundle, denoise=stub, presmooth_cases=cases[:1])
    assert fit.pass_rows == []
    assert (fit.policy.max_passes, fit.policy.pass_tolerance) == (2, 0.0)
    assert fit.policy.presmooths
    assert len(stub.calls) == len(cal.PRESMOOTH_CONDITIONS) * (MAX_STEPS + 1)


# --------------------------------------------------------------------------------------
# The learned pre-smoothing choice
# --------------------------------------------------------------------------------------


def _learn_rows(n_mesh=10, seed=0):
    """Synthetic `learn_rows`: every feature reads how noisy a case is (each its own
    linear function of the level, plus noise), and the best count grows with the level."""
    from dmd_jax.presmooth import FEATURE_NAMES

    rng = np.random.default_rng(seed)
    slopes = np.linspace(-2.0, 3.0, len(FEATURE_NAMES))
    grid = np.array(cal.LEARN_GRID, float)
    rows = []
    for m in range(n_mesh):
        for level in np.linspace(0, 1, 9):
            x = slopes * level + rng.normal(scale=0.05, size=len(FEATURE_NAMES))
            best = 11 * level
            errors = 5.0 + 0.3 * np.abs(grid - best)
            rows.append([f"m{m}.ply", "gaussian", level, m, *x, 0, *errors])
    return rows


def test_fit_learned_presmooth_recovers_a_known_choice():
    rows = _learn_rows()
    fit = cal.fit_learned_presmooth(rows)
    assert set(fit.cv_regret) == set(cal.LEARN_NEIGHBOURS)
    assert fit.neighbours == min(fit.cv_regret, key=fit.cv_regret.get)
    # Held-out meshes of the same law: the chosen count is the best one or next to it.
    test = _learn_rows(n_mesh=3, seed=1)
    features, errors = cal._split_rows(test, cal.LEARN_GRID)
    chosen = fit.choose(features)
    best = np.array(cal.LEARN_GRID)[errors.argmin(axis=1)]
    grid = list(cal.LEARN_GRID)
    assert all(abs(grid.index(c) - grid.index(b)) <= 1 for c, b in zip(chosen, best, strict=True))
    assert cal.regret_of(errors, np.array([grid.index(c) for c in chosen])) < 1.05
    # The fields make a valid policy (its JSON round-trips, as in a weights file).
    policy = DenoisePolicy(presmooth_start=27.0, presmooth_per_step=4.5, **fit.policy_fields())
    assert policy.learns_presmoothing and policy.presmooths
    assert DenoisePolicy.from_dict(policy.to_dict()) == policy


def test_fit_learned_presmooth_rejects_what_cannot_be_fitted():
    rows = _learn_rows(n_mesh=3)
    with pytest.raises(ValueError, match="cross-validation needs at least 5"):
        cal.fit_learned_presmooth(rows)
    bad = _learn_rows()
    bad[0][-1] = float("nan")
    with pytest.raises(ValueError, match="positive and finite"):
        cal.fit_learned_presmooth(bad)


def test_learn_rows_measure_every_count_under_the_rule(cases, tmp_path):
    stub = StubDenoiser()

    def denoise(vertices, faces, bundle, return_info=False, **kw):
        out = stub(vertices, faces, bundle, **kw)
        if return_info:

            class Info:
                presmooth_steps = 3

            return out, Info()
        return out

    conds = (protocol.NoiseCondition("gaussian", 0.2), None)
    rows = cal.learn_rows(cases, None, conds, grid=(0, 2), denoise=denoise)
    assert len(rows) == len(cases) * 2
    assert [r[1] for r in rows[:2]] == ["gaussian", "clean"]
    assert all(r[-3] == 3 for r in rows)  # the rule's steps
    assert [c.get("presmooth") for c in stub.calls[:3]] == [None, 0, 2]
    header = cal.learn_header((0, 2))
    assert all(len(r) == len(header) for r in rows)
    from benchmarks.common import write_csv

    write_csv(tmp_path / "rows.csv", header, rows)
    back = cal.read_learn_csv(tmp_path / "rows.csv", (0, 2))
    assert [r[0] for r in back] == [r[0] for r in rows]
    np.testing.assert_allclose([r[4:] for r in back], [r[4:] for r in rows], rtol=1e-12)
    with pytest.raises(ValueError, match="expected the columns"):
        cal.read_learn_csv(tmp_path / "rows.csv", (0, 2, 4))
