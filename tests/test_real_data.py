"""Real training meshes: the fixed validation split and connected patches."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere, skip_without_shared
from scipy.sparse.csgraph import connected_components

from dmd_jax.data import real
from dmd_jax.data.repair import decimate
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
        skip_without_shared(folder)
    val = real.validation_names(folder)
    n = len(real.mesh_files(folder, "all"))
    assert 0.1 < len(val) / n < 0.25


def test_coarse_copies_are_whole_decimated_meshes_of_the_training_split(tmp_path):
    """`coarse_copies`: each training file decimated to every count it exceeds by half,
    closed, topology kept, with larger angles between its faces than the fine mesh."""
    from dmd_jax.mesh import edge_dihedral_angles
    from dmd_jax.topology import face_adjacency

    v, f = icosphere(4)  # 5120 faces, 2562 vertices
    names = [n for n in (f"m{i:02d}.ply" for i in range(20)) if not real.is_validation(n)][:2]
    held = next(n for n in (f"v{i:02d}.ply" for i in range(200)) if real.is_validation(n))
    for name in (*names, held):
        save_mesh(tmp_path / name, v, f)
    copies = real.coarse_copies(tmp_path, "train", face_counts=(3000, 500, 4000))
    # 4000 is not exceeded by half: two counts per training file, none of the held-out one.
    assert sorted(c[1].shape[0] for c in copies) == [500, 500, 3000, 3000]
    fine_angle = np.median(edge_dihedral_angles(v, f)[2])
    for cv, cf in copies:
        assert cf.dtype == np.int32 and cf.min() == 0 and cf.max() == cv.shape[0] - 1
        assert cv.shape[0] - cf.shape[0] // 2 == 2  # still a closed genus-0 surface
        a, _ = face_adjacency(cf, cv.shape[0])
        assert a.shape[0] == cf.shape[0] * 3 // 2  # every edge shared by two faces
        # On a sphere the angle between neighbours grows as the edge, 1/sqrt(faces):
        # 1.3x at 3000 faces, 3.2x at 500 (quadric collapse leaves them uneven).
        angle = np.median(edge_dihedral_angles(cv, cf)[2])
        assert angle > (1.1 if cf.shape[0] == 3000 else 2.5) * fine_angle
        assert np.abs(np.linalg.norm(cv, axis=1) - 1.0).max() < 0.05  # on the sphere
    # A mesh at or under the count comes back as it is.
    same_v, same_f = decimate(v, f, 6000)
    np.testing.assert_array_equal(same_f, f)
    np.testing.assert_array_equal(same_v, v)


def test_training_sets_add_the_coarse_copies(tmp_path):
    from dmd_jax.config import DataConfig
    from dmd_jax.data.dataset import make_dataset
    from dmd_jax.data.training_sets import training_sets

    v, f = icosphere(4)
    folder = tmp_path / "real"
    folder.mkdir()
    name = next(n for n in (f"m{i:02d}.ply" for i in range(20)) if not real.is_validation(n))
    held = next(n for n in (f"v{i:02d}.ply" for i in range(200)) if real.is_validation(n))
    for n in (name, held):
        save_mesh(folder / n, v, f)
    data = tmp_path / "data"
    make_dataset(
        data,
        per_category=2,
        categories=("blocks",),
        test_inter=(),
        seed=0,
        workers=1,
        min_vertices=300,
        max_vertices=600,
        progress=False,
    )
    d = DataConfig(dataset_dir=str(data), real_root=str(folder), eval_meshes_per_split=0)
    plain = training_sets(d, seed=0)
    coarse = training_sets(d.replace(real_coarse_faces=(1000,)), seed=0)
    assert len(coarse.train) == len(plain.train) + 1
    assert coarse.train[-1][1].shape[0] == 1000
    assert len(coarse.evals["val"]) == len(plain.evals["val"])
    with pytest.raises(ValueError, match="real_coarse_faces must be an integer >= 4"):
        d.replace(real_coarse_faces=(1000, 0))
