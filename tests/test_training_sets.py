"""Generated training meshes: the stress family and simulated scans (`data.training_sets`)."""

import numpy as np
import pytest
import trimesh

from dmd_jax.config import DataConfig
from dmd_jax.data import training_sets as ts
from dmd_jax.data.stress import STRESS_SHAPES
from dmd_jax.pipeline import make_examples


def test_stress_meshes_copies_every_shape():
    meshes = ts.stress_meshes(2)
    assert len(meshes) == 2 * len(STRESS_SHAPES)
    for v, f in meshes:
        assert v.shape[1] == 3 and f.shape[1] == 3 and len(f) > 0
    assert ts.stress_meshes(0) == []


def test_scan_meshes_are_open_range_images_with_views():
    sphere = trimesh.creation.icosphere(3)
    mesh = (np.asarray(sphere.vertices), np.asarray(sphere.faces))
    scans = ts.scan_meshes([mesh, mesh], 2, resolution=48, seed=5)
    assert len(scans) == 4
    for clean, faces, view in scans:
        assert faces.shape[0] >= ts.MIN_SCAN_FACES
        assert np.isclose(np.linalg.norm(view), 1.0)
        # Every scan point lies on the sphere (the clean surface), and the scan is open.
        radius = np.linalg.norm(clean, axis=1)
        assert np.all(np.abs(radius - 1.0) < 0.02)
        edges = trimesh.Trimesh(clean, faces, process=False).edges_sorted
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert np.any(counts == 1)
    # Same seed, same scans; the views differ between meshes and draws.
    again = ts.scan_meshes([mesh, mesh], 2, resolution=48, seed=5)
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(scans, again, strict=True))
    assert len({tuple(np.round(s[2], 6)) for s in scans}) == 4
    # The pipeline keeps the view (scanner noise along it).
    examples = make_examples(scans[:1])
    assert examples[0].view is not None


@pytest.mark.parametrize(
    "field, value",
    [("stress_copies", -1), ("stress_copies", 65), ("scan_views", 17), ("scan_resolution", 4)],
)
def test_generated_set_bounds(field, value):
    with pytest.raises(ValueError, match=field):
        DataConfig(**{field: value})


def test_real_mesh_folder_skips_temporary_files(tmp_path):
    from dmd_jax.data.real import mesh_files
    from dmd_jax.io import save_mesh

    sphere = trimesh.creation.icosphere(1)
    save_mesh(tmp_path / "a.obj", sphere.vertices, sphere.faces)
    # What an interrupted atomic write leaves beside its output.
    (tmp_path / ".b.obj.1a2b3c4d.obj").write_text("v 0 0 0\n")
    assert [p.name for p in mesh_files(tmp_path, "all")] == ["a.obj"]
