"""The benchmark scripts at a tiny size, so they keep running (no timing is asserted)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere

from benchmarks import bench_aggregation as agg
from benchmarks import bench_aggregation_variants as variants
from benchmarks import bench_allocation as allocation
from benchmarks.common import Timing, markdown_table, time_interleaved
from dmd_jax.mesh import build_mesh_graph


@pytest.mark.parametrize("mesh", ["grid", "icosphere"])
def test_gcn_edges_equal_build_mesh_graph(mesh):
    if mesh == "grid":
        faces, n = agg.grid_faces(50)
    else:
        v, faces = icosphere(2)
        n = len(v)
    g = build_mesh_graph(faces, n)
    s, r, w = agg.gcn_edges(faces, n)
    np.testing.assert_array_equal(s, g.vertex_senders)
    np.testing.assert_array_equal(r, g.vertex_receivers)
    np.testing.assert_array_equal(w, g.vertex_edge_weight)


def test_grid_is_a_regular_triangulation():
    faces, n = agg.grid_faces(10_000)
    assert n == 100 * 100 and faces.shape == (2 * 99 * 99, 3)
    _, r, _ = agg.gcn_edges(faces, n)
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


def test_variants_agree_with_scipy_and_are_timed():
    # `run` raises if any formulation disagrees with SciPy.
    n, results = variants.run(100, 4, repeat=1)
    assert n == 100
    assert [name for name, _, _ in results] == [*variants.VARIANTS, "scipy_csr"]
    assert "| 100 | 4 | ell (gcn_aggregate_ell) |" in variants.table(n, 4, results)


def test_allocation_measure_times_every_case():
    times = allocation.measure([1000], repeat=1)
    assert list(times) == ["1000"]
    assert sorted(times["1000"]) == sorted(allocation.CASES)
