"""Issue 53's benchmark conditions: scanner noise, simulated scans and the stress family
in `dmd_jax.protocol`, the ratio summary of `dmd_jax.comparison`, and the quality scripts
(`sota_lite`, `no_harm`) running them."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from conftest import icosphere
from test_inference import TINY_CONFIG, tiny_params

from dmd_jax import checkpoints, comparison, protocol
from dmd_jax.protocol import NoiseCondition


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    path = tmp_path_factory.mktemp("weights") / "tiny.msgpack"
    return checkpoints.save_weights(path, tiny_params(), TINY_CONFIG, {"note": "tiny"})


def test_conditions_parse_label_and_seed():
    for text, kind, level, label in (
        ("0.2", "gaussian", 0.2, "0.2"),
        ("impulse:0.6", "impulse", 0.6, "impulse 0.6"),
        ("scanner:0.5", "scanner", 0.5, "scanner 0.5"),
        ("scan 0.15", "scan", 0.15, "scan 0.15"),
        ("clean", "clean", 0.0, "clean"),
    ):
        c = protocol.parse_condition(text)
        assert c == NoiseCondition(kind, level) and c.label == label
    for bad in ("speckle:0.2", "scanner:-1", "clean:0.3"):
        with pytest.raises(ValueError, match="noise condition"):
            protocol.parse_condition(bad)
    assert [c.level for c in protocol.SCANNER_CONDITIONS] == [0.3, 0.5, 0.8]
    assert len(protocol.SCAN_CONDITIONS) == 2
    assert [c.label for c in protocol.STRESS_CONDITIONS] == ["clean", "0.1"]
    a = protocol.condition_seed("x.obj", NoiseCondition("scanner", 0.5))
    assert a != protocol.condition_seed("x.obj", NoiseCondition("scan", 0.5))


def test_condition_mesh_of_each_kind():
    import dmd_jax

    v, f = icosphere(3)
    clean, noisy, faces = protocol.condition_mesh(v, f, NoiseCondition("clean", 0.0), 1)
    assert np.array_equal(clean, v) and np.array_equal(noisy, v) and np.array_equal(faces, f)
    clean, noisy, faces = protocol.condition_mesh(v, f, NoiseCondition("scanner", 0.5), 7)
    np.testing.assert_array_equal(noisy, dmd_jax.add_noise(7, v, f, "scanner", 0.5, units="edge"))
    scan = NoiseCondition("scan", 0.5)
    clean, noisy, faces = protocol.condition_mesh(v, f, scan, 3)
    ref = dmd_jax.simulate_scan(
        3, v, f, view=protocol.scan_view(v, f, 3), resolution=protocol.SCAN_RESOLUTION, level=0.5
    )
    np.testing.assert_array_equal(clean, ref.clean)
    np.testing.assert_array_equal(noisy, ref.noisy)
    np.testing.assert_array_equal(faces, ref.faces)
    with pytest.raises(ValueError, match="condition_mesh"):
        protocol.condition_noise(v, f, scan, 3)


def test_scan_view_faces_an_open_patch():
    from conftest import crop_mesh

    v, f = icosphere(3)
    patch, pf = crop_mesh(v, f, np.array([0.0, 0.0, 1.0]), 0.6)  # a cap facing +z
    for seed in range(10):
        assert protocol.scan_view(patch, pf, seed)[2] < 0  # looks down onto the cap
        clean, _, faces = protocol.condition_mesh(patch, pf, NoiseCondition("scan", 0.15), seed)
        assert faces.shape[0] > 100


def test_ratio_floor_and_summary():
    errors = {
        "pyramid": {"dmd": 0.4, "bnf": 0.0, "taubin": 6.7},
        "cube": {"dmd": 0.05, "bnf": 0.02},
        "bunny": {"dmd": 3.0, "bnf": 4.0},
    }
    plain = comparison.ratios_to_best_other(errors, "dmd", ["bnf", "taubin"])
    assert math.isinf(plain["pyramid"])
    ratios = comparison.ratios_to_best_other(
        errors, "dmd", ["bnf", "taubin"], floor=comparison.RATIO_FLOOR_DEG
    )
    assert ratios == pytest.approx({"pyramid": 4.0, "cube": 1.0, "bunny": 0.75})
    s = comparison.summarise_ratios(ratios)
    assert s.n == 3 and s.worst == pytest.approx(4.0) and s.worst_case == "pyramid"
    assert s.geometric_mean == pytest.approx(3.0 ** (1 / 3))
    assert s.best == 2 and s.within == 2
    with pytest.raises(ValueError, match="at least one"):
        comparison.summarise_ratios({})


@pytest.mark.slow  # two sota_lite runs: ~60 s on 2 loaded cores
def test_sota_lite_runs_the_new_conditions_and_merges(tmp_path, weights, shared_meshes):
    from benchmarks.quality import sota_lite

    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / "decimated-knight.off").symlink_to(shared_meshes / "decimated-knight.off")
    common = ["--meshes", str(folder), "--weights", str(weights), "--no-val"]
    common += ["--methods", "bnf", "dmd", "--name", "t", "--out-dir", str(tmp_path)]
    argv = [*common, "--sets", "shared", "stress", "--max-meshes", "1"]
    argv += ["--conditions", "scanner:0.5", "scan:0.5"]
    assert sota_lite.main(argv) == 0
    with open(tmp_path / "t.csv") as fh:
        rows = list(csv.DictReader(fh))
    cases = {(r["set"], r["mesh"], r["noise"], r["level"]) for r in rows}
    assert cases == {
        ("shared", "decimated-knight.off", "scanner", "0.5"),
        ("shared", "decimated-knight.off", "scan", "0.5"),
        ("stress", "pyramid", "clean", "0.0"),
        ("stress", "pyramid", "gaussian", "0.1"),
    }
    scan_rows = [r for r in rows if r["noise"] == "scan"]
    # The scan is its own mesh: sizes differ from the knight's 1,000 faces.
    assert len({r["n_face"] for r in scan_rows}) == 1 and scan_rows[0]["n_face"] != "1000"
    clean_rows = {r["method"]: r for r in rows if r["noise"] == "clean"}
    assert float(clean_rows["noisy"]["normal_deg"]) == 0.0
    report = (tmp_path / "t.md").read_text()
    shapes = report.split("## Per shape")[1].split("\n## ")[0]
    assert "| stress | clean | 1 |" in shapes and "(pyramid)" in shapes
    assert "| shared | scan 0.5 | 1 |" in shapes and "(decimated-knight.off)" in shapes
    # Only the stress set again, merged into the report: the shared rows stay.
    argv = [*common, "--sets", "stress", "--max-meshes", "1", "--reuse", "--merge"]
    assert sota_lite.main(argv) == 0
    with open(tmp_path / "t.csv") as fh:
        again = list(csv.DictReader(fh))
    assert {(r["set"], r["mesh"], r["noise"], r["level"]) for r in again} == cases

    def values(rs):  # every field but the run time, which DMD-Net's rerun changes
        return sorted(str({k: v for k, v in r.items() if k != "seconds"}) for r in rs)

    assert values(again) == values(rows)


@pytest.mark.slow  # DMD-Net, CNR, BNF and Taubin on two meshes: ~25 s
def test_no_harm_runs_the_stress_and_scan_sets(tmp_path, weights, shared_meshes):
    from benchmarks.quality import no_harm

    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / "decimated-knight.off").symlink_to(shared_meshes / "decimated-knight.off")
    out = tmp_path / "no_harm.md"
    argv = ["--meshes", str(folder), "--weights", str(weights), "--out", str(out)]
    assert no_harm.main([*argv, "--sets", "stress", "scan", "--max-meshes", "1"]) == 0
    report = out.read_text()
    assert "| stress | pyramid |" in report and "| scan | decimated-knight.off |" in report
    ratios = report.split("## Per mesh: DMD-Net")[1].split("\n## ")[0]
    assert "| stress | 1 |" in ratios and "(pyramid)" in ratios
