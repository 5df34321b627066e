"""Hostile and careless inputs (issue 31): no silent wrong answer, no traceback.

One test (or a few) per numbered case of the issue, named `test_case<N>_...`, each
failing before the fix and passing after; the fuzz test of the readers is in
`tests/test_fuzz.py`. Everything runs on tiny meshes, without a network pass, except
where the case is about the denoise command itself.
"""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np
import pytest
from conftest import tetrahedron

from dmd_jax.io import load_mesh, save_mesh

BOM = b"\xef\xbb\xbf"
TET_V, TET_F = tetrahedron()
# A tetrahedron plus one unused vertex at the end: a one-off vertex shift is silent.
TET5_V = np.concatenate([TET_V, [[9.0, 9.0, 9.0]]])


def _obj(v, f) -> bytes:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    lines += ["f " + " ".join(str(int(i) + 1) for i in face) for face in f]
    return ("\n".join(lines) + "\n").encode()


def _off(v, f, *, declared_faces=None) -> bytes:
    n_f = len(f) if declared_faces is None else declared_faces
    lines = ["OFF", f"{len(v)} {n_f} 0"]
    lines += [f"{x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    lines += [f"{len(face)} " + " ".join(str(int(i)) for i in face) for face in f]
    return ("\n".join(lines) + "\n").encode()


def _ply_ascii(v, f) -> bytes:
    head = (
        "ply\nformat ascii 1.0\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = [f"{x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    body += [f"{len(face)} " + " ".join(str(int(i)) for i in face) for face in f]
    return (head + "\n".join(body) + "\n").encode()


def _load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # triangulation notes
        return load_mesh(path)


# --------------------------------------------------------------------------------------
# 1. A UTF-8 byte-order mark
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "suffix, data",
    [
        (".obj", _obj(TET5_V, TET_F)),
        (".obj", _obj(TET_V, TET_F)),
        (".off", _off(TET5_V, TET_F)),
        (".ply", _ply_ascii(TET5_V, TET_F)),
    ],
    ids=["obj-unused-vertex", "obj", "off", "ply"],
)
def test_case1_utf8_bom_is_ignored(tmp_path, suffix, data):
    path = tmp_path / f"bom{suffix}"
    path.write_bytes(BOM + data)
    v, f = _load(path)
    expected_v = TET5_V if b"9.0" in data else TET_V
    np.testing.assert_array_equal(v, expected_v)
    np.testing.assert_array_equal(f, TET_F)


def test_case1_utf8_bom_before_ascii_stl(tmp_path):
    import trimesh

    text = trimesh.Trimesh(TET_V, TET_F, process=False).export(file_type="stl_ascii")
    path = tmp_path / "bom.stl"
    path.write_bytes(BOM + text.encode())
    v, f = _load(path)
    assert len(v) == 4 and len(f) == 4


# --------------------------------------------------------------------------------------
# 4. Writers round-trip every finite float64 exactly
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply"])
@pytest.mark.parametrize("scale", [1e-300, 1e-160, 1e-16, 1.0, 1e150, 1e300])
def test_case4_writers_round_trip_float64_exactly(tmp_path, suffix, scale):
    rng = np.random.default_rng(4)
    v = rng.standard_normal((5, 3)) * scale
    path = save_mesh(tmp_path / f"m{suffix}", v, TET_F)
    v2, f2 = load_mesh(path)
    np.testing.assert_array_equal(v2, v)  # bit for bit, unused vertex 4 included
    np.testing.assert_array_equal(f2, TET_F)


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply"])
def test_case4_extreme_floats_round_trip(tmp_path, suffix):
    # The smallest subnormal, the largest finite, -0.0 and a value with 17 digits.
    v = np.array(
        [[5e-324, -0.0, 1.7976931348623157e308], [0.1, 1 / 3, -2.2250738585072014e-308]]
        + TET_V[2:].tolist()
        + [[9.0, 9.0, 9.0]]
    )
    path = save_mesh(tmp_path / f"x{suffix}", v, TET_F)
    v2, _ = load_mesh(path)
    assert v2.tobytes() == v.tobytes()  # -0.0 keeps its sign too


# --------------------------------------------------------------------------------------
# 5. A file that contradicts its own header
# --------------------------------------------------------------------------------------


def test_case5_off_with_more_faces_than_declared_is_refused(tmp_path):
    path = tmp_path / "more.off"
    path.write_bytes(_off(TET_V, TET_F, declared_faces=3))
    with pytest.raises(ValueError, match=r"more.off: line 10: data after the 3 faces"):
        load_mesh(path)


def test_case5_ply_with_more_faces_than_declared_is_refused(tmp_path):
    data = _ply_ascii(TET_V, TET_F).replace(b"element face 4", b"element face 3")
    path = tmp_path / "more.ply"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=r"more.ply: 4 values after the last element"):
        load_mesh(path)
    binary = _ply_binary(TET_V, [list(f) for f in TET_F]).replace(
        b"element face 4", b"element face 3"
    )
    path.write_bytes(binary)
    with pytest.raises(ValueError, match=r"more.ply: 13 bytes after the last element"):
        load_mesh(path)


# --------------------------------------------------------------------------------------
# 14. Valid PLY variants; FIFOs and symlink loops; a header that hides its faces
# --------------------------------------------------------------------------------------


def _ply_binary(v, faces, *, order="<", extra_list=False) -> bytes:
    fmt = {"<": "binary_little_endian", ">": "binary_big_endian"}[order]
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(v)}\nproperty float x\n"
        f"property float y\nproperty float z\nelement face {len(faces)}\n"
        "property list uchar int vertex_indices\n"
        + ("property list uchar float texcoord\n" if extra_list else "")
        + "end_header\n"
    )
    body = np.asarray(v, order + "f4").tobytes()
    for face in faces:
        body += struct.pack(f"{order}B{len(face)}i", len(face), *face)
        if extra_list:
            body += struct.pack(f"{order}B6f", 6, *range(6))
    return head.encode() + body


SQUARE_PYRAMID_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], float)
SQUARE_PYRAMID = [[3, 2, 1, 0], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]
SQUARE_PYRAMID_TRIS = [[3, 2, 1], [3, 1, 0], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]


@pytest.mark.parametrize("order", ["<", ">"])
def test_case14_binary_ply_mixing_triangles_and_quads(tmp_path, order):
    path = tmp_path / "mixed.ply"
    path.write_bytes(_ply_binary(SQUARE_PYRAMID_V, SQUARE_PYRAMID, order=order))
    with pytest.warns(UserWarning, match="triangulated 1 polygon faces"):
        v, f = load_mesh(path)
    np.testing.assert_array_equal(v, SQUARE_PYRAMID_V)
    np.testing.assert_array_equal(f, SQUARE_PYRAMID_TRIS)


def test_case14_ply_with_two_face_lists(tmp_path):
    # A texture-coordinate list after the index list, in ASCII and in binary.
    head = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 4\nproperty list uchar int vertex_indices\n"
        "property list uchar float texcoord\nend_header\n"
    )
    body = [" ".join(map(repr, row)) for row in TET_V.tolist()]
    body += [f"3 {a} {b} {c} 6 0 0 1 0 0 1" for a, b, c in TET_F]
    path = tmp_path / "uv.ply"
    path.write_text(head + "\n".join(body) + "\n")
    v, f = load_mesh(path)
    np.testing.assert_array_equal(v, TET_V)
    np.testing.assert_array_equal(f, TET_F)
    path.write_bytes(_ply_binary(TET_V, [list(x) for x in TET_F], extra_list=True))
    v, f = load_mesh(path)
    np.testing.assert_array_equal(v, TET_V)
    np.testing.assert_array_equal(f, TET_F)


def test_case14_ply_size_guard_cannot_be_bypassed(tmp_path):
    # A face count that is not a plain integer used to slip past the size guard and
    # be reported as a point cloud; a count beyond the file's size is refused early.
    path = tmp_path / "odd.ply"
    path.write_bytes(_ply_ascii(TET_V, TET_F).replace(b"element face 4", b"element face -4"))
    with pytest.raises(ValueError, match="header line 7: an element needs a name and a count"):
        load_mesh(path)
    path.write_bytes(_ply_ascii(TET_V, TET_F).replace(b"element face 4", b"element face 4e9"))
    with pytest.raises(ValueError, match="an element needs a name and a count"):
        load_mesh(path)
    path.write_bytes(
        _ply_ascii(TET_V, TET_F).replace(b"element face 4", b"element face 10000000000")
    )
    with pytest.raises(ValueError, match="more than the file's .* bytes can hold"):
        load_mesh(path)


def test_case14_fifo_is_not_a_missing_file(tmp_path):
    path = tmp_path / "pipe.obj"
    os.mkfifo(path)
    with pytest.raises(ValueError, match="pipe.obj: is a FIFO"):
        load_mesh(path)  # and does not block reading it


def test_case14_symlink_loop_is_not_a_missing_file(tmp_path):
    path = tmp_path / "loop.obj"
    os.symlink(path, path)
    with pytest.raises(OSError, match="loop.obj: cannot open it .*symbolic links") as info:
        load_mesh(path)
    assert not isinstance(info.value, FileNotFoundError)
    dangling = tmp_path / "dangling.obj"
    os.symlink(tmp_path / "gone.obj", dangling)
    with pytest.raises(FileNotFoundError, match="dangling.obj: a symbolic link to .*gone.obj"):
        load_mesh(dangling)


# --------------------------------------------------------------------------------------
# CLI helpers
# --------------------------------------------------------------------------------------


def run(capsys, *argv):
    """`dmd-jax ARGV`: `(exit code, stdout, stderr)`."""
    from dmd_jax.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(err: str, *words: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("note: ")]
    assert len(lines) == 1 and "error: " in lines[0], err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


@pytest.fixture
def sphere_files(tmp_path):
    from conftest import icosphere

    v, f = icosphere(2)
    save_mesh(tmp_path / "gt.off", v, f)
    return tmp_path, v, f


# --------------------------------------------------------------------------------------
# 3. evaluate --json is valid JSON and never scores a ruined or degenerate mesh well
# --------------------------------------------------------------------------------------


def _strict_json(text: str):
    import json

    def refuse(name):
        raise AssertionError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture
def float32_jax():
    """JAX without float64, as the command line runs (conftest turns float64 on)."""
    import jax

    jax.config.update("jax_enable_x64", False)
    yield
    jax.config.update("jax_enable_x64", True)


def test_case3_evaluate_json_of_a_far_off_mesh_is_valid_and_honest(
    capsys, sphere_files, float32_jax
):
    tmp, v, f = sphere_files
    save_mesh(tmp / "big.off", v * 1e39, f)
    code, out, err = run(
        capsys, "evaluate", "--gt", tmp / "gt.off", "--mesh", tmp / "big.off", "--json"
    )
    assert code == 0, err
    (row,) = _strict_json(out)
    # 1e39 times too large: a huge vertex and chamfer error (not Infinity, not 0.0), and
    # the normals of a uniformly scaled copy are the ground truth's (not 90°).
    assert 1e76 < row["vertex"] < 1e79 and 1e76 < row["chamfer"] < 1e79
    assert row["normal_deg"] < 1e-3


@pytest.mark.parametrize("scale", [1e-15, 1e15, 1e30])
def test_case3_scaled_copy_has_the_ground_truths_normals(scale, float32_jax):
    from conftest import icosphere

    from dmd_jax.metrics import face_normal_errors_deg, mesh_metrics

    v, f = icosphere(2)
    assert mesh_metrics(v * scale, v, f)["normal_deg"] < 1e-3
    assert face_normal_errors_deg(v * scale, v, f).max() < 1e-2


def test_case3_evaluate_refuses_an_overflowing_error(capsys, sphere_files):
    tmp, v, f = sphere_files
    save_mesh(tmp / "huge.off", v * 1e300, f)
    code, out, err = run(
        capsys, "evaluate", "--gt", tmp / "gt.off", "--mesh", tmp / "huge.off", "--json"
    )
    assert code == 2 and out == ""
    _one_line_error(err, "huge.off", "overflows float64")


def test_case3_zero_area_ground_truth_is_refused_not_a_perfect_score(capsys, sphere_files):
    from dmd_jax.metrics import mesh_metrics

    tmp, v, f = sphere_files
    flat = v.copy()
    flat[:, 1:] = 0.0  # every face collapses onto the x axis
    save_mesh(tmp / "flat.off", flat, f)
    assert np.isnan(mesh_metrics(flat, flat, f)["normal_deg"])
    code, out, err = run(
        capsys, "evaluate", "--gt", tmp / "flat.off", "--mesh", tmp / "flat.off", "--json"
    )
    assert code == 2 and out == ""
    _one_line_error(err, "flat.off", "no face of the ground truth has a non-zero area")
    # A prediction collapsed to zero area is scored as bad, not perfect.
    m = mesh_metrics(np.zeros_like(v), v, f)
    assert m["normal_deg"] > 80 and m["chamfer"] > 0.1


# --------------------------------------------------------------------------------------
# 8. add-noise --seed beyond 64 bits
# --------------------------------------------------------------------------------------


def test_case8_huge_seed_is_a_clear_error(capsys, sphere_files):
    import dmd_jax

    tmp, v, f = sphere_files
    code, _, err = run(
        capsys,
        "add-noise",
        tmp / "gt.off",
        "-o",
        tmp / "n.off",
        "--level",
        "0.01",
        "--seed",
        "1180591620717411303424",
    )
    assert code == 2
    _one_line_error(err, "seed must lie in [-2**63, 2**63)", "1180591620717411303424")
    assert not (tmp / "n.off").exists()
    with pytest.raises(ValueError, match="seed must lie in"):
        dmd_jax.add_noise(2**70, v, f, "gaussian", 0.01)
    dmd_jax.add_noise(2**63 - 1, v, f, "gaussian", 0.01)  # the largest seed works


# --------------------------------------------------------------------------------------
# 9. render --panel-size is bounded
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", ["1000", "150", "0", "-1", "nan"])
def test_case9_render_panel_size_is_bounded(capsys, sphere_files, size):
    tmp, _, _ = sphere_files
    for out in ("r.png", "r.html"):
        code, _, err = run(capsys, "render", tmp / "gt.off", "-o", tmp / out, "--panel-size", size)
        assert code == 2
        _one_line_error(err, "--panel-size must be in [0.5, 20] inches")
        assert not (tmp / out).exists()


def test_case9_render_meshes_refuses_a_huge_canvas(sphere_files):
    from dmd_jax.render import render_meshes

    tmp, v, f = sphere_files
    with pytest.raises(ValueError, match="panel_size must be in"):
        render_meshes([(v, f)], tmp / "x.png", panel_size=150)
    with pytest.raises(ValueError, match="M pixels, over the 100 M limit"):
        render_meshes([(v, f)] * 40, tmp / "x.png", panel_size=20)
    assert not (tmp / "x.png").exists()


# --------------------------------------------------------------------------------------
# 6, 7, 10. Weights files: nested JSON, tiny filter sigmas, unbounded counts
# --------------------------------------------------------------------------------------


def _bundled_payload() -> dict:
    from flax import serialization

    from dmd_jax.checkpoints import pretrained_path

    return serialization.msgpack_restore(pretrained_path().read_bytes())


def _weights_with(tmp_path, payload: dict, name: str = "w.msgpack"):
    from flax import serialization

    path = tmp_path / name
    path.write_bytes(serialization.msgpack_serialize(payload))
    return path


def _with_model_field(payload: dict, field: str, value) -> dict:
    import json

    config = json.loads(payload["config"])
    config["model"][field] = value
    return {**payload, "config": json.dumps(config)}


@pytest.mark.parametrize("section", ["config", "meta", "policy"])
def test_case6_deeply_nested_json_in_weights_is_one_value_error(tmp_path, capsys, section):
    from dmd_jax.checkpoints import load_weights

    payload = _bundled_payload()
    if section not in payload:
        pytest.skip(f"this weights format has no {section} section")
    payload[section] = "[" * 100_000 + "]" * 100_000
    path = _weights_with(tmp_path, payload)
    with pytest.raises(ValueError, match=f"w.msgpack: unreadable {section} .*nested too deeply"):
        load_weights(path)
    save_mesh(tmp_path / "t.off", TET_V, TET_F)
    code, _, err = run(
        capsys, "denoise", tmp_path / "t.off", "-o", tmp_path / "o.off", "--weights", path
    )
    assert code == 2
    _one_line_error(err, "w.msgpack", "nested too deeply")


@pytest.mark.parametrize("sigma", [1e-300, 0.0, 1e-5, 1e6, float("nan"), float("inf")])
def test_case7_filter_sigmas_out_of_range_are_refused_on_load(tmp_path, sigma):
    from dmd_jax.checkpoints import load_weights

    path = _weights_with(
        tmp_path, _with_model_field(_bundled_payload(), "filter_sigmas", [0.2, sigma])
    )
    with pytest.raises(ValueError, match=r"w.msgpack: unreadable config .*(filter_sigmas|finite)"):
        load_weights(path)


@pytest.mark.parametrize(
    "field, value",
    [
        ("filter_iterations", 10**7),
        ("vertex_iterations", 10**6),
        ("taubin_iterations", 10**6),
        ("width", 10**6),
        ("depth", 1000),
        ("fe_two_streams", 1000),
        ("n_agg", 1000),
        ("dense_layers", 1000),
        ("stn_width", 10**6),
        ("transformer_width", 10**6),
        ("filter_sigmas", [0.2] * 100),
        ("head_init_scale", 1e300),
        ("dropout", float("nan")),
    ],
)
def test_case10_every_count_of_a_weights_file_is_bounded(tmp_path, field, value):
    from dmd_jax.checkpoints import load_weights

    path = _weights_with(tmp_path, _with_model_field(_bundled_payload(), field, value))
    with pytest.raises(ValueError, match=f"w.msgpack: unreadable config .*{field}") as info:
        load_weights(path)
    assert "\n" not in str(info.value)


def test_case10_non_finite_numbers_anywhere_in_a_config_are_refused():
    from dmd_jax.config import ExperimentConfig, preset

    base = preset("small").to_dict()
    for section, field in [("train", "lr"), ("loss", "gamma_h"), ("train", "grad_clip")]:
        for bad in (float("inf"), float("nan"), 10**400):
            data = {**base, section: {**base[section], field: bad}}
            with pytest.raises(ValueError, match=f"{field}: expected a finite number"):
                ExperimentConfig.from_dict(data)


def test_case10_the_bounds_hold_every_preset():
    from dmd_jax.config import preset

    for name in ("paper", "small", "test"):
        preset(name)  # builds, so its model sits inside every bound


# --------------------------------------------------------------------------------------
# 11. SIGTERM during a write is handled like Ctrl-C
# --------------------------------------------------------------------------------------

_SIGTERM_MID_WRITE = """
import os, signal, sys, time
import dmd_jax.io.obj as io

def rows_then_sigterm(fh, row, rows):
    fh.write("v 0 0 0\\n")  # half a file on disk, then `timeout` or `docker stop`
    fh.flush()
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(10)  # the handler raises here; without one the process dies at once

io._write_rows = rows_then_sigterm
from dmd_jax.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_case11_sigterm_mid_write_leaves_no_temp_file(tmp_path):
    import subprocess
    import sys

    save_mesh(tmp_path / "in.off", TET_V, TET_F)  # before the writer is patched
    run_ = subprocess.run(
        [
            sys.executable,
            "-c",
            _SIGTERM_MID_WRITE,
            "add-noise",
            str(tmp_path / "in.off"),
            "-o",
            str(tmp_path / "out.obj"),
            "--level",
            "0.01",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run_.returncode == 143, (run_.returncode, run_.stderr)
    assert "dmd-jax add-noise: terminated" in run_.stderr
    assert "Traceback" not in run_.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.off"]  # no .out.obj.* left


# --------------------------------------------------------------------------------------
# 12. The output path is checked before any work
# --------------------------------------------------------------------------------------


@pytest.fixture
def no_work(monkeypatch):
    """Fails the test if a denoise, a noise draw or a mesh load starts."""
    import dmd_jax.api
    import dmd_jax.cli.add_noise
    import dmd_jax.cli.denoise

    def boom(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(dmd_jax.api, "denoise_with", boom)
    monkeypatch.setattr(dmd_jax.api, "add_noise", boom)
    monkeypatch.setattr(dmd_jax.cli.denoise, "_load_input", boom)
    monkeypatch.setattr(dmd_jax.cli.add_noise, "_load_input", boom)


@pytest.mark.parametrize(
    "output, words",
    [
        ("out.xyz", ["out.xyz: unknown mesh format '.xyz'"]),
        ("-", ["-o -: meshes are not written to stdout"]),
        ("missing/out.off", ["missing: output directory does not exist", "--parents"]),
        ("hard.off", ["hard.off: the output path is the input file"]),
        ("in.off/x.off", ["in.off: is not a directory"]),
    ],
    ids=["extension", "stdout", "missing-folder", "hard-link", "file-as-folder"],
)
@pytest.mark.parametrize("command", ["denoise", "add-noise"])
def test_case12_output_checked_before_the_work(tmp_path, capsys, no_work, output, words, command):
    save_mesh(tmp_path / "in.off", TET_V, TET_F)
    os.link(tmp_path / "in.off", tmp_path / "hard.off")
    dst = output if output == "-" else tmp_path / output
    extra = ["--level", "0.01"] if command == "add-noise" else ["--method", "laplacian"]
    code, _, err = run(capsys, command, tmp_path / "in.off", "-o", dst, "--overwrite", *extra)
    assert code == 2
    _one_line_error(err, *words)


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_case12_unwritable_folder_checked_before_the_work(tmp_path, capsys, no_work):
    save_mesh(tmp_path / "in.off", TET_V, TET_F)
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    code, _, err = run(capsys, "denoise", tmp_path / "in.off", "-o", locked / "o.off")
    assert code == 2
    _one_line_error(err, "cannot write in", "permission denied")


# --------------------------------------------------------------------------------------
# 13. A folder run goes on past a bad file and exits non-zero with a summary
# --------------------------------------------------------------------------------------


def test_case13_folder_mode_reports_a_bad_file_and_goes_on(tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a.off", "c.obj"):
        save_mesh(folder / name, TET_V, TET_F)
    (folder / "b.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # truncated
    code, out, err = run(
        capsys, "denoise", folder, "--out", tmp_path / "out", "--method", "laplacian"
    )
    assert code == 1
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.off", "c.obj"]
    assert "b.off: truncated" in err and "going on with the others" in err
    assert err.strip().splitlines()[-1] == (
        "dmd-jax denoise: 1 of 3 meshes failed (b.off); the others were written"
    )
    assert "2 meshes in" in out and "Traceback" not in err


# --------------------------------------------------------------------------------------
# 14. The rest: --level 1e308, coordinate overflow without raw NumPy warnings
# --------------------------------------------------------------------------------------


def test_case14_huge_noise_level_does_not_blame_the_output(tmp_path, capsys):
    save_mesh(tmp_path / "in.off", TET_V, TET_F)
    code, _, err = run(
        capsys, "add-noise", tmp_path / "in.off", "-o", tmp_path / "noisy.off", "--level", "1e308"
    )
    assert code == 2  # beyond add-noise's bound (issue 56), before any work
    _one_line_error(err, "--level must be from 0 to 1000, got 1e+308")
    assert "noisy.off" not in err and not (tmp_path / "noisy.off").exists()
    # Within the bound, noise on a mesh near float64's limit still overflows: said so.
    save_mesh(tmp_path / "huge.off", TET_V * 1e306, TET_F)
    code, _, err = run(
        capsys, "add-noise", tmp_path / "huge.off", "-o", tmp_path / "noisy.off", "--level", "500"
    )
    assert code == 2
    _one_line_error(err, "--level 500", "beyond float64's range")
    assert "noisy.off" not in err and not (tmp_path / "noisy.off").exists()


@pytest.mark.parametrize("scale", [1e300, 1e-300])
def test_case14_extreme_coordinates_give_no_raw_numpy_warnings(tmp_path, capsys, scale):
    save_mesh(tmp_path / "in.off", TET_V * scale, TET_F)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any RuntimeWarning of NumPy fails the test
        code, _, err = run(
            capsys, "add-noise", tmp_path / "in.off", "-o", tmp_path / "n.off", "--level", "0.01"
        )
    assert code == 0, err
    assert "Warning" not in err and "note:" not in err  # no face is degenerate


def test_case14_cli_does_not_call_a_hidden_face_count_a_point_cloud(tmp_path, capsys):
    path = tmp_path / "odd.ply"
    path.write_bytes(_ply_ascii(TET_V, TET_F).replace(b"element face 4", b"element face -4"))
    code, _, err = run(capsys, "add-noise", path, "-o", tmp_path / "noisy.off", "--level", "0.01")
    assert code == 2
    _one_line_error(err, "odd.ply: header line 7: an element needs a name and a count")
    assert "point cloud" not in err
    # A real point cloud is still called one.
    path.write_bytes(_ply_ascii(TET_V, []))
    code, _, err = run(capsys, "add-noise", path, "-o", tmp_path / "noisy.off", "--level", "0.01")
    assert code == 2 and "is a point cloud (4 vertices, no faces)" in err


def test_case14_weights_fifo_and_symlink_loop_are_named(tmp_path):
    from dmd_jax.checkpoints import load_weights

    fifo = tmp_path / "w.msgpack"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="w.msgpack: is a FIFO .*weights file"):
        load_weights(fifo)  # without blocking on the read
    loop = tmp_path / "loop.msgpack"
    os.symlink(loop, loop)
    with pytest.raises(OSError, match="loop.msgpack: cannot open it") as info:
        load_weights(loop)
    assert not isinstance(info.value, FileNotFoundError)
    with pytest.raises(FileNotFoundError, match="gone.msgpack: no such weights file"):
        load_weights(tmp_path / "gone.msgpack")
