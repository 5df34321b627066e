"""Bad inputs, weights files, atomic writes and the user's files, through API and CLI.

The bad-input matrix is one table (`CASES`). Every row runs twice: through the Python
API (`load_mesh` then `denoise`, or `denoise` on arrays) and through the command line
(`dmd-jax denoise`), and must end in a clear `ValueError` / one-line CLI error, or, for
a legal input, in finite vertices of the input's shape. The model is the `test` preset
with fixed random weights (the bundled weights are not needed); every small mesh falls
in one padded bucket, so the network compiles once per size class.
"""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
import pytest
import trimesh
from conftest import REPO, shared_mesh_path, tetrahedron

from dmd_jax import checkpoints, inference
from dmd_jax.cli import main
from dmd_jax.config import preset
from dmd_jax.io import atomic_write, load_mesh, save_mesh
from dmd_jax.model import param_shapes

# --------------------------------------------------------------------------------------
# A small model with fixed random weights
# --------------------------------------------------------------------------------------

CONFIG = preset("test")


def random_params(config, seed: int = 0):
    """Params of `config` drawn from N(0, 1/fan_in) (kernels) and N(0, 0.1²) (biases).

    The denoiser head is scaled down so offsets stay comparable to the mesh size.
    """
    rng = np.random.default_rng(seed)

    def draw(path, spec):
        scale = 1.0 / np.sqrt(spec.shape[0]) if len(spec.shape) >= 2 else 0.1
        if "denoiser" in jax.tree_util.keystr(path) and "head" in jax.tree_util.keystr(path):
            scale *= 1e-3
        return (scale * rng.standard_normal(spec.shape)).astype(spec.dtype)

    return jax.tree_util.tree_map_with_path(draw, param_shapes(config.model))


@pytest.fixture(scope="module")
def bundle():
    return checkpoints.ModelBundle(random_params(CONFIG), CONFIG, {})


@pytest.fixture(scope="module")
def weights_file(tmp_path_factory, bundle):
    path = tmp_path_factory.mktemp("weights") / "test.msgpack"
    return checkpoints.save_weights(path, bundle.params, CONFIG, {"purpose": "tests"})


# --------------------------------------------------------------------------------------
# Mesh text in the four formats
# --------------------------------------------------------------------------------------

TET_V, TET_F = tetrahedron()


def obj(v, f, extra: str = "") -> bytes:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    lines += ["f " + " ".join(str(int(i) + 1) for i in face) for face in f]
    return (extra + "\n".join(lines) + "\n").encode()


def off(v, f) -> bytes:
    lines = ["OFF", f"{len(v)} {len(f)} 0"]
    lines += [f"{x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    lines += [f"{len(face)} " + " ".join(str(int(i)) for i in face) for face in f]
    return ("\n".join(lines) + "\n").encode()


def ply(v, f, *, declared_faces: int | None = None) -> bytes:
    head = (
        "ply\nformat ascii 1.0\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f) if declared_faces is None else declared_faces}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    body = [f"{x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    body += [f"{len(face)} " + " ".join(str(int(i)) for i in face) for face in f]
    return (head + "\n".join(body) + "\n").encode()


def exported(v, f, file_type: str) -> bytes:
    data = trimesh.Trimesh(np.asarray(v, float), np.asarray(f), process=False).export(
        file_type=file_type
    )
    return data if isinstance(data, bytes) else data.encode()


CUBE_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
CUBE_QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
PENT = [[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 5, endpoint=False)]
PYRAMID_V = np.array(PENT + [[0.0, 0.0, 1.0]])
PYRAMID_F = [[4, 3, 2, 1, 0]] + [[i, (i + 1) % 5, 5] for i in range(5)]
TWO_TETS_V = np.concatenate([TET_V, TET_V + [5.0, 0.0, 0.0]])
TWO_TETS_F = np.concatenate([TET_F, TET_F + 4])
# Two tetrahedra sharing vertex 0 only (a non-manifold vertex).
BOWTIE_V = np.concatenate([TET_V, -TET_V[1:] + 2 * TET_V[0]])
BOWTIE_F = np.concatenate([TET_F, np.where(TET_F == 0, 0, TET_F + 3)])
# Three triangles on the edge (0, 1) (a non-manifold edge).
FAN_V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0.3], [0.5, 0, 1]], float)
FAN_F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
TRIANGLE_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _binary_stl_truncated() -> bytes:
    return exported(TET_V, TET_F, "stl")[:-7]


def _binary_ply_truncated() -> bytes:
    return exported(TET_V, TET_F, "ply")[:-5]


# --------------------------------------------------------------------------------------
# Checks for legal inputs
# --------------------------------------------------------------------------------------


def _scaled(scale: float, shift: float) -> Callable:
    """Denoising `v·s + t` gives `denoise(v)·s + t` (translation / scale equivariance)."""

    def check(out, v, f, bundle):
        base = inference.denoise((v - shift) / scale, f, bundle)
        expected = base * scale + shift
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-5 * scale)

    return check


def _same_as_float64(out, v, f, bundle):
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, inference.denoise(v.astype(np.float64), f, bundle))


def _float32_out(out, v, f, bundle):
    assert out.dtype == np.float32


def _faces_are(expected) -> Callable:
    def check(out, v, f, bundle):
        np.testing.assert_array_equal(f, expected)

    return check


def _face_count(n: int) -> Callable:
    def check(out, v, f, bundle):
        assert f.shape == (n, 3)

    return check


def _vertex_count(n: int) -> Callable:
    def check(out, v, f, bundle):
        assert len(v) == len(out) == n

    return check


class Case(NamedTuple):
    """One row of the bad-input matrix.

    `file` is `(suffix, bytes)` (or `("shared", name)`) for `load_mesh` and the CLI;
    `arrays` is `(vertices, faces)` for `denoise` directly. `error` is a regex of the
    `ValueError` message, `None` for a legal input; `warn` a regex of the warning a
    legal input must raise; `check(out, v, f, bundle)` more assertions on legal output.
    """

    id: str
    file: tuple | None = None
    arrays: tuple | None = None
    error: str | None = None
    warn: str | None = None
    check: Callable | None = None


N = np.nan
CASES = [
    Case("empty file", file=(".obj", b""), error="the file is empty"),
    Case("blank file", file=(".off", b" \n\n  \n"), error="the file is empty"),
    Case("comments only", file=(".obj", b"# nothing\n"), error="holds no faces"),
    Case(
        "no faces",
        file=(".obj", obj(TET_V, [])),
        arrays=(TET_V, np.zeros((0, 3), int)),
        error="no faces",
    ),
    Case("no vertices", arrays=(np.zeros((0, 3)), TET_F), error="no vertices"),
    Case(
        "NaN coordinate",
        file=(".obj", obj(TET_V, TET_F).replace(b"v 1.0 1.0 1.0", b"v nan 1.0 1.0")),
        arrays=(np.where(np.arange(12).reshape(4, 3) == 4, N, TET_V), TET_F),
        error="NaN or infinite coordinates",
    ),
    Case(
        "inf coordinate",
        file=(".off", off(TET_V, TET_F).replace(b"-1.0 -1.0 1.0", b"-1.0 -inf 1.0")),
        arrays=(TET_V * [[1], [1], [1], [np.inf]], TET_F),
        error="NaN or infinite coordinates",
    ),
    Case(
        "index out of range (OBJ)",
        file=(".obj", obj(TET_V, TET_F) + b"f 1 2 9\n"),
        arrays=(TET_V, [[0, 1, 2], [0, 1, 9]]),
        error="face index 9 is out of range",
    ),
    Case(
        "index out of range (OFF)",
        file=(".off", off(TET_V, [[0, 1, 2], [0, 1, 4]])),
        error="face index 4 is out of range for 4 vertices",
    ),
    Case(
        "index out of range (PLY)",
        file=(".ply", ply(TET_V, [[0, 1, 2], [0, 1, 7]])),
        error="face index 7 is out of range for 4 vertices",
    ),
    Case(
        "index beyond int64 (OFF)",
        file=(".off", off(TET_V, TET_F).replace(b"3 1 3 2", b"3 1 3 99999999999999999999")),
        error="face index 99999999999999999999 is out of range",
    ),
    Case(
        "index beyond int64 (OBJ)",
        file=(".obj", obj(TET_V, TET_F) + b"f 1 2 99999999999999999999\n"),
        error="face index 99999999999999999999 is out of range",
    ),
    Case(
        "negative index",
        file=(".off", off(TET_V, [[0, 1, 2], [0, 1, -1]])),
        arrays=(TET_V, [[0, 1, 2], [0, 1, -1]]),
        error="negative face index -1",
    ),
    Case(
        "OBJ index 0",
        file=(".obj", obj(TET_V, []) + b"f 0 1 2\n"),
        error="face index 0 is invalid \\(OBJ indices start at 1\\)",
    ),
    Case(
        "OBJ relative indices (legal)",
        file=(".obj", obj(TET_V, []) + b"f -4 -3 -2\nf -4 -1 -3\n"),
        check=_faces_are([[0, 1, 2], [0, 3, 1]]),
    ),
    Case(
        "OBJ relative index before the first vertex",
        file=(".obj", obj(TET_V, []) + b"f -1 -2 -9\n"),
        error="relative face index -9 points before the first vertex",
    ),
    Case(
        "face with 2 corners",
        file=(".obj", obj(TET_V, TET_F) + b"f 1 2\n"),
        error="line 9: a face needs at least 3 vertices, got 2",
    ),
    Case(
        "quads (OBJ)",
        file=(".obj", obj(CUBE_V, CUBE_QUADS)),
        warn="triangulated 6 polygon faces",
        check=_face_count(12),
    ),
    Case(
        "n-gon (OFF pentagon)",
        file=(".off", off(PYRAMID_V, PYRAMID_F)),
        warn="triangulated 1 polygon faces",
        check=_faces_are([[4, 3, 2], [4, 2, 1], [4, 1, 0]] + PYRAMID_F[1:]),
    ),
    Case("quads (PLY)", file=(".ply", ply(CUBE_V, CUBE_QUADS)), warn="triangulated"),
    Case(
        "polygon array [n, 4]",
        arrays=(CUBE_V, CUBE_QUADS),
        error="polygons with 4 corners; triangulate them first",
    ),
    Case(
        "zero-area face (collinear corners)",
        file=(".obj", obj(np.vstack([TET_V, [0, 0, 0]]), np.vstack([TET_F, [[1, 4, 3]]]))),
        arrays=(np.vstack([TET_V, [0, 0, 0]]), np.vstack([TET_F, [[1, 4, 3]]])),
    ),
    Case(
        "zero-area face (coincident corners)",
        arrays=(np.vstack([TET_V, TET_V[:1], TET_V[:1]]), np.vstack([TET_F, [[0, 4, 5]]])),
    ),
    Case(
        "face repeating a vertex index",
        file=(".obj", obj(TET_V, TET_F) + b"f 1 1 2\n"),
        arrays=(TET_V, np.vstack([TET_F, [[0, 0, 1]]])),
        error="1 faces repeat a vertex index",
    ),
    Case(
        "duplicate vertices",
        file=(".off", off(np.vstack([TET_V, TET_V[:1]]), np.vstack([TET_F, [[4, 2, 1]]]))),
        check=_vertex_count(5),
    ),
    Case("duplicate faces", file=(".ply", ply(TET_V, np.vstack([TET_F, TET_F[:2]])))),
    Case(
        "unreferenced vertices",
        file=(".obj", obj(np.vstack([TET_V, [[9, 9, 9], [8, 8, 8]]]), TET_F)),
        check=_vertex_count(6),
    ),
    Case(
        "unreferenced vertex with texture indices",
        file=(
            ".obj",
            obj(np.vstack([TET_V, [[9, 9, 9]]]), [])
            + b"vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 4/2 2/3\nf 1/1 3/2 4/3\n",
        ),
        check=_vertex_count(5),
    ),
    Case("non-manifold edge", file=(".obj", obj(FAN_V, FAN_F)), arrays=(FAN_V, FAN_F)),
    Case("non-manifold vertex", file=(".off", off(BOWTIE_V, BOWTIE_F))),
    Case("several components", file=(".ply", ply(TWO_TETS_V, TWO_TETS_F))),
    Case("single triangle", file=(".obj", obj(TRIANGLE_V, [[0, 1, 2]]))),
    Case(
        "coordinates at 1e6 scale",
        file=(".obj", obj(TET_V * 1e6 + 3e6, TET_F)),
        arrays=(TET_V * 1e6 + 3e6, TET_F),
        check=_scaled(1e6, 3e6),
    ),
    Case(
        "coordinates at 1e-6 scale",
        file=(".off", off(TET_V * 1e-6 - 2e-6, TET_F)),
        arrays=(TET_V * 1e-6 - 2e-6, TET_F),
        check=_scaled(1e-6, -2e-6),
    ),
    Case(
        # The frame is taken from scaled coordinates (#31 item 2): a mesh whose extent
        # overflows float64 still denoises, to finite coordinates.
        "extent overflows float64 (legal)",
        arrays=(TET_V * 1.5e308, TET_F),
    ),
    Case(
        "zero extent (all vertices coincide)",
        file=(".obj", obj(np.zeros((4, 3)), TET_F)),
        error="zero extent",
    ),
    Case("float16 input", arrays=(TET_V.astype(np.float16), TET_F), check=_same_as_float64),
    Case("float32 input", arrays=(TET_V.astype(np.float32), TET_F), check=_float32_out),
    Case("int input", arrays=(TET_V.astype(np.int64), TET_F.astype(np.uint8))),
    Case("vertices [n, 2]", arrays=(TET_V[:, :2], TET_F), error="vertices must have shape"),
    Case("vertices 1-D", arrays=(TET_V.ravel(), TET_F), error="vertices must have shape"),
    Case("faces 1-D", arrays=(TET_V, TET_F.ravel()), error="faces must have shape"),
    Case("non-integral faces", arrays=(TET_V, TET_F + 0.5), error="non-integral"),
    Case("boolean faces", arrays=(TET_V, TET_F > 1), error="integers"),
    Case("complex vertices", arrays=(TET_V + 1j, TET_F), error="real numbers"),
    Case("ragged lists", arrays=([[0, 0, 0], [1, 0]], [[0, 1, 2]]), error="ragged"),
    Case(
        "truncated OBJ",
        file=(".obj", obj(TET_V, TET_F).replace(b"v -1.0 -1.0 1.0", b"v -1.0 -1.0")),
        error="line 4: a vertex needs 3 coordinates, got 2",
    ),
    Case(
        "truncated OFF",
        file=(".off", off(TET_V, TET_F).rsplit(b"\n", 2)[0] + b"\n"),
        error="truncated: the header promises 4 faces, the file ends after 3",
    ),
    Case(
        "truncated PLY (ASCII)",
        file=(".ply", ply(TET_V, TET_F[:3], declared_faces=4)),
        error="truncated PLY: the file ends inside the 4 'face' elements",
    ),
    Case(
        "truncated PLY (binary)",
        file=(".ply", _binary_ply_truncated()),
        error="truncated PLY",
    ),
    Case(
        "truncated STL (binary)",
        file=(".stl", _binary_stl_truncated()),
        error="truncated or corrupt binary STL",
    ),
    Case(
        "truncated STL (ASCII)",
        file=(".stl", exported(TET_V, TET_F, "stl_ascii")[:-40]),
        error="truncated ASCII STL",
    ),
    Case(
        "corrupt OBJ (binary junk)",
        file=(".obj", bytes(range(256)) * 4),
        error="binary data in a text mesh format",
    ),
    Case(
        "corrupt OFF (words for counts)",
        file=(".off", b"OFF\nfour two zero\n"),
        error="line 2: expected the counts",
    ),
    Case(
        "corrupt PLY header", file=(".ply", b"ply\nformat nonsense\n"), error="no 'end_header' line"
    ),
    Case("not an OFF file", file=(".off", b"solid x\n"), error="not an OFF file"),
    Case("unknown extension", file=(".xyz", obj(TET_V, TET_F)), error="unknown mesh format"),
    Case(
        "Latin-1 comment (legal)",
        file=(".obj", obj(TET_V, TET_F, extra="# caf\xe9\n").replace(b"\xc3\xa9", b"\xe9")),
        check=_vertex_count(4),
    ),
    Case(
        "truck.obj (inconsistent winding)",
        file=("shared", "truck.obj"),
        check=_vertex_count(2956),
    ),
    Case(
        "horse_quad.obj (quads)",
        file=("shared", "horse_quad.obj"),
        warn="triangulated 2398 polygon faces",
        check=_face_count(4796),
    ),
]
CASE_IDS = [c.id for c in CASES]
FILE_CASES = [c for c in CASES if c.file is not None]


def _write_case(case: Case, tmp_path: Path) -> Path:
    kind, content = case.file
    if kind == "shared":
        return shared_mesh_path(content)
    path = tmp_path / f"input{kind}"
    path.write_bytes(content)
    return path


def _check_legal(out, v, f, case: Case, bundle) -> None:
    v = np.asarray(v)
    assert out.shape == v.shape, f"{case.id}: output shape {out.shape} for input {v.shape}"
    assert np.all(np.isfinite(out)), f"{case.id}: non-finite output"
    if case.check is not None:
        case.check(out, v, np.asarray(f), bundle)


def test_matrix_has_enough_cases():
    assert len(CASES) >= 25 and len(set(CASE_IDS)) == len(CASES)
    assert sum(c.error is None for c in CASES) >= 10  # legal inputs are part of it


# A refusal or an answer, never NumPy's overflow or invalid-value noise on the way.
@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("case", CASES, ids=CASE_IDS)
def test_bad_input_through_the_api(case, bundle, tmp_path):
    if case.file is not None:
        path = _write_case(case, tmp_path)
        if case.error is not None:
            try:
                v, f = load_mesh(path)
            except ValueError as exc:
                assert re.search(case.error, str(exc)), str(exc)
                assert str(path) in str(exc)  # the message names the file
            else:  # a readable file the model cannot take (zero extent, say)
                with pytest.raises(ValueError, match=case.error):
                    inference.denoise(v, f, bundle)
        else:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                v, f = load_mesh(path)
            messages = [str(w.message) for w in caught]
            if case.warn is not None:
                assert any(re.search(case.warn, m) for m in messages), messages
                with pytest.raises(ValueError, match="faces are polygons"):
                    load_mesh(path, polygons="reject")
            _check_legal(inference.denoise(v, f, bundle), v, f, case, bundle)
    if case.arrays is not None:
        v, f = case.arrays
        if case.error is not None:
            with pytest.raises(ValueError, match=case.error):
                inference.denoise(v, f, bundle)
        else:
            _check_legal(inference.denoise(v, f, bundle), v, f, case, bundle)


def _cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _one_line_error(err: str, command: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith(f"dmd-jax {command}: error: ")]
    assert len(errors) == 1, err
    return errors[0]


@pytest.mark.parametrize("case", FILE_CASES, ids=[c.id for c in FILE_CASES])
def test_bad_input_through_the_cli(case, weights_file, tmp_path, capsys):
    path = _write_case(case, tmp_path)
    before = _sha256(path)
    out = tmp_path / "out.obj"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc, stdout, err = _cli(capsys, "denoise", path, "-o", out, "--weights", weights_file)
    assert _sha256(path) == before
    if case.error is not None:
        assert rc == 2
        line = _one_line_error(err, "denoise")
        assert re.search(case.error, line), line
        assert not out.exists()
    else:
        assert rc == 0, err
        assert "denoised" in stdout and out.is_file()
        v_in, f_in = _quiet_load(path)
        v_out, f_out = load_mesh(out)
        assert v_out.shape == v_in.shape and np.all(np.isfinite(v_out))
        np.testing.assert_array_equal(f_out, f_in)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def _quiet_load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_mesh(path)


# --------------------------------------------------------------------------------------
# CLI paths: outputs, inputs, weights
# --------------------------------------------------------------------------------------


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture
def tet_file(tmp_path):
    path = tmp_path / "tet.obj"
    path.write_bytes(obj(TET_V, TET_F))
    return path


CLI_CASES = {
    "output is the input": (
        lambda d, i: ["denoise", i, "-o", i],
        "the output path is the input file",
    ),
    "output is the input, --overwrite": (
        lambda d, i: ["denoise", i, "-o", i, "--overwrite"],
        "the output path is the input file",
    ),
    "output is the input via another spelling": (
        lambda d, i: ["denoise", i, "-o", d / "." / "x" / ".." / i.name],
        "the output path is the input file",
    ),
    "output directory missing": (
        lambda d, i: ["denoise", i, "-o", d / "missing" / "out.obj"],
        "output directory does not exist",
    ),
    "output exists": (
        lambda d, i: ["denoise", i, "-o", _touch(d / "out.obj")],
        "already exists \\(pass --overwrite",
    ),
    "output is a directory, --overwrite": (
        lambda d, i: ["denoise", i, "-o", _mkdir(d / "dir.obj"), "--overwrite"],
        "dir.obj",
    ),
    "output has an unknown extension": (
        lambda d, i: ["denoise", i, "-o", d / "out.xyz"],
        "unknown mesh format '.xyz'",
    ),
    "input missing": (lambda d, i: ["denoise", d / "absent.obj", "-o", d / "o.obj"], "no such"),
    "input is a directory": (
        lambda d, i: ["denoise", _mkdir(d / "in.obj"), "-o", d / "o.obj"],
        "take --out DIR, not -o",
    ),
    "weights missing": (
        lambda d, i: ["denoise", i, "-o", d / "o.obj", "--weights", d / "none.msgpack"],
        "no such weights file",
    ),
    "weights corrupt": (
        lambda d, i: ["denoise", i, "-o", d / "o.obj", "--weights", _junk(d / "w.msgpack")],
        "not a readable weights file",
    ),
    "checkpoint directory empty": (
        lambda d, i: ["denoise", i, "-o", d / "o.obj", "--weights", _mkdir(d / "ckpt")],
        "holds no checkpoint",
    ),
    "add-noise, output is the input": (
        lambda d, i: ["add-noise", i, "-o", i, "--level", "0.01"],
        "the output path is the input file",
    ),
    "add-noise, negative level": (
        lambda d, i: ["add-noise", i, "-o", d / "o.obj", "--level", "-1"],
        "level",
    ),
}


def _touch(path: Path) -> Path:
    path.write_text("keep me\n")
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _junk(path: Path) -> Path:
    path.write_bytes(b"\xc1\x00junk")
    return path


@pytest.mark.parametrize("name", list(CLI_CASES))
def test_cli_refuses_bad_paths_with_one_line(name, tet_file, weights_file, tmp_path, capsys):
    build, message = CLI_CASES[name]
    argv = build(tmp_path, tet_file)
    if argv[0] == "denoise" and "--weights" not in argv:
        argv += ["--weights", weights_file]
    listing = sorted(p.name for p in tmp_path.iterdir())
    before = _sha256(tet_file)
    rc, _, err = _cli(capsys, *argv)
    assert rc == 2
    assert re.search(message, _one_line_error(err, argv[0])), err
    assert _sha256(tet_file) == before
    # Nothing was written: no output, no temporary file.
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    if (tmp_path / "out.obj").exists():
        assert (tmp_path / "out.obj").read_text() == "keep me\n"


@pytest.mark.parametrize("command", ["denoise", "add-noise"])
def test_cli_never_modifies_its_input(command, weights_file, tmp_path, capsys):
    inputs = [tmp_path / "tet.ply", tmp_path / "two.off"]
    inputs[0].write_bytes(ply(TET_V, TET_F))
    inputs[1].write_bytes(off(TWO_TETS_V, TWO_TETS_F))
    for i, path in enumerate(inputs):
        before = (_sha256(path), path.stat().st_mtime_ns)
        out = tmp_path / f"out{i}.obj"
        extra = ["--weights", weights_file] if command == "denoise" else ["--level", "0.01"]
        rc, _, err = _cli(capsys, command, path, "-o", out, *extra)
        assert rc == 0, err
        rc, _, err = _cli(capsys, command, path, "-o", out, "--overwrite", *extra)
        assert rc == 0, err
        assert (_sha256(path), path.stat().st_mtime_ns) == before
        assert load_mesh(out)[0].shape == load_mesh(path)[0].shape


# --------------------------------------------------------------------------------------
# Weights files and checkpoints
# --------------------------------------------------------------------------------------


def _payload(path: Path) -> dict:
    from flax import serialization

    return serialization.msgpack_restore(path.read_bytes())


def _write_payload(path: Path, payload: dict) -> Path:
    from flax import serialization

    path.write_bytes(serialization.msgpack_serialize(payload))
    return path


def test_weights_round_trip(weights_file, bundle):
    loaded = checkpoints.load_weights(weights_file)
    assert loaded.config == CONFIG and loaded.meta == {"purpose": "tests"}
    _assert_same_params(loaded.params, bundle.params)


def _tamper(edit: Callable[[dict], None]) -> Callable[[Path, Path], Path]:
    def make(src: Path, dst: Path) -> Path:
        payload = _payload(src)
        edit(payload)
        return _write_payload(dst, payload)

    return make


def _set(key, value):
    return _tamper(lambda p: p.__setitem__(key, value))


def _other_config(p):
    p["config"] = json.dumps(preset("small").to_dict())


def _future_config(p):
    cfg = json.loads(p["config"])
    cfg["model"]["new_field_of_a_later_version"] = 1
    p["config"] = json.dumps(cfg)


def _first_kernel(params):
    # The normal-first head sits on the denoiser, the offset head on its stack.
    denoiser = params["denoiser"]
    return denoiser["head"] if "head" in denoiser else denoiser["stack"]["head"]


def _nan_param(p):
    head = _first_kernel(p["params"])
    head["kernel"] = head["kernel"].copy()
    head["kernel"][0, 0] = np.nan


def _float64_param(p):
    head = _first_kernel(p["params"])
    head["kernel"] = head["kernel"].astype(np.float64)


def _drop_param(p):
    del _first_kernel(p["params"])["bias"]


WEIGHTS_CASES = {
    "empty file": (lambda s, d: _junk_bytes(d, b""), "not a readable weights file"),
    "random bytes": (
        lambda s, d: _junk_bytes(d, np.random.default_rng(0).bytes(300)),
        "not a readable weights file|not a dmd_jax weights file",
    ),
    "truncated to 10%": (lambda s, d: _cut(s, d, 0.1), "truncated or corrupt"),
    "truncated to 60%": (lambda s, d: _cut(s, d, 0.6), "truncated or corrupt"),
    "last byte missing": (lambda s, d: _cut(s, d, -1), "truncated or corrupt"),
    "another msgpack file": (
        lambda s, d: _write_payload(d, {"hello": np.zeros(3)}),
        "not a dmd_jax weights file",
    ),
    "format version 3": (_set("version", 3), "version 3 is not supported"),
    "no params": (_tamper(lambda p: p.pop("params")), "incomplete weights file \\(no params\\)"),
    "config is not JSON": (_set("config", "{model: small"), "unreadable config"),
    "config of another preset": (
        _tamper(_other_config),
        "params do not match their config",
    ),
    "config of a later version": (_tamper(_future_config), "new_field_of_a_later_version"),
    "params missing a leaf": (_tamper(_drop_param), "params do not match their config"),
    "params of another dtype": (_tamper(_float64_param), "has dtype float64"),
    "params with NaN": (_tamper(_nan_param), "NaN or infinite values"),
    "params not a dict": (_set("params", [1, 2, 3]), "params must be a nested dict"),
}


def _junk_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _cut(src: Path, dst: Path, fraction: float) -> Path:
    data = src.read_bytes()
    n = len(data) - 1 if fraction < 0 else int(len(data) * fraction)
    dst.write_bytes(data[:n])
    return dst


@pytest.mark.parametrize("name", list(WEIGHTS_CASES))
def test_bad_weights_file_is_a_clear_value_error(name, weights_file, tmp_path, capsys):
    make, message = WEIGHTS_CASES[name]
    path = make(weights_file, tmp_path / "bad.msgpack")
    with pytest.raises(ValueError, match=message) as info:
        checkpoints.load_weights(path)
    assert str(path) in str(info.value)
    mesh = tmp_path / "tet.obj"
    mesh.write_bytes(obj(TET_V, TET_F))
    rc, _, err = _cli(capsys, "denoise", mesh, "-o", tmp_path / "o.obj", "--weights", path)
    assert rc == 2 and re.search(message, _one_line_error(err, "denoise")), err


def test_checkpoints_round_trip_export_and_fail_clearly(tmp_path, bundle, capsys):
    import jax.numpy as jnp

    from dmd_jax.checkpoints import checkpoint_managers, load_params, save_checkpoint
    from dmd_jax.train import TrainState
    from dmd_jax.train import split_params as split

    with pytest.raises(FileNotFoundError, match="no such checkpoint directory"):
        load_params(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no checkpoint"):
        load_params(tmp_path / "empty")

    latest, _ = checkpoint_managers(tmp_path / "run", 1)
    state = TrainState(jnp.asarray(7, jnp.int32), split(bundle.params), {"fe": {}, "rest": {}})
    save_checkpoint(latest, state, CONFIG)
    ckpt = tmp_path / "run" / "checkpoints" / "latest"
    params, config = load_params(ckpt)
    assert config == CONFIG
    _assert_same_params(params, bundle.params)

    # export-weights writes a weights file with the same params and config.
    rc, _, err = _cli(capsys, "export-weights", ckpt, "-o", tmp_path / "w.msgpack")
    assert rc == 0, err
    exported_bundle = checkpoints.load_weights(tmp_path / "w.msgpack")
    assert exported_bundle.config == CONFIG
    _assert_same_params(exported_bundle.params, bundle.params)

    # Cut every stored array file short: a clear ValueError, a one-line CLI error.
    data_files = [p for p in (ckpt / "7" / "state").rglob("*") if p.is_file()]
    assert data_files
    for p in data_files:
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(ValueError, match="checkpoint"):
        load_params(ckpt)
    mesh = tmp_path / "tet.obj"
    mesh.write_bytes(obj(TET_V, TET_F))
    rc, _, err = _cli(capsys, "denoise", mesh, "-o", tmp_path / "o.obj", "--weights", ckpt)
    assert rc == 2 and _one_line_error(err, "denoise")
    assert not (tmp_path / "o.obj").exists()


def _assert_same_params(a, b) -> None:
    flat_a = jax.tree_util.tree_flatten_with_path(a)[0]
    flat_b = jax.tree_util.tree_flatten_with_path(b)[0]
    assert [p for p, _ in flat_a] == [p for p, _ in flat_b]
    for (_, x), (_, y) in zip(flat_a, flat_b, strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(x, y)


# The one pickle use allowed, and all of it: `jax.experimental.serialize_executable` is
# JAX's only way to reload a compiled executable without tracing, and its payload is
# pickle-based. The compilation cache (`dmd_jax/compile_cache.py`) dumps and loads those
# payloads and nothing else, only in the user's own cache directory, and only after
# checking that the directory and the entry belong to the user and no one else may write
# them (`EntryStore.trusted`). Weights, meshes and every other data file stay pickle-free.
PICKLE_ALLOWED = {
    "dmd_jax/compile_cache.py": [
        "import pickle",
        "serialized, in_tree, out_tree = pickle.loads(payload)",
        "payload = pickle.dumps(serialize(compiled), protocol=pickle.HIGHEST_PROTOCOL)",
    ]
}


def test_no_pickle_anywhere():
    """No module of the package (nor benchmarks, experiments) can read or write pickles,
    except the compilation cache's executables (`PICKLE_ALLOWED`)."""
    forbidden = [
        r"^\s*(import|from)\s+(pickle|cPickle|_pickle|cloudpickle|dill|joblib|shelve|marshal)\b",
        r"\bpickle\.(loads?|dumps?|Unpickler|Pickler)\b",
        r"allow_pickle\s*=\s*True",
        r"\btorch\.load\b",
        r"\bread_pickle\b|\bto_pickle\b",
    ]
    sources = [
        p
        for folder in ("dmd_jax", "benchmarks", "experiments")
        for p in sorted((REPO / folder).rglob("*.py"))
    ]
    assert len(sources) > 10
    hits: dict[str, list[str]] = {}
    for path in sources:
        text = path.read_text()
        lines = text.splitlines()
        for pattern in forbidden:
            for m in re.finditer(pattern, text, flags=re.MULTILINE):
                line = lines[text[: m.start()].count(chr(10))].strip()
                hits.setdefault(path.relative_to(REPO).as_posix(), []).append(line)
    # Each allowed line matched once (`pickle.dumps(..., protocol=pickle.HIGHEST_PROTOCOL)`
    # matches one pattern once), and nothing else anywhere.
    assert {k: sorted(v) for k, v in hits.items()} == {
        k: sorted(v) for k, v in PICKLE_ALLOWED.items()
    }
    # Those calls serve `serialize_executable` alone: the load feeds `deserialize_and_load`,
    # the dump takes `serialize`'s result.
    cache = (REPO / "dmd_jax/compile_cache.py").read_text()
    loads = cache.index("pickle.loads(payload)")
    assert "deserialize_and_load(serialized, in_tree, out_tree)" in cache[loads : loads + 200]
    assert "from jax.experimental.serialize_executable import serialize\n" in cache
    assert re.findall(r"\bpickle\.\w+", cache) == [
        "pickle.loads",
        "pickle.dumps",
        "pickle.HIGHEST_PROTOCOL",
    ]
    # Every np.load in the package refuses pickles explicitly or by NumPy's default.
    for path in sources:
        for m in re.finditer(r"np\.load\(([^)]*)\)", path.read_text()):
            assert "allow_pickle=True" not in m.group(1), path


# --------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------


def _leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


@pytest.mark.parametrize("exception", [RuntimeError, KeyboardInterrupt])
def test_failing_writer_leaves_no_partial_and_no_temp_file(tmp_path, exception):
    def half_then_fail(tmp):
        Path(tmp).write_bytes(b"half a fi")
        raise exception("writer died")

    target = tmp_path / "mesh.obj"
    with pytest.raises(exception):
        atomic_write(target, half_then_fail)
    assert _leftovers(tmp_path, set()) == []
    target.write_text("old content\n")
    with pytest.raises(exception):
        atomic_write(target, half_then_fail, overwrite=True)
    assert target.read_text() == "old content\n"
    assert _leftovers(tmp_path, {"mesh.obj"}) == []


def test_save_mesh_and_weights_are_atomic(tmp_path, monkeypatch, bundle):
    save_mesh(tmp_path / "kept.obj", TET_V, TET_F)
    checkpoints.save_weights(tmp_path / "kept.msgpack", bundle.params, CONFIG)
    originals = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def failing_rows(fh, row, rows):
        fh.write("v 1 2")  # a partial file, then the disk fills
        raise OSError("disk full")

    import dmd_jax.io.obj

    monkeypatch.setattr(dmd_jax.io.obj, "_write_rows", failing_rows)
    for name in ("new.obj", "kept.obj"):
        with pytest.raises(OSError, match="disk full"):
            save_mesh(tmp_path / name, TET_V * 2, TET_F, overwrite=True)
    monkeypatch.undo()

    # A failing rename (the last step) must clean up too, for meshes and weights.
    import os

    def failing_replace(src, dst):
        raise OSError("rename failed")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        save_mesh(tmp_path / "kept.obj", TET_V * 2, TET_F, overwrite=True)
    with pytest.raises(OSError, match="rename failed"):
        checkpoints.save_weights(tmp_path / "kept.msgpack", bundle.params, CONFIG, overwrite=True)
    with pytest.raises(OSError, match="rename failed"):
        checkpoints.save_weights(tmp_path / "new.msgpack", bundle.params, CONFIG)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == originals


def test_weights_file_is_msgpack_not_pickle(weights_file):
    # 0x86 opens a msgpack map of 6 entries (format, version, config, policy, meta,
    # params); a pickle stream of protocol 2 or later opens with 0x80 (PROTO).
    assert weights_file.read_bytes()[0] == 0x86
