"""benchmarks/quality/table2.py (Table II) end to end on one small mesh, two fast methods."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from conftest import SHARED_MESHES, shared_mesh_path

from dmd_jax.baselines import taubin
from dmd_jax.io import load_mesh
from dmd_jax.metrics import mesh_metrics


@pytest.fixture(scope="module")
def sota():
    from benchmarks.quality import table2

    return table2


def test_sota_script_on_one_mesh(sota, tmp_path):
    shared_mesh_path("decimated-knight.off")
    missing = tmp_path / "no_such_weights.msgpack"
    rc = sota.main(
        [
            "--table", "sota",
            "--out", str(tmp_path),
            "--meshes-dir", str(SHARED_MESHES),
            "--case", "Knight=decimated-knight.off:gaussian:0.01:3",
            "--methods", "laplacian", "taubin", "dmd",
            "--dmd-weights", str(missing),
        ]
    )  # fmt: skip
    assert rc == 0
    rows = list(csv.DictReader(open(tmp_path / "sota.csv")))
    assert [r["method"] for r in rows] == ["noisy", "laplacian", "taubin", "dmd"]
    by = {r["method"]: r for r in rows}
    # Missing DMD-Net weights are reported, not fatal.
    assert by["dmd"]["status"] == sota.PENDING and by["dmd"]["normal_deg"] == "nan"
    # The numbers are the metrics of the method's output on the seeded noisy mesh.
    import jax

    from dmd_jax.noise import add_noise_jax

    v, f = load_mesh(shared_mesh_path("decimated-knight.off"))
    noisy = np.asarray(add_noise_jax(jax.random.PRNGKey(3), v, f, "gaussian", 0.01), np.float64)
    met = mesh_metrics(taubin(noisy, f), v, f)
    assert float(by["taubin"]["normal_deg"]) == pytest.approx(met["normal_deg"], rel=1e-5)
    assert float(by["taubin"]["vertex_e3"]) == pytest.approx(
        met["vertex_per_coord"] * 1e3, rel=1e-5
    )
    assert float(by["taubin"]["chamfer_e3"]) == pytest.approx(met["chamfer"] * 1e3, rel=1e-5)
    assert float(by["noisy"]["normal_deg"]) > float(by["taubin"]["normal_deg"])
    assert float(by["laplacian"]["seconds"]) > 0
    md = (tmp_path / "sota.md").read_text()
    assert "python benchmarks/quality/table2.py" in md and "Hardware:" in md
    # The provenance line: the commit and the weights (here missing) it was made with.
    assert "Made at commit" in md and "`no_such_weights.msgpack` (missing)" in md
    assert "| Knight | N(0, 0.01) | Normal (°) |" in md
    assert sota.PENDING in md
    png = tmp_path / "sota.png"
    assert png.stat().st_size > 1000
    from PIL import Image

    with Image.open(png) as im:
        # Clean, noisy and two methods: four panels side by side.
        assert im.width > 3 * im.height


def test_case_parsing_and_bad_method(sota):
    case = sota.parse_case("Bunny=bunny.off:gamma:0.015:2")
    assert case == sota.Case("Bunny", "bunny.off", "gamma", 0.015, 2)
    assert sota.noise_label(case) == "0.015·Γ(2,2)"
    with pytest.raises(Exception, match="NAME=FILE"):
        sota.parse_case("bunny.off")
    with pytest.raises(ValueError, match="unknown method"):
        sota.build_methods(["nope"])


def test_extra_checkpoints_become_columns(sota, tmp_path):
    methods = sota.build_methods(["taubin"], extra_weights=[("late", tmp_path / "none")])
    assert [m.key for m in methods] == ["taubin", "dmd:late"]
    assert methods[1].fn is None and methods[1].status.startswith("missing")
    assert "iterations=10" in methods[0].status


def test_dmd_passes_become_columns(sota):
    import dmd_jax

    methods = sota.build_methods(["dmd"], dmd_passes=[3])
    # The bundled weights carry a smoothing controller: a column with it off.
    assert [m.key for m in methods] == ["dmd", "dmd:rules", "dmd:net", "dmd:x3"]
    assert [m.label for m in methods] == [
        "DMD-Net",
        "DMD-Net, controller off",
        "DMD-Net, network only",
        "DMD-Net, network only ×3",
    ]
    assert "3 passes" in methods[3].status and "passes" not in methods[0].status
    assert "defaults" in methods[0].status and "presmooth=0" in methods[2].status
    assert "controller=False" in methods[1].status
    v, f = load_mesh(shared_mesh_path("decimated-knight.off"))
    bundle = dmd_jax.load_pretrained()
    np.testing.assert_array_equal(methods[0].fn(v, f), dmd_jax.denoise(v, f, bundle))
    np.testing.assert_array_equal(
        methods[1].fn(v, f), dmd_jax.denoise(v, f, bundle, controller=False)
    )
    np.testing.assert_array_equal(
        methods[3].fn(v, f), dmd_jax.denoise(v, f, bundle, iterations=3, presmooth=0)
    )


def test_scan_table_runs_sota_lite_on_the_six_meshes_whole(sota, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(sota.subprocess, "run", lambda cmd, check: calls.append(cmd))
    assert sota.main(["--table", "scan", "--out", str(tmp_path)]) == 0
    cmd = calls[0]
    assert cmd[1].endswith("sota_lite.py") and "--no-val" in cmd

    def after(flag, n):
        i = cmd.index(flag)
        return cmd[i + 1 : i + 1 + n]

    assert after("--only", 6) == [c.file for c in sota.SOTA_CASES]
    assert after("--conditions", 5) == list(sota.SCAN_CONDITIONS)
    assert after("--sets", 2) == ["shared", "stress"] and after("--max-faces", 1) == ["0"]
    assert after("--name", 1) == ["sota_scan"] and after("--out-dir", 1) == [str(tmp_path)]
    assert [protocol_label(c) for c in sota.SCAN_CONDITIONS] == [
        "scanner 0.3", "scanner 0.5", "scanner 0.8", "scan 0.15", "scan 0.5",
    ]  # fmt: skip


def protocol_label(condition: str) -> str:
    from dmd_jax import protocol

    return protocol.parse_condition(condition).label


def test_sota_lite_only_runs_the_named_meshes(tmp_path):
    from benchmarks.quality import sota_lite

    shared_mesh_path("decimated-knight.off")
    common = dict(val_dir=None, methods=("laplacian",), out_dir=tmp_path, max_faces=0)
    with pytest.raises(ValueError, match="no-such.off"):
        sota_lite.run(SHARED_MESHES, only=("no-such.off",), **common)
    conditions = (sota_lite.protocol.parse_condition("0.1"),)
    sota_lite.run(
        SHARED_MESHES,
        only=("decimated-knight.off",),
        conditions=conditions,
        sets=("shared",),
        **common,
    )
    rows = list(csv.DictReader(open(tmp_path / "sota_lite.csv")))
    assert {r["mesh"] for r in rows} == {"decimated-knight.off"}
