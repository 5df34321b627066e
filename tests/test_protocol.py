"""dmd_jax.protocol: one definition of the benchmark noise, seeds, crop, sets and labels."""

from __future__ import annotations

import subprocess
import sys
import zlib

import numpy as np
import pytest
from conftest import icosphere

from dmd_jax import baselines, protocol
from dmd_jax.io import save_mesh


def test_import_loads_no_jax():
    code = "import sys, dmd_jax.protocol; print('jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_noise_seed_is_a_crc32_of_name_and_level():
    assert protocol.noise_seed("fandisk.off", 0.2) == zlib.crc32(b"fandisk.off|0.2")
    # `:g` formatting: 0.1 and 0.10 are one level, another level another seed.
    assert protocol.noise_seed("a.obj", 0.10) == protocol.noise_seed("a.obj", 0.1)
    assert protocol.noise_seed("a.obj", 0.1) != protocol.noise_seed("a.obj", 0.3)


def test_benchmark_noise_is_add_noise_along_normals_in_edges():
    import dmd_jax
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.noise import vertex_normals_np

    v, f = icosphere(2)
    noisy = protocol.benchmark_noise(v, f, 0.2, seed=7)
    expected = dmd_jax.add_noise(7, v, f, "gaussian", 0.2, units="edge", direction="normal")
    np.testing.assert_array_equal(noisy, expected)
    assert noisy.dtype == np.float64
    # Along the normals: the offset is parallel to each vertex normal.
    offset = noisy - v
    cross = np.cross(offset, vertex_normals_np(v, f))
    assert np.abs(cross).max() < 1e-9 * max(1.0, np.abs(offset).max())
    # σ = 0.2 mean edges: the RMS offset is that, up to sampling (642 draws).
    rms = np.sqrt(np.mean(np.sum(offset**2, 1)))
    assert rms == pytest.approx(0.2 * mean_edge_length(v, f), rel=0.15)
    iso = protocol.benchmark_noise(v, f, 0.2, seed=7, direction="isotropic")
    assert not np.allclose(iso, noisy)


def test_noise_config_is_the_same_protocol():
    cfg = protocol.benchmark_noise_config()
    assert cfg.kinds == (protocol.NOISE_KIND,)
    assert tuple(cfg.edge_levels) == protocol.NOISE_LEVELS == (0.1, 0.2, 0.3)
    assert cfg.p_edge == 1.0 and cfg.p_normal == 1.0


def test_crop_keeps_small_meshes_and_cuts_a_connected_patch():
    v, f = icosphere(3)  # 1280 faces
    same = protocol.crop(v, f, 2000)
    assert same[0] is v and same[1] is f
    assert protocol.crop(v, f, 0)[1] is f
    pv, pf = protocol.crop(v, f, 300)
    assert pf.shape == (300, 3) and pf.max() == len(pv) - 1
    again = protocol.crop(v, f, 300)
    np.testing.assert_array_equal(pf, again[1])
    np.testing.assert_array_equal(pv, again[0])
    assert protocol.MAX_FACES == 15_000


def test_shared_meshes_dir_reads_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("DMD_SHARED_MESHES", raising=False)
    monkeypatch.setenv(protocol.SHARED_MESHES_ENV, str(tmp_path))
    assert protocol.shared_meshes_dir() == tmp_path
    assert protocol.validation_dir() == tmp_path / "train"
    monkeypatch.delenv(protocol.SHARED_MESHES_ENV)
    assert protocol.shared_meshes_dir().parts[-2:] == ("shared", "meshes")
    # The old name still works, and says so.
    monkeypatch.setenv("DMD_SHARED_MESHES", str(tmp_path / "old"))
    with pytest.warns(DeprecationWarning, match=protocol.SHARED_MESHES_ENV):
        assert protocol.shared_meshes_dir() == tmp_path / "old"


def test_mesh_files_and_validation_split(tmp_path):
    from dmd_jax.data import real

    v, f = icosphere(1)
    names = ["b.obj", "a.off", "c.ply", "d.stl", "e.OBJ"]
    for name in names:
        save_mesh(tmp_path / name, v, f)
    (tmp_path / "notes.txt").write_text("not a mesh")
    assert [p.name for p in protocol.mesh_files(tmp_path)] == sorted(names)
    assert [p.name for p in protocol.mesh_files(tmp_path, skip=("a.off",))] == sorted(
        set(names) - {"a.off"}
    )
    with pytest.raises(ValueError, match="x.obj"):
        protocol.mesh_files(tmp_path, skip=("x.obj",))
    with pytest.raises(FileNotFoundError, match=protocol.SHARED_MESHES_ENV):
        protocol.mesh_files(tmp_path / "none")
    val = protocol.validation_files(tmp_path)
    assert val == real.mesh_files(tmp_path, "val")
    assert all(real.is_validation(p.name) for p in val)
    assert set(protocol.MESH_SUFFIXES) == {".obj", ".off", ".ply", ".stl"}


def test_methods_and_labels():
    assert protocol.benchmark_methods() == (
        *protocol.REFERENCE_METHODS,
        *baselines.REGISTRY,
        "cnr",
        "dmd",
    )
    # Every method anyone can name has a label, in both label sets.
    every = {*protocol.METHODS, *protocol.REFERENCE_METHODS, "noisy", "dmd_x2"}
    assert every <= set(protocol.LABELS) and every <= set(protocol.PAPER_LABELS)
    assert protocol.label("dmd") == "DMD-Net" and protocol.label("new") == "new"
    assert protocol.PAPER_LABELS["l0"] == "L0M" and protocol.LABELS["l0"] == "L0"


def test_quality_conditions_keep_the_benchmark_levels_and_seeds():
    from dmd_jax import protocol

    labels = [c.label for c in protocol.QUALITY_CONDITIONS]
    assert labels == ["0.1", "0.2", "0.3", "0.6", "impulse 0.6"]
    gauss = protocol.NoiseCondition("gaussian", 0.2)
    # A Gaussian condition is the benchmark noise, seed and draws alike.
    assert protocol.condition_seed("a.obj", gauss) == protocol.noise_seed("a.obj", 0.2)
    impulse = protocol.NoiseCondition("impulse", 0.2)
    assert protocol.condition_seed("a.obj", impulse) != protocol.noise_seed("a.obj", 0.2)
    assert protocol.parse_condition("impulse:0.6") == protocol.NoiseCondition("impulse", 0.6)
    assert protocol.parse_condition("0.3") == protocol.NoiseCondition("gaussian", 0.3)
    for bad in ("uniform:0.2", "impulse:x", "-1", "nan"):
        with pytest.raises(ValueError, match="noise condition"):
            protocol.parse_condition(bad)


def test_impulse_condition_moves_thirty_percent_of_vertices_along_their_normals():
    import trimesh

    from dmd_jax import protocol
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.noise import vertex_normals_np

    mesh = trimesh.creation.icosphere(3)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    condition = protocol.NoiseCondition("impulse", 0.6)
    noisy = protocol.condition_noise(v, f, condition, 7)
    d = noisy - v
    moved = np.linalg.norm(d, axis=1) > 1e-12
    assert 0.25 < moved.mean() < 0.35  # δ(0.15, 0.15)
    np.testing.assert_allclose(
        np.linalg.norm(d[moved], axis=1), 0.6 * mean_edge_length(v, f), rtol=1e-5
    )
    normals = vertex_normals_np(v, f)
    cos = np.abs(np.sum(d[moved] * normals[moved], axis=1)) / np.linalg.norm(d[moved], axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=1e-6)
    gauss = protocol.NoiseCondition("gaussian", 0.2)
    np.testing.assert_array_equal(
        protocol.condition_noise(v, f, gauss, 3), protocol.benchmark_noise(v, f, 0.2, 3)
    )
