"""The benchmark scripts at a tiny size, so they keep running (no timing is asserted)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from benchmarks import bench_aggregation as agg
from benchmarks import bench_inference as inference
from benchmarks import bench_training as training
from benchmarks.common import (
    Timing,
    gcn_edges,
    grid_faces,
    markdown_table,
    noisy_grid,
    time_interleaved,
)
from dmd_jax import pipeline
from dmd_jax.graph import build_mesh_graph


@pytest.mark.parametrize("mesh", ["grid", "icosphere"])
def test_gcn_edges_equal_build_mesh_graph(mesh):
    if mesh == "grid":
        faces, n = grid_faces(50)
    else:
        v, faces = icosphere(2)
        n = len(v)
    g = build_mesh_graph(faces, n)
    s, r, w = gcn_edges(faces, n)
    np.testing.assert_array_equal(s, g.vertex_senders)
    np.testing.assert_array_equal(r, g.vertex_receivers)
    np.testing.assert_array_equal(w, g.vertex_edge_weight)


def test_grid_is_a_regular_triangulation():
    faces, n = grid_faces(10_000)
    assert n == 100 * 100 and faces.shape == (2 * 99 * 99, 3)
    _, r, _ = gcn_edges(faces, n)
    degree = np.bincount(r, minlength=n)
    # Interior vertices: six neighbours plus the self loop.
    assert np.median(degree) == 7 and degree.max() == 7


def test_time_interleaved_runs_round_robin():
    calls = []
    cases = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}
    timings = time_interleaved(cases, repeat=3, warmup=2)
    assert calls == ["a", "a", "b", "b"] + ["a", "b"] * 3
    assert [t.n for t in timings.values()] == [3, 3]


def test_timing_statistics():
    t = Timing((3.0, 1.0, 2.0, 10.0))
    assert t.median == np.median(t.times) and t.min == 1.0
    assert t.iqr == pytest.approx(np.percentile(t.times, 75) - np.percentile(t.times, 25))


def test_markdown_table_aligns_numbers():
    text = markdown_table(["name", "ms"], [("a", "1.5"), ("b", "—")])
    assert text.splitlines()[1] == "| --- | ---: |"


def test_run_problem_checks_and_times_every_method():
    rows = agg.run_problem(agg.grid_problem(100, 4), repeat=1, min_total_s=0.0)
    assert [r.method for r in rows] == list(agg.METHODS)
    for r in rows:
        assert r.fwd.n == 1 and r.fwd_bwd.n == 1
        assert np.isfinite(r.ratio_fwd) and np.isfinite(r.ratio_fwd_bwd)
    assert rows[-1].ratio_fwd == 1.0


def test_skip_parsing():
    skip = agg.parse_skip(["100x4", "400x8:bcoo", "400x8:bcsr"])
    assert skip == {(100, 4): None, (400, 8): {"bcoo", "bcsr"}}
    with pytest.raises(ValueError, match="unknown method"):
        agg.parse_skip(["100x4:dense"])


def test_main_writes_report_csv_and_plot(tmp_path):
    # The size and width of the test above: the jitted functions are compiled already.
    argv = ["--sizes", "100", "--widths", "4", "--repeat", "1", "--min-total-s", "0"]
    argv += ["--meshes", "--skip", "100x4:bcoo", "--out", str(tmp_path), "--name", "smoke"]
    assert agg.main(argv) == 0
    report = (tmp_path / "smoke.md").read_text()
    assert "| nodes | edges | width | method |" in report
    assert "100 × 4: bcoo" in report
    assert (tmp_path / "smoke.png").stat().st_size > 0
    lines = (tmp_path / "smoke.csv").read_text().splitlines()
    # 4 methods (bcoo skipped) × 2 modes.
    assert len(lines) == 1 + 4 * 2


# --------------------------------------------------------------------------------------
# bench_inference and bench_training
# --------------------------------------------------------------------------------------


def test_noisy_grid_has_the_requested_size():
    v, f = noisy_grid(20_000)
    assert abs(len(f) / 20_000 - 1) < 0.02 and len(v) == (int(np.sqrt(len(v)))) ** 2
    assert f.dtype == np.int32 and f.max() == len(v) - 1


def test_fit_exponent_is_the_log_log_slope():
    faces = [1_000, 10_000, 100_000, 1_000_000]
    rows = [{"faces": n, "times": {"denoise": [2e-6 * n**1.5] * 3}} for n in faces]
    # Sizes below 10k are left out of the fit; the rest lie on t ∝ n^1.5.
    assert inference.fit_exponent(rows) == pytest.approx(1.5)
    assert inference.fit_exponent(rows[:2]) is None


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_inference_measure_and_report(tmp_path):
    rows = [
        inference.measure("test", n, repeat=1, budget_s=0.0, pymeshlab=n == 200) for n in (200, 800)
    ]
    for r in rows:
        assert r["faces"] <= r["padded_faces"] and r["vertices"] < r["padded_vertices"]
        assert r["peak_rss_gib"] >= r["rss_before_gib"] > 0 and r["compile_s"] > 0
        assert all(len(t) == 1 and t[0] > 0 for t in r["times"].values())
    assert set(rows[0]["times"]) == set(inference.CASES)
    text, found = inference.targets(rows, None)
    assert [t[0] for t in found] == [
        "`test` faster than pymeshlab two-step at 200 faces (denoise / two_step, same "
        "process, interleaved)",
        "`test` no slower than bnf at 200 faces (denoise / bnf, same process, interleaved)",
    ]
    assert found[0][2] in ("met", "missed") and found[0][0] in text
    assert "| test | 800 |" in inference.table(rows)
    assert "XLA temp GiB" in inference.memory_table(rows)
    assert inference.plot(rows, tmp_path / "p.png").stat().st_size > 0


@pytest.mark.slow
def test_training_measure_counts_one_compilation_per_bucket():
    examples = pipeline.make_examples([icosphere(1), tetrahedron(), icosphere(2)])
    edits = {"model": {"variant": "do_1s", "depth": 1, "n_agg": 1}, "loss": {"feature": 0.0}}
    rows = training.measure("test", [1, 2], examples, rounds=2, edits=edits)
    assert [r["batch_size"] for r in rows] == [1, 2]
    for r in rows:
        assert r["epoch_compiles"] == len(r["epoch_buckets"]) >= 1
        assert r["steps_per_epoch"] == -(-3 // r["batch_size"])
        assert len(r["step_times"]) == len(r["input_times"]) == 2
    assert "| test |" in training.table(rows) and "| yes |" in training.compile_table(rows)


@pytest.mark.parametrize("mode", ["default", "patches", "whole"])
def test_inference_scale_worker_runs_each_mode(tmp_path, mode):
    """`bench_inference_scale`'s worker on a small grid, every mode (the forced patch
    path calls `inference` internals, which must keep up with their signatures)."""
    from benchmarks import bench_inference_scale as scale

    faces, n = grid_faces(2_000)
    side = int(round(n**0.5))
    u, w = np.meshgrid(np.arange(side, dtype=np.float64), np.arange(side, dtype=np.float64))
    rng = np.random.default_rng(0)
    v = np.stack([u.ravel(), w.ravel(), 0.1 * rng.standard_normal(n)], axis=1)
    np.save(tmp_path / "vertices.npy", v)
    np.save(tmp_path / "faces.npy", faces)
    row = scale.worker("small", len(faces), mode, tmp_path, "2GiB")
    assert row["faces"] == len(faces) and row["mode"] == mode
    # A 2,000-face grid fits the budget whole unless the patch path is forced.
    assert row["path"] == ("patches" if mode == "patches" else "whole")
    if mode == "patches":
        assert row["patches"] >= 1


@pytest.mark.slow
def test_pass_cost_report(tmp_path, monkeypatch):
    from benchmarks import bench_pass_cost

    monkeypatch.setattr(bench_pass_cost, "RESULTS_DIR", tmp_path)
    args = ["--faces", "600", "--repeat", "1", "--name", "p", "--filter-iterations", "60"]
    assert bench_pass_cost.main(args) == 0
    text = (tmp_path / "p.md").read_text()
    assert "solve, 8 passes" in text and "jacobi, 1 pass " in text and "ms per pass" in text
    assert "denoise (default), 60 pre-filter passes" in text
