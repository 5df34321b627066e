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


# --------------------------------------------------------------------------------------
# Folder runs: Ctrl-C then --skip-existing; output folders that do not exist yet
# --------------------------------------------------------------------------------------


@pytest.fixture
def folder(tmp_path):
    v, f = icosphere(1)
    src = tmp_path / "scans"
    src.mkdir()
    for name in ("a.off", "b.obj", "c.ply"):
        save_mesh(src / name, v, f)
    return src


def test_interrupted_folder_run_resumes_with_skip_existing(tmp_path, capsys, folder, monkeypatch):
    import dmd_jax.api

    real = dmd_jax.api.denoise_with
    calls = []

    def interrupt_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(dmd_jax.api, "denoise_with", interrupt_on_second)
    out = tmp_path / "out"
    code, _, err = run(capsys, "denoise", folder, "--out", out, "--method", "laplacian")
    assert code == 130
    assert "interrupted after 1 of 3 meshes" in err and "--skip-existing to resume" in err
    assert [p.name for p in out.iterdir()] == ["a.off"]  # complete, no temp file
    first = (out / "a.off").read_bytes()

    # The same command again refuses to clobber; with --skip-existing it resumes.
    code, _, err = run(capsys, "denoise", folder, "--out", out, "--method", "laplacian")
    assert code == 2 and "a.off: already exists" in err
    monkeypatch.setattr(dmd_jax.api, "denoise_with", real)
    code, stdout, err = run(
        capsys, "denoise", folder, "--out", out, "--method", "laplacian", "--skip-existing"
    )
    assert code == 0, err
    assert "--skip-existing: 1 of 3 outputs exist already" in err
    assert sorted(p.name for p in out.iterdir()) == ["a.off", "b.obj", "c.ply"]
    assert (out / "a.off").read_bytes() == first  # left as it was
    assert "a.off" not in stdout and "2 meshes in" in stdout


def test_skip_existing_and_overwrite_contradict(tmp_path, capsys, folder):
    code, _, err = run(
        capsys, "denoise", folder, "--out", tmp_path / "o", "--skip-existing", "--overwrite"
    )
    assert code == 2 and "contradict" in err


def test_out_dir_is_created_and_o_needs_parents(tmp_path, capsys, folder):
    # --out DIR: created (nested too), as its help says.
    out = tmp_path / "new" / "deeper"
    code, _, err = run(capsys, "denoise", folder, "--out", out, "--method", "laplacian")
    assert code == 0, err
    assert len(list(out.iterdir())) == 3
    # -o FILE into a missing folder: refused before any work, with the flag to pass ...
    target = tmp_path / "missing" / "sub" / "a.off"
    code, _, err = run(capsys, "denoise", folder / "a.off", "-o", target, "--method", "laplacian")
    assert code == 2 and "output directory does not exist (pass --parents" in err
    assert not (tmp_path / "missing").exists()
    # ... which creates it.
    code, _, err = run(
        capsys, "denoise", folder / "a.off", "-o", target, "--method", "laplacian", "--parents"
    )
    assert code == 0, err
    assert target.is_file()
    for command, extra in (("add-noise", ["--level", "0.01"]), ("render", [])):
        dst = tmp_path / f"made_by_{command}" / ("x.off" if command == "add-noise" else "x.png")
        code, _, err = run(capsys, command, folder / "a.off", "-o", dst, *extra, "--parents")
        assert code == 0, err
        assert dst.is_file()


def test_help_documents_the_folder_edges(capsys):
    with pytest.raises(SystemExit):
        main(["denoise", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--skip-existing" in text and "resume" in text
    assert "--parents" in text and "--out DIR is always created when missing" in text
    assert "exits with 1 and a summary" in text


def test_render_gt_matches_an_stl_output_too(capsys, meshes):
    tmp, v, f, noisy = meshes
    save_mesh(tmp / "noisy.stl", noisy, f)
    code, _, err = run(
        capsys, "render", tmp / "noisy.stl", "--gt", tmp / "clean.off", "-o", tmp / "r.png"
    )
    assert code == 0, err
    assert "vertices matched to" in err and (tmp / "r.png").is_file()
