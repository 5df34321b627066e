"""The command-line edges of issue 30: resuming a folder run, output folders that do
not exist yet, and `evaluate` on a mesh whose vertex order differs from the source."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import icosphere

from dmd_jax.cli import main
from dmd_jax.io import load_mesh, save_mesh


def run(capsys, *argv):
    """`dmd-jax ARGV`: `(exit code, stdout, stderr)`."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def meshes(tmp_path):
    v, f = icosphere(2)
    rng = np.random.default_rng(30)
    noisy = v + 0.01 * rng.standard_normal(v.shape)
    save_mesh(tmp_path / "clean.off", v, f)
    save_mesh(tmp_path / "noisy.off", noisy, f)
    return tmp_path, v, f, noisy


# --------------------------------------------------------------------------------------
# evaluate: another vertex order with equal counts
# --------------------------------------------------------------------------------------


def test_evaluate_matches_an_stl_output_through_its_faces(capsys, meshes):
    tmp, v, f, noisy = meshes
    save_mesh(tmp / "noisy.stl", noisy, f)  # STL renumbers the vertices
    v_stl, f_stl = load_mesh(tmp / "noisy.stl")
    assert len(v_stl) == len(v) and not (f_stl == f).all()
    code, out, err = run(
        capsys,
        "evaluate",
        "--gt",
        tmp / "clean.off",
        "--mesh",
        tmp / "noisy.off",
        tmp / "noisy.stl",
        "--json",
    )
    assert code == 0, err
    assert "noisy.stl: vertices matched to" in err and "through the faces" in err
    import json

    off_row, stl_row = json.loads(out)
    # The same scores, to the float32 rounding STL applies to the coordinates.
    for key in ("vertex", "normal_deg", "chamfer"):
        assert stl_row[key] == pytest.approx(off_row[key], rel=1e-4)


def test_evaluate_matches_a_reordered_copy_by_position(capsys, meshes):
    tmp, v, f, _ = meshes
    perm = np.random.default_rng(1).permutation(len(v))
    inverse = np.argsort(perm)
    faces = inverse[f][np.random.default_rng(2).permutation(len(f))]  # faces shuffled too
    save_mesh(tmp / "shuffled.obj", v[perm], faces)
    code, out, err = run(
        capsys, "evaluate", "--gt", tmp / "clean.off", "--mesh", tmp / "shuffled.obj"
    )
    assert code == 0, err
    assert "matched to" in err and "by position" in err


def test_evaluate_names_the_vertex_order_when_it_cannot_match(capsys, meshes):
    tmp, v, f, noisy = meshes
    perm = np.random.default_rng(1).permutation(len(v))
    inverse = np.argsort(perm)
    faces = inverse[f][np.random.default_rng(2).permutation(len(f))]
    save_mesh(tmp / "other.obj", noisy[perm], faces)  # moved and renumbered: no match
    code, out, err = run(capsys, "evaluate", "--gt", tmp / "clean.off", "--mesh", tmp / "other.obj")
    assert code == 2 and out == ""
    (line,) = err.strip().splitlines()
    assert "other.obj: the counts match" in line and "but the vertex order does not" in line
    assert f"{len(v)} vs {len(v)} vertices" in line
