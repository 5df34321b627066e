"""Real training meshes: the fixed validation split and connected patches."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere
from scipy.sparse.csgraph import connected_components

from dmd_jax.data import real
from dmd_jax.io import save_mesh


def test_validation_split_is_a_pure_function_of_the_name():
    names = [f"mesh_{i}.ply" for i in range(2000)]
    held = [n for n in names if real.is_validation(n)]
    assert 0.12 < len(held) / len(names) < 0.18
    assert held == [n for n in names if real.is_validation("/some/dir/" + n)]


def test_split_files_partition_the_folder(tmp_path):
    v, f = icosphere(1)
    for i in range(40):
        save_mesh(tmp_path / f"m{i:02d}.ply", v, f)
    (tmp_path / "README.md").write_text("not a mesh")
    train = real.mesh_files(tmp_path, "train")
    val = real.mesh_files(tmp_path, "val")
    assert sorted(train + val) == real.mesh_files(tmp_path, "all")
    assert len(real.mesh_files(tmp_path, "all")) == 40
    assert not set(train) & set(val)
    with pytest.raises(ValueError, match="unknown split"):
        real.mesh_files(tmp_path, "test")
    with pytest.raises(FileNotFoundError):
        real.mesh_files(tmp_path / "missing", "train")


def test_patches_are_connected_bounded_and_reindexed():
    v, f = icosphere(4)  # 5120 faces
    rng = np.random.default_rng(0)
    patches = real.mesh_patches(v, f, max_faces=1000, n_patches=4, rng=rng)
    assert len(patches) == 4
    for pv, pf in patches:
        assert pf.shape[0] == 1000
        assert pf.min() == 0 and pf.max() == pv.shape[0] - 1
        assert np.unique(pf).shape[0] == pv.shape[0]  # no unreferenced vertex
        adj = real.face_adjacency_matrix(pf, pv.shape[0])
        assert connected_components(adj, directed=False)[0] == 1
    # A mesh under the limit comes back whole.
    ((whole_v, whole_f),) = real.mesh_patches(v, f, max_faces=10_000, n_patches=3, rng=rng)
    assert whole_f.shape == f.shape


def test_shared_training_folder_has_a_validation_split(shared_meshes):
    folder = shared_meshes / "train"
    if not folder.is_dir():
        pytest.skip("shared/meshes/train is not present")
    val = real.validation_names(folder)
    n = len(real.mesh_files(folder, "all"))
    assert 0.1 < len(val) / n < 0.25
