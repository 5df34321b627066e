"""The ablation sweeps of `experiments/`: plans, ids, evaluations, aggregation, smoke run."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys

import jax
import numpy as np
import pytest
import scipy.stats
from conftest import REPO, icosphere

from dmd_jax import losses
from dmd_jax.config import NoiseConfig
from dmd_jax.metrics import mesh_metrics
from dmd_jax.pipeline import corrupt, make_examples
from experiments import aggregate as agg
from experiments import evaluation, planning, runner, stats
from experiments import studies as st
from experiments.ablations import ABLATIONS, ablation_config

PAPER_TEX = REPO.parent / "shared" / "paper" / "dmd-net.tex"


@pytest.fixture(scope="module")
def test_preset():
    return st.get_preset("test")


@pytest.fixture(scope="module")
def base(test_preset):
    return st.base_config(test_preset, {"gamma_h": 1e-3, "gamma_g": 1e-6})


# --------------------------------------------------------------------------------------
# Plans and ids
# --------------------------------------------------------------------------------------


def test_training_studies_are_config_ablations(test_preset, base):
    runs = st.plan(test_preset, base)
    for study in st.STUDIES:
        if study.kind != st.TRAIN:
            continue
        assert study.rows == tuple(ABLATIONS[study.key])
        got = {r.row: r.config for r in runs if r.study == study.key}
        for row in study.rows:
            want = ablation_config(base, study.key, row)
            if not want.model.uses_feature_extractor:
                # No extractor, no extractor loss: the only change the sweep makes.
                assert got[row].loss.feature == 0.0
                want = want.with_edits({"loss": {"feature": 0.0}})
            assert got[row] == want


def test_run_ids_are_deterministic_and_equal_settings_train_once(test_preset, base):
    runs = st.plan(test_preset, base)
    again = st.plan(test_preset, st.base_config(test_preset, {"gamma_h": 1e-3, "gamma_g": 1e-6}))
    assert [r.run_id for r in runs] == [r.run_id for r in again]
    assert len({(r.study, r.run_id) for r in runs}) == len(runs)
    by_row = {(r.study, r.row): r for r in runs}
    # The paper's own numbers repeat across these tables: the same all-ones FGT-8 model.
    same = [
        ("scheme", "Joint"),
        ("dropout", "Dr=0.0"),
        ("attention", "Without Attention"),
        ("structure", "FGT-8"),
        ("loss", "With All"),
        ("depth", "DMD-Net 2"),
        ("stn", "Without STN"),
    ]
    assert len({by_row[k].train_hash for k in same}) == 1
    noise_hashes = {r.train_hash for r in runs if r.study == "noise"}
    assert noise_hashes == {by_row[("rotation", "Rotation Augmentation")].train_hash}
    assert len(runs) == sum(len(s.rows) for s in st.STUDIES)
    # 4 + 3 + 1 + 6 + 5 + 3 + 1 training rows beyond the shared one, 4 rotation models,
    # and 2 of the encoding/head studies: "xyz (paper)" is the base model (the rotation
    # study's first), head "offset" is encoding "local".
    assert len(st.training_homes(runs)) == 1 + 3 + 3 + 1 + 6 + 5 + 3 + 1 + 4 + 2
    assert by_row[("head", "offset")].train_hash == by_row[("encoding", "local")].train_hash
    home = st.training_homes(runs)[by_row[("depth", "DMD-Net 2")].train_hash]
    assert (home.study, home.row) == ("scheme", "Joint")


def test_a_fresh_checkout_reuses_another_studys_result_instead_of_retraining(
    tmp_path, test_preset, base
):
    # Checkpoints are not committed: in a fresh checkout only metrics.json is there. A
    # row another study already scored (the shared base model) takes its result.
    runs = st.plan(test_preset, base)
    by_row = {(r.study, r.row): r for r in runs}
    src, dst = by_row[("scheme", "Joint")], by_row[("depth", "DMD-Net 2")]
    other = by_row[("depth", "DMD-Net 1")]
    record = {
        "study": "scheme",
        "row": "Joint",
        "run_id": src.run_id,
        "trained_in": "x/y",
        "metrics": {"test_intra/normal": 9.5},
        "per_mesh": {"normal": [9.0, 10.0]},
        "evaluation": src.evaluation,
        "status": "ok",
    }
    (tmp_path / src.study / src.run_id).mkdir(parents=True)
    (tmp_path / src.study / src.run_id / "metrics.json").write_text(json.dumps(record))
    depth = [r for r in runs if r.study == "depth"]
    written = planning.reuse_finished(depth, runs, tmp_path, lambda m: None)
    assert written == [f"depth/{dst.run_id}"]
    got = json.loads((tmp_path / "depth" / dst.run_id / "metrics.json").read_text())
    assert got["metrics"] == record["metrics"] and got["per_mesh"] == record["per_mesh"]
    assert (got["study"], got["row"], got["run_id"]) == ("depth", "DMD-Net 2", dst.run_id)
    assert got["results_of"] == f"scheme/{src.run_id}" and got["trained_in"] == "x/y"
    assert not (tmp_path / "depth" / other.run_id).exists()
    jobs = planning.make_jobs(
        depth, tmp_path, data_dir=tmp_path, preset_name="test", eval_meshes=1, progress=False
    )
    assert {j["label"] for j in jobs} == {"depth/dmd-net_1", "depth/dmd-net_3", "depth/dmd-net_4"}
    # A second call writes nothing; a different evaluation of the same model is not reused.
    assert planning.reuse_finished(depth, runs, tmp_path, lambda m: None) == []
    noise = [r for r in runs if r.study == "noise"]
    assert all(r.evaluation != src.evaluation for r in noise)


def test_hash_ignores_the_name_and_sees_every_setting(base):
    assert st.config_hash(base) == st.config_hash(base.with_edits({"name": "other"}))
    assert st.config_hash(base) != st.config_hash(base.with_edits({"train": {"seed": 1}}))
    assert st.config_hash(base) != st.config_hash(base.with_edits({"loss": {"gamma_g": 2e-6}}))
    ev = {"kind": "test", "eval_meshes": 1}
    assert st.run_hash(base, ev) != st.run_hash(base, {**ev, "eval_meshes": 2})
    # A field added later hashes only away from the value that leaves a run as it was.
    assert st.config_hash(base) == st.config_hash(base.with_edits({"loss": {"crease_weight": 1}}))
    assert st.config_hash(base) != st.config_hash(base.with_edits({"loss": {"crease_weight": 4}}))


@pytest.mark.parametrize("sweep", ["cpu", "cpu-offset"])
def test_committed_sweeps_plan_to_their_recorded_runs(sweep, tmp_path):
    """A committed sweep's plan.json (preset, base config, calibration) reproduces its
    runs: planned again, every run gets the id it was recorded with, so a new config
    field must not rename finished runs (the machine that holds them would retrain
    them). The runs' own folders are not in git, so the test makes empty ones under
    the recorded ids: the cpu sweep's runs were recorded before `train.passes` entered
    the hash (`recorded_hashes` finds them under those ids), the cpu-offset sweep's after."""
    from pathlib import Path

    from dmd_jax.config import ExperimentConfig

    root = Path(__file__).resolve().parents[1] / "experiments" / "results" / sweep
    plan = json.loads((root / "plan.json").read_text())
    recorded = {(r["study"], r["run_id"]) for r in plan["runs"]}
    assert len(recorded) >= 150
    p = st.AblatePreset.from_dict(plan["preset"])
    base = ExperimentConfig.from_dict(plan["base_config"])
    for study, run_id in recorded:
        (tmp_path / study / run_id).mkdir(parents=True)
    runs = st.plan(p, base, out_dir=tmp_path)
    assert {(r.study, r.run_id) for r in runs} == recorded
    # Without the directories, today's ids: the cpu sweep's differ, the cpu-offset's do not.
    fresh = {r.run_id for r in st.plan(p, base)}
    assert (fresh == {r.run_id for r in runs}) == (sweep == "cpu-offset")


def test_list_in_a_fresh_clone_uses_the_recorded_calibration(tmp_path, capsys):
    """Without the dataset (and so its curvature calibration) `experiments list` takes the
    gammas from the results' plan.json: it lists every recorded run under its recorded id
    (the ids hash the gammas), `todo` where the run's folder is absent, as in a fresh
    clone."""
    import shutil
    from pathlib import Path

    from experiments.__main__ import main

    root = Path(__file__).resolve().parents[1] / "experiments" / "results" / "cpu-offset"
    out = tmp_path / "cpu-offset"
    out.mkdir()
    shutil.copy(root / "plan.json", out / "plan.json")
    args = ["list", "--preset", "cpu-offset", "--data-dir", str(tmp_path / "data")]
    assert main([*args, "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "plan.json" in lines[0]
    listed = [line.split()[:2] for line in lines[1:-1]]
    plan = json.loads((root / "plan.json").read_text())
    assert {f"{r['study']}/{r['run_id']}" for r in plan["runs"]} <= {run for _, run in listed}
    assert len(listed) >= 250 and {status for status, _ in listed} == {"todo"}


def test_plan_keeps_todays_ids_where_nothing_older_is_recorded(test_preset, tmp_path):
    base = st.base_config(test_preset)
    runs = st.plan(test_preset, base, ["depth"])
    # Record one run under the id it had before `train.passes` was hashed.
    r = runs[0]
    older = st._older_hashed(r.config)[0]
    train_hash, rid = st._ids(test_preset, r.row, r.seed, r.config, r.evaluation, older)
    (tmp_path / r.study / rid).mkdir(parents=True)
    found = st.plan(test_preset, base, ["depth"], out_dir=tmp_path)
    assert found[0].run_id == rid and found[0].train_hash == train_hash
    # The same training's other runs share its older hash; other trainings keep today's.
    for old, new in zip(runs[1:], found[1:], strict=True):
        same = old.train_hash == r.train_hash
        assert (new.train_hash == train_hash) if same else (new == old)


def test_seeds_multiply_runs_and_ids_name_the_seed(test_preset):
    p = test_preset.with_changes(seeds=(0, 1))
    runs = st.plan(p, st.base_config(p, None), ["depth"])
    assert len(runs) == 8
    assert {r.seed for r in runs} == {0, 1}
    assert all(f"-s{r.seed}-" in r.run_id for r in runs)
    assert all(r.config.train.seed == r.seed for r in runs)


def test_preset_round_trips_through_json(test_preset):
    p = st.AblatePreset.from_dict(json.loads(json.dumps(test_preset.to_dict())))
    assert p == test_preset
    with pytest.raises(ValueError, match="unknown"):
        st.AblatePreset.from_dict({**test_preset.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="unknown study"):
        st.plan(test_preset, st.base_config(test_preset), ["nonsense"])


def test_slugs_are_readable_directory_names():
    assert st.slug("W/O T") == "w_o_t"
    assert st.slug("Dr=0.35") == "dr_0.35"
    assert st.slug("0.05·δ(0.15,0.15)") == "0.05xdelta_0.15_0.15"
    assert st.slug("Rotation Augmentation + STN") == "rotation_augmentation_plus_stn"


# --------------------------------------------------------------------------------------
# Evaluations
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere_examples():
    v, f = icosphere(1)
    v = v / (v.max(0) - v.min(0)).max()
    return make_examples([(v, f), (v * np.array([1.0, 0.8, 0.6]), f)])


def test_calibration_is_half_the_normal_loss_over_the_median_terms(sphere_examples):
    cal = runner.calibrate_curvature(sphere_examples, seed=3)
    h, g, n = [], [], []
    for i, ex in enumerate(sphere_examples):
        noisy, clean, _ = corrupt(
            jax.random.fold_in(jax.random.PRNGKey(3), i),
            ex.vertices,
            ex.faces,
            rotate=True,
            noise=NoiseConfig(),
        )
        lh, lg = losses.curvature_terms(noisy, clean, ex.faces)
        h.append(float(lh))
        g.append(float(lg))
        n.append(float(losses.normal_loss(noisy, clean, ex.faces)))
    np.testing.assert_allclose(cal["median_l_h"], np.median(h), rtol=1e-4)
    np.testing.assert_allclose(cal["median_l_g"], np.median(g), rtol=1e-4)
    np.testing.assert_allclose(cal["median_l_n"], np.median(n), rtol=1e-4)
    np.testing.assert_allclose(cal["gamma_h"], 0.5 * np.median(n) / np.median(h), rtol=0.05)
    np.testing.assert_allclose(cal["gamma_g"], 0.5 * np.median(n) / np.median(g), rtol=0.05)


@pytest.fixture(scope="module")
def identity_bundle(base):
    """An untrained offset model with a zero head: exactly the identity map."""
    from dmd_jax.checkpoints import ModelBundle
    from dmd_jax.model import init_params

    # The paper's offset head (the test preset's normal-first head is no identity at init).
    base = base.with_edits({"model": {"encoding": "xyz", "head": "offset"}})
    assert base.model.predict_offset and base.model.head_init_scale == 0
    # One compiled init instead of hundreds of op-by-op dispatches.
    params = jax.jit(lambda key: init_params(base.model, key))(jax.random.PRNGKey(0))
    return ModelBundle(params=params, config=base, meta={})


def test_noise_evaluation_of_the_identity_equals_the_reference(identity_bundle, sphere_examples):
    out = evaluation.noise_evaluation(identity_bundle, sphere_examples, "gaussian", 0.025)
    for key in ("vertex_per_coord", "normal_deg", "chamfer"):
        np.testing.assert_allclose(out[f"denoised/{key}"], out[f"reference/{key}"], rtol=1e-4)
    # The paper's reference vertex error of N(0, 0.025) is σ² = 6.25e-4 per coordinate.
    assert 4e-4 < out["reference/vertex_per_coord"] < 8e-4
    assert out["n_meshes"] == 2
    assert evaluation.noise_evaluation(identity_bundle, sphere_examples, "gaussian", 0.025) == out


def _noisy_metrics(cfg, examples):
    """Metrics of the noisy test meshes every row is scored on (`EVAL_SEED`)."""
    from dmd_jax.pipeline import evaluation_batches, unpadded_mesh

    batches = evaluation_batches(
        examples,
        seed=evaluation.EVAL_SEED,
        noise=cfg.noise,
        rotate=cfg.train.rotate,
        encoding=cfg.model.encoding,
    )
    return [mesh_metrics(*unpadded_mesh(batch)) for batch, _ in batches]


def test_classic_references_score_the_meshes_every_row_is_scored_on(
    monkeypatch, base, sphere_examples
):
    """Each classic reference sees the noisy test meshes of `evaluation_batches` at
    `EVAL_SEED` (those of every row's `noisy_*` metrics); with an identity 'denoiser' it
    reports exactly the noisy input's errors."""
    import dmd_jax.api

    evals = {"test_intra": list(sphere_examples), "test_inter": list(sphere_examples)[:1]}
    taubin = evaluation.classic_references(base, evals, methods=("taubin",))["taubin"]
    assert len(taubin["per_mesh"]["test_intra/normal_deg"]) == 2
    assert len(taubin["per_mesh"]["test_inter/normal_deg"]) == 1
    monkeypatch.setattr(dmd_jax.api, "denoise_with", lambda method, v, f: v)
    ident = evaluation.classic_references(base, evals, methods=("identity",))["identity"]
    want = _noisy_metrics(base, evals["test_intra"])
    for key in ("vertex_per_coord", "normal_deg", "chamfer"):
        np.testing.assert_allclose(
            ident["per_mesh"][f"test_intra/{key}"], [w[key] for w in want], rtol=1e-5
        )
    # Taubin smooths the noisy spheres: lower normal error than the input.
    assert taubin["test_intra/normal_deg"] < ident["test_intra/normal_deg"]


def test_references_are_computed_once_with_the_untrained_base(
    monkeypatch, tmp_path, base, sphere_examples
):
    """The untrained normal-first model (its zero head averages the candidate normals)
    is no identity: its row differs from the noisy input's. `ensure_references` keeps
    its file."""
    assert base.model.head == "normal"
    evals = {"test_intra": list(sphere_examples), "test_inter": []}
    monkeypatch.setattr(evaluation, "CLASSIC_REFERENCES", ("taubin",))
    refs = evaluation.ensure_references(tmp_path, base, evals)
    assert set(refs) == {"taubin", "untrained"}
    noisy = evaluation.classic_references(base, evals, methods=("taubin",))
    assert refs["taubin"] == noisy["taubin"]
    untrained = refs["untrained"]
    assert len(untrained["per_mesh"]["test_intra/normal_deg"]) == 2
    ident = _noisy_metrics(base, evals["test_intra"])
    got = np.array(untrained["per_mesh"]["test_intra/normal_deg"])
    assert np.all(np.isfinite(got)) and np.all(got < 90)
    assert np.all(np.abs(got - [m["normal_deg"] for m in ident]) > 0.1)

    def boom(*args, **kwargs):
        raise AssertionError("recomputed")

    monkeypatch.setattr(evaluation, "classic_references", boom)
    monkeypatch.setattr(evaluation, "untrained_reference", boom)
    assert evaluation.ensure_references(tmp_path, base, evals) == json.loads(
        (tmp_path / evaluation.REFERENCES_FILE).read_text()
    )


def test_rotation_test_of_the_identity_is_zero(identity_bundle, sphere_examples):
    out = evaluation.rotation_evaluation(identity_bundle, sphere_examples, gamma=2)
    assert out["gamma"] == 2 and out["n_meshes"] == 2
    for key in ("re/vertex_per_coord", "re/chamfer"):
        assert out[key] < 1e-10
    assert out["re/normal_deg"] < 0.05  # float32 round-off of rotated normals
    # The denoising error is that of the noisy input, drawn with the documented keys.
    want = []
    for i, ex in enumerate(sphere_examples):
        k_noise, _ = jax.random.split(
            jax.random.fold_in(jax.random.PRNGKey(evaluation.EVAL_SEED), i)
        )
        noisy, clean, _ = corrupt(
            k_noise,
            ex.vertices,
            ex.faces,
            rotate=False,
            noise=identity_bundle.config.noise,
        )
        want.append(mesh_metrics(noisy, clean, ex.faces)["normal_deg"])
    np.testing.assert_allclose(out["denoised/normal_deg"], np.mean(want), rtol=1e-4)


def test_rotation_test_of_a_translating_denoiser(monkeypatch, identity_bundle, sphere_examples):
    """D(G) = G + c for a fixed world offset c is not rotation-equivariant: every vertex
    of R(D(G)) and D(R(G)) differs by R c − c, so L_vertex = |R c − c|² exactly and the
    normals agree."""
    from dmd_jax import inference
    from dmd_jax.pipeline import random_rotation

    c = np.array([0.02, -0.01, 0.005])
    monkeypatch.setattr(inference, "denoise", lambda v, f, bundle: np.asarray(v) + c)
    out = evaluation.rotation_evaluation(identity_bundle, sphere_examples, gamma=3)
    want = []
    for i in range(len(sphere_examples)):
        _, k_rot = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(evaluation.EVAL_SEED), i))
        for j in range(3):
            r = random_rotation(jax.random.fold_in(k_rot, j))
            want.append(np.sum((r @ c - c) ** 2))
    np.testing.assert_allclose(out["re/vertex"], np.mean(want), rtol=1e-4)
    np.testing.assert_allclose(out["re/vertex_per_coord"], np.mean(want) / 3, rtol=1e-4)
    assert out["re/normal_deg"] < 0.05
    assert 0 < out["re/chamfer"] <= 2 * out["re/vertex"] * (1 + 1e-4)


# --------------------------------------------------------------------------------------
# Aggregation
# --------------------------------------------------------------------------------------


def test_spearman_matches_scipy():
    rng = np.random.default_rng(0)
    for n in (3, 5, 9):
        a, b = rng.normal(size=n), rng.normal(size=n)
        np.testing.assert_allclose(stats.spearman(a, b), scipy.stats.spearmanr(a, b)[0])
    assert stats.spearman([1.0], [2.0]) is None


def test_fmt_follows_the_paper():
    assert agg.fmt(3.9171) == "3.917"
    assert agg.fmt(1.039e16) == "1.039e+16"
    assert agg.fmt(None) == "–"
    assert agg.fmt(2.0, 0.25) == "2.000 ± 0.250"


def _numbers(cell: str) -> float:
    text = re.sub(r"\\textbf|[${}\s]", "", cell)
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(?:\\times10\^(\d+))?", text)
    if m is None:
        raise ValueError(cell)
    return float(m.group(1)) * (10 ** int(m.group(2)) if m.group(2) else 1.0)


def test_paper_tables_match_the_tex_source():
    if not PAPER_TEX.is_file():
        pytest.skip(f"{PAPER_TEX} is absent")
    tex = PAPER_TEX.read_text()
    for study in st.STUDIES:
        if not study.paper_table:  # our own studies (encoding, head)
            assert study.key not in stats.PAPER
            continue
        block = tex[tex.index(f"\\label{{{study.paper_table}}}") :]
        block = block[: block.index("\\end{table")]
        k = len(stats.PAPER_COLUMNS[study.kind])
        rows = []
        for segment in block.split("\\\\"):
            cells = segment.split("&")
            if len(cells) < k + 1:
                continue
            try:
                rows.append(tuple(_numbers(c) for c in cells[-k:]))
            except ValueError:
                continue
        assert rows == list(stats.PAPER[study.key].values()), study.key
        assert list(stats.PAPER[study.key]) == [
            r for r in study.rows if r in stats.PAPER[study.key]
        ]


def _fake_results(out_dir, p, base, values_for):
    """A results dir whose runs report `values_for(study, row) -> metrics`."""
    runs = st.plan(p, base)
    planning._write_json(
        out_dir / "plan.json",
        {
            "preset": p.to_dict(),
            "base_config": base.to_dict(),
            "calibration": None,
            "runs": [
                {k: v for k, v in planning._spec_to_json(r).items() if k != "config"} for r in runs
            ],
        },
    )
    host = {"platform": "test", "cpu_count": 2}
    for r in runs:
        metrics = values_for(r.study, r.row)
        if metrics is None:
            continue
        planning._write_json(
            out_dir / r.study / r.run_id / "metrics.json",
            {
                "study": r.study,
                "row": r.row,
                "seed": r.seed,
                "run_id": r.run_id,
                "trained_in": f"{r.study}/{r.run_id}",
                "status": "ok",
                "metrics": metrics,
                "train": {"wall_s": 1.0, "cpu_s": 2.0},
                "host": host,
            },
        )


def _paper_as_metrics(study_key, row):
    study = st.get_study(study_key)
    vals = stats.PAPER.get(study_key, {}).get(row)
    if vals is None:
        return None
    cols = {k: s for k, s, _ in stats._columns(study)}
    out = {k: v / cols[k] for k, v in zip(stats.PAPER_COLUMNS[study.kind], vals, strict=True)}
    if study.kind == st.TRAIN:
        out.update({f"{s}/noisy_{m}": 1.0 for s in stats.SPLITS for m, _, _ in stats.METRICS})
    if study.kind == st.NOISE:
        out.update({"denoised/chamfer": 1e-4, "reference/chamfer": 2e-4})
    if study.kind == st.ROTATION:
        out.update({"denoised/vertex_per_coord": 1e-4, "denoised/normal_deg": 20.0})
    return out


def test_aggregating_the_papers_own_numbers_agrees_with_the_paper(tmp_path, test_preset, base):
    _fake_results(tmp_path, test_preset, base, _paper_as_metrics)
    # Taubin's normal error between the paper's FGT-8 (25.458) and FGT-1S (28.368).
    taubin = {f"{s}/{k}": v for s in stats.SPLITS for k, v in (("normal_deg", 26.0),)}
    planning._write_json(
        tmp_path / evaluation.REFERENCES_FILE, {"taubin": {**taubin, "per_mesh": {}}}
    )
    summary = agg.aggregate(tmp_path)
    for study in st.STUDIES:
        if study.key not in stats.PAPER:  # our own studies: the paper has no numbers to fake
            continue
        assert (tmp_path / f"{study.key}.md").is_file()
        assert (tmp_path / f"{study.key}.png").stat().st_size > 1000
        cmp = summary["studies"][study.key]["comparison"]
        for col in cmp["columns"].values():
            assert col["ours_best"] == col["paper_best"]
            if col["spearman"] is not None:
                assert col["spearman"] == pytest.approx(1.0)
        if study.kind == st.TRAIN:
            assert cmp["disagree"] == []
    structure = (tmp_path / "structure.md").read_text()
    assert (
        "| FGT-8 | **3.917** | **25.458** | **2.028** | **3.717** | **25.184** | **2.035** |"
        in (structure)
    )
    assert "| FGT-1S | 9.620 | 28.368 | 3.969 |" in structure
    assert "| *Taubin* | – | 26.000 | – | – | 26.000 | – |" in structure
    assert summary["classic"]["taubin"]["test_intra/normal_deg"] == 26.0
    # Only FGT-8 (25.458) beats 26.0 on the paper's test-intra column.
    readme = (tmp_path / "README.md").read_text()
    assert "Rows with a lower normal error than Taubin: 1/7 on test_intra" in readme
    with open(tmp_path / "structure.csv") as fh:
        header = fh.readline().strip().split(",")
        first = fh.readline().strip().split(",")
    assert first[header.index("test_intra/vertex_per_coord")] == repr(3.917e-4)
    assert "other sign than in the paper" not in (tmp_path / "README.md").read_text()
    # Only the rotation study's extra rows, and our own two studies, are unmatched by the
    # paper.
    assert sorted(summary["missing"]) == ["encoding", "head", "rotation"]
    index = agg.write_index(tmp_path.parent)
    assert "preset `test`" in index.read_text()  # each section: "## `<dir>/`: preset `test`"


def test_reversed_numbers_report_the_disagreements(tmp_path, test_preset, base):
    def reversed_structure(study, row):
        m = _paper_as_metrics(study, row)
        if study == "structure" and m is not None:
            m = {k: (1.0 / v if "noisy" not in k else v) for k, v in m.items()}
        return m

    _fake_results(tmp_path, test_preset, base, reversed_structure)
    _, records = stats.load_records(tmp_path)
    study = st.get_study("structure")
    rows = stats.study_rows(study, records["structure"], stats.TRAIN_COLUMNS)
    cmp = stats.compare_with_paper(study, rows)
    assert cmp["agree"] == []
    assert {c["ours_best"] for c in cmp["columns"].values()} == {"FGT-1S"}
    assert all(c["spearman"] == pytest.approx(-1.0) for c in cmp["columns"].values())
    text = agg.comparison_text(study, rows, cmp)
    assert "best in 6/6 columns of the paper's table and in 0/6 of ours" in text
    assert (
        "(intra/inter V, N, C): FGT-3 (intra V, intra N, intra C, inter V, inter N, inter C)"
        in text
    )


def test_list_prints_every_run_without_running_anything(tmp_path, capsys):
    from experiments.__main__ import main

    rc = main(["list", "--preset", "test", "--data-dir", str(tmp_path), "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.count("todo") == sum(len(s.rows) for s in st.STUDIES)
    runs = st.plan(st.get_preset("test"), st.base_config(st.get_preset("test")))
    assert f"{len(st.training_homes(runs))} distinct trainings" in out


# --------------------------------------------------------------------------------------
# The smoke sweep (`make ablate-smoke`)
# --------------------------------------------------------------------------------------


def _run_smoke(out, data):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    cmd = [sys.executable, "-m", "experiments", "run", "--preset", "test", "--no-progress"]
    cmd += ["--out", str(out), "--data-dir", str(data)]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=3000)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


# Slow since the test preset became the small recipe (local encoding, normal-first head):
# 190 s of one worker on 2 cores, a third of the default suite's budget. `make test-slow`
# and `make ablate-smoke` run it; tests/test_multiseed.py covers resume and skip per row.
@pytest.mark.slow
def test_smoke_sweep_writes_every_study_with_finite_numbers(tmp_path):
    out, data = tmp_path / "results", tmp_path / "data"
    _run_smoke(out, data)
    summary = json.loads((out / "summary.json").read_text())
    plan = json.loads((out / "plan.json").read_text())
    for study in st.STUDIES:
        for ext in ("md", "csv", "png"):
            assert (out / f"{study.key}.{ext}").is_file(), (study.key, ext)
        table = summary["studies"][study.key]["table"]
        assert set(table) == set(study.rows)
        for row, values in table.items():
            assert values and all(math.isfinite(v) for v in values.values()), (study.key, row)
    for run in plan["runs"]:
        d = out / run["study"] / run["run_id"]
        record = json.loads((d / "metrics.json").read_text())
        assert (
            record["status"] == "ok" and (d / "config.json").is_file() and (d / "run.log").is_file()
        )
    assert not summary["missing"]

    # Rerun: nothing to do. Then lose one finished run's metrics (as if killed after
    # training): the rerun evaluates its checkpoint and gets the same numbers.
    victim = out / "depth" / next(r["run_id"] for r in plan["runs"] if r["row"] == "DMD-Net 1")
    before = json.loads((victim / "metrics.json").read_text())["metrics"]
    proc = _run_smoke(out, data)
    assert "0 jobs" in proc.stdout + proc.stderr
    (victim / "metrics.json").unlink()
    (victim / "train_metrics.json").unlink()
    _run_smoke(out, data)
    after = json.loads((victim / "metrics.json").read_text())
    assert after["train"]["resumed_from"] == 2
    for k, v in before.items():
        np.testing.assert_allclose(after["metrics"][k], v, rtol=1e-5, err_msg=k)


# --------------------------------------------------------------------------------------
# Packing rows into worker processes, and the device benchmark (issue 32 items 3-4)
# --------------------------------------------------------------------------------------


def test_rows_sharing_a_program_are_packed_into_one_process(tmp_path, test_preset, base):
    runs = st.plan(test_preset, base)
    jobs = planning.make_jobs(
        runs, tmp_path, data_dir=tmp_path, preset_name="test", eval_meshes=1, progress=False
    )
    for job in jobs:
        job["programs"] = planning.job_programs(job)
    tasks = planning.pack_jobs(jobs, 2)
    assert sorted(j["label"] for t in tasks for j in t) == sorted(j["label"] for j in jobs)
    where = {j["label"]: i for i, t in enumerate(tasks) for j in t}
    # The dropout rows with dropout on share one step program, as do Alter, 2-Phase and
    # U-FE (the phase without the FE term): one process each.
    assert where["dropout/dr_0.2"] == where["dropout/dr_0.35"] == where["dropout/dr_0.5"]
    assert where["scheme/alter"] == where["scheme/2-phase"] == where["scheme/u-fe"]
    steps = {p for j in jobs for p in j["programs"] if p.startswith("step:")}
    models = {p for j in jobs for p in j["programs"] if p.startswith("model:")}
    assert len(steps) < sum(1 for j in jobs for p in j["programs"] if p.startswith("step:"))
    assert len(models) < len(jobs)
    # No task takes more than an even share of the sweep, and the largest comes first.
    total = sum(j["cost"] for j in jobs) + planning.COMPILE_COST_STEPS * len(steps | models)

    def cost(task):
        progs = {p for j in task for p in j["programs"]}
        return sum(j["cost"] for j in task) + planning.COMPILE_COST_STEPS * len(progs)

    assert all(cost(t) <= total / 2 for t in tasks)
    assert [cost(t) for t in tasks] == sorted((cost(t) for t in tasks), reverse=True)


# One preset and one mesh size: ~35 s of CPU, two thirds of it compiling (both presets
# and both sizes, `python -m experiments.device_bench` on CPU: ~65 s).
@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_device_bench_runs_tiny_sizes_on_cpu(tmp_path):
    from experiments import device_bench

    report = device_bench.run("auto", presets=("paper",), faces=(2_000,), out_dir=tmp_path)
    assert report["size"] == "tiny" and report["platform"] == "cpu"
    assert [t["preset"] for t in report["training"]] == ["paper"]
    assert report["training"][0]["width"] == 8
    for t in report["training"]:
        assert t["finite"] and t["steps_per_s"] > 0 and t["compiles"] == 1
        assert len(t["weights_sha256"]) == 16
    (inf,) = report["inference"]
    assert inf["finite"] and inf["faces"] >= 2_000 and inf["median_s"] > 0
    assert len(report["inference_weights"]["sha256"]) == 16 and report["commit"]
    md = (tmp_path / "cpu-tiny.md").read_text()
    assert "steps/s" in md and report["device"] in md
    assert json.loads((tmp_path / "cpu-tiny.json").read_text())["commit"] == report["commit"]


def test_the_gpu_preset_is_the_whole_sweep_with_three_seeds():
    p = st.get_preset("gpu")
    runs = st.plan(p, st.base_config(p))
    assert {r.study for r in runs} == set(st.STUDY_KEYS) and p.seeds == (0, 1, 2)
    rows = {planning.seedless_hash(r.config): r for r in runs}
    steps = sorted(r.config.train.steps for r in rows.values())
    # The sizing in dmd_jax.config.presets._gpu: 27 rows at 1,200 steps, the 4 depth rows at 4,000.
    assert steps == [1200] * 27 + [4000] * 4
    assert {r.config.model.width for r in rows.values()} == {128}


def test_the_cpu_offset_preset_is_the_cpu_sweep_with_the_network_doing_the_work():
    """Issue 32's second recipe: the cpu preset's data, model size and evaluation, with
    the direct-offset head (the identity before training), 3,000 steps, 5 seeds."""
    cpu, off = st.get_preset("cpu"), st.get_preset("cpu-offset")
    assert off.dataset_name == cpu.dataset_name == "cpu"  # the same test meshes
    assert off.seeds == (0, 1, 2, 3, 4) and off.workers == 2
    b_cpu, b_off = st.base_config(cpu), st.base_config(off)
    assert b_cpu.model.head == "normal" and b_off.model.head == "offset"
    assert b_off.model.replace(head="normal") == b_cpu.model
    assert (b_off.train.steps, b_off.train.lr) == (3000, 1e-3)
    assert b_off.data == b_cpu.data and b_off.noise == b_cpu.noise
    runs = st.plan(off, b_off)
    assert {r.study for r in runs} == set(st.STUDY_KEYS)
    assert {r.seed for r in runs} == set(off.seeds)
    # Rows keep their own head where the study sets one (the head study's normal-first).
    heads = {(r.study, r.row): r.config.model.head for r in runs}
    assert heads[("structure", "FGT-8")] == "offset"
    assert heads[("head", "normal-first")] == "normal"


def test_seeds_together_splits_a_row_into_groups_trained_one_after_the_other(
    tmp_path, monkeypatch, test_preset, base
):
    from experiments import multiseed

    runs = [r for r in st.plan(test_preset.with_changes(seeds=(0, 1, 2)), base)]
    row = [r for r in runs if r.study == "structure" and r.row == "FGT-3"]
    calls = []

    def fake_train_seeds(cfgs, train_ex, homes, **kwargs):
        calls.append([c.train.seed for c in cfgs])
        return [
            {
                "status": "ok",
                "error": None,
                "step": 2,
                "resumed_from": 0,
                "metrics": {},
                "per_mesh": {},
                "compiles": 0,
                "step_times": [0.1],
            }
            for _ in cfgs
        ]

    monkeypatch.setattr(multiseed, "train_seeds", fake_train_seeds)
    monkeypatch.setattr(runner, "load_examples", lambda data_dir, eval_meshes: ([], {}))
    evaluated = []
    monkeypatch.setattr(
        runner,
        "_evaluate_member",
        lambda job, member, evals, log: evaluated.append((len(calls), member["home"])),
    )
    for together, want in ((None, [[0, 1, 2]]), (1, [[0], [1], [2]]), (2, [[0, 1], [2]])):
        calls.clear()
        evaluated.clear()
        out = tmp_path / f"t{together}"
        (job,) = planning.make_jobs(
            row,
            out,
            data_dir=tmp_path,
            preset_name="test",
            eval_meshes=1,
            progress=False,
            seeds_together=together,
        )
        assert job["seeds_together"] == together
        runner.run_job(job)
        assert calls == want
        assert all((out / m["home"] / "train_metrics.json").is_file() for m in job["members"])
        # Each group is evaluated right after it is trained, before the next trains.
        seeds_done = [sum(len(g) for g in calls[:n]) for n, _ in evaluated]
        assert seeds_done == [
            sum(len(g) for g in want[: 1 + next(i for i, g in enumerate(want) if k in g)])
            for k in range(3)
        ]


def test_references_are_computed_beside_the_jobs_and_their_errors_surface(
    tmp_path, monkeypatch, test_preset
):
    """The reference rows run in a thread while the jobs train: the jobs start without
    waiting for them, and a failure computing them still fails the sweep."""
    import threading

    class Counts:
        def counts(self):
            return {}

    started = threading.Event()
    release = threading.Event()
    order = []

    def references(out_dir, cfg, evals):
        started.set()
        assert release.wait(10)
        order.append("references")
        raise ValueError("no references")

    def execute(jobs, workers, log, progress):
        assert started.wait(10)
        order.append("jobs")  # the references are still running
        release.set()
        return []

    monkeypatch.setattr(runner, "ensure_dataset", lambda p, data_dir, progress=True: Counts())
    monkeypatch.setattr(runner, "load_examples", lambda data_dir, eval_meshes: ([], {}))
    monkeypatch.setattr(runner, "ensure_calibration", lambda data_dir, train_ex: None)
    monkeypatch.setattr(runner, "ensure_references", references)
    monkeypatch.setattr(runner, "_execute", execute)
    with pytest.raises(ValueError, match="no references"):
        runner.run_sweep(
            test_preset,
            tmp_path / "out",
            tmp_path,
            studies=["stn"],
            progress=False,
            aggregate=False,
            echo=False,
        )
    assert order == ["jobs", "references"]


def test_seeds_run_now_leave_the_plan_with_every_seed(tmp_path, monkeypatch, test_preset):
    """`run --seeds 2 3` trains only seeds 2 and 3, but plan.json (what the tables are
    made of) keeps the preset's seeds too, so a sweep run seed by seed aggregates all."""
    from experiments.__main__ import main

    class Counts:
        def counts(self):
            return {}

    jobs_run = []
    monkeypatch.setattr(runner, "ensure_dataset", lambda p, data_dir, progress=True: Counts())
    monkeypatch.setattr(runner, "load_examples", lambda data_dir, eval_meshes: ([], {}))
    monkeypatch.setattr(runner, "ensure_calibration", lambda data_dir, train_ex: None)
    monkeypatch.setattr(runner, "ensure_references", lambda out_dir, cfg, evals: {})
    monkeypatch.setattr(
        runner, "_execute", lambda jobs, workers, log, progress: jobs_run.extend(jobs) or []
    )
    preset = test_preset.with_changes(seeds=(0, 1))
    monkeypatch.setattr(st, "get_preset", lambda name: preset)
    out = tmp_path / "out"
    argv = ["run", "--preset", "test", "--studies", "stn", "--seeds", "2", "3"]
    assert main([*argv, "--out", str(out), "--data-dir", str(tmp_path), "--no-aggregate"]) == 0
    trained = {r["seed"] for j in jobs_run for m in j["members"] for r in m["runs"]}
    assert trained == {2, 3}
    plan = json.loads((out / "plan.json").read_text())
    assert plan["preset"]["seeds"] == [0, 1, 2, 3]
    assert {r["seed"] for r in plan["runs"] if r["study"] == "stn"} == {0, 1, 2, 3}
    assert "seeds 2, 3 of [0, 1, 2, 3]" in (out / "ablate.log").read_text()
