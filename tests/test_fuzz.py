"""Bounded fuzzing of the mesh loaders: any bytes give a valid mesh or a `ValueError`.

Inputs are raw random bytes, lines of random keywords and numbers, and mutations of
valid OBJ / OFF / PLY (ASCII, binary) / STL (ASCII, binary) files: flipped, deleted,
inserted and duplicated bytes, cuts, and numbers replaced by awkward ones (NaN, huge
counts, negative indices...). Anything
other than a valid mesh or a `ValueError` fails: another exception type, a hang (a
20 s alarm per file) or a crash of the worker. The default suite runs a few dozen
inputs of each hypothesis strategy and the 1,500 seeded corruptions of issue 31 (mesh
and weights files, below); `make test-slow` runs thousands more and every prefix of
every seed file.
"""

from __future__ import annotations

import re
import signal
import threading
import warnings
from contextlib import contextmanager

import numpy as np
import pytest
import trimesh
from conftest import tetrahedron
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmd_jax.io import load_mesh
from dmd_jax.mesh import validate_mesh

FEW = settings(
    max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
MANY = settings(
    max_examples=3000, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)


def _export(v, f, file_type: str) -> bytes:
    data = trimesh.Trimesh(v, f, process=False).export(file_type=file_type)
    return data if isinstance(data, bytes) else data.encode()


def _seeds() -> dict[str, list[bytes]]:
    v, f = tetrahedron()
    quads = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3 4\nf 1 2 5\nf 2 3 5\n"
    textured = (
        "# textured\nv 1 1 1\nv 1 -1 -1\nv -1 1 -1\nv -1 -1 1\nvt 0 0\nvt 1 0\nvt 0 1\n"
        "vn 0 0 1\nf 1/1/1 2/2/1 3/3/1\nf -4/1/1 -1/2/1 -3/3/1\nf 1//1 3//1 4//1\n"
    )
    coff = "COFF\n4 2 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n"
    coff += "0 0 1 9 9 9 255\n3 0 1 2\n4 0 1 3 2 1 1 1\n"
    ply_quads = (
        "ply\nformat ascii 1.0\ncomment quads\nelement vertex 5\nproperty float x\n"
        "property float y\nproperty float z\nelement face 3\n"
        "property list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3\n3 0 1 4\n3 1 2 4\n"
    )
    return {
        ".obj": [_export(v, f, "obj"), quads.encode(), textured.encode()],
        ".off": [_export(v, f, "off"), coff.encode()],
        ".ply": [
            _export(v, f, "ply"),
            trimesh.exchange.ply.export_ply(trimesh.Trimesh(v, f), encoding="ascii"),
            ply_quads.encode(),
        ],
        ".stl": [_export(v, f, "stl"), _export(v, f, "stl_ascii")],
    }


SEEDS = _seeds()
AWKWARD = [
    b"nan",
    b"inf",
    b"-inf",
    b"-1",
    b"0",
    b"-0",
    b"3.5",
    b"1e309",
    b"1e-320",
    b"4294967296",
    b"99999999999999999999",
    b"0x10",
    b"",
    b"\xff\xfe",
    b"\x00",
]


@st.composite
def mutated_files(draw):
    """A seed file with 1-4 random mutations, and the suffix it is saved under."""
    suffix = draw(st.sampled_from(sorted(SEEDS)))
    data = bytearray(draw(st.sampled_from(SEEDS[suffix])))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "delete", "insert", "duplicate", "cut", "number"]))
        pos = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[pos] = draw(st.integers(0, 255))
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 16))]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "duplicate":
            data[pos:pos] = data[pos : pos + draw(st.integers(1, 64))]
        elif op == "cut":
            del data[pos:]
        else:
            numbers = list(re.finditer(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?", bytes(data)))
            if numbers:
                m = numbers[draw(st.integers(0, len(numbers) - 1))]
                data[m.start() : m.end()] = draw(st.sampled_from(AWKWARD))
    # Sometimes save it under another format's suffix.
    if draw(st.integers(0, 9)) == 0:
        suffix = draw(st.sampled_from(sorted(SEEDS)))
    return suffix, bytes(data)


KEYWORDS = [b"v", b"f", b"vt", b"vn", b"#", b"OFF", b"COFF", b"ply", b"end_header", b"solid"]
TOKENS = st.one_of(
    st.sampled_from(KEYWORDS + AWKWARD),
    st.integers(-8, 8).map(lambda i: str(i).encode()),
    st.floats(allow_nan=True, allow_infinity=True).map(lambda x: repr(x).encode()),
    st.sampled_from([b"1/2", b"1//3", b"-1/-1", b"//", b"/", b"1/"]),
)


@st.composite
def token_soups(draw):
    """Lines of keywords, numbers and awkward tokens: text the OBJ/OFF readers parse far."""
    lines = draw(st.lists(st.lists(TOKENS, max_size=8), max_size=30))
    return draw(st.sampled_from([".obj", ".off"])), b"\n".join(b" ".join(ln) for ln in lines)


class _Hang(BaseException):
    """Not an `Exception`: the loader's catch-all must not turn a hang into a ValueError."""


@contextmanager
def _time_limit(seconds: int):
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_alarm(signum, frame):
        raise _Hang(f"the loader ran for more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def check_loader(folder, suffix: str, data: bytes) -> None:
    path = folder / f"fuzz{suffix}"
    path.write_bytes(data)
    with _time_limit(20), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # triangulation warnings are legal
        try:
            v, f = load_mesh(path)
        except ValueError as exc:
            assert str(exc), "a ValueError without a message"
            return
    # Anything returned is a valid mesh, exactly as validate_mesh describes it.
    assert v.dtype == np.float64 and f.dtype == np.int32
    v2, f2 = validate_mesh(v, f)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def test_seed_files_load(folder):
    for suffix, files in SEEDS.items():
        for data in files:
            path = folder / f"seed{suffix}"
            path.write_bytes(data)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                v, f = load_mesh(path)
            assert len(v) >= 4 and len(f) >= 3


@FEW
@given(suffix=st.sampled_from([".obj", ".off", ".ply", ".stl"]), data=st.binary(max_size=600))
def test_random_bytes(folder, suffix, data):
    check_loader(folder, suffix, data)


@FEW
@given(case=mutated_files())
def test_mutated_files(folder, case):
    check_loader(folder, *case)


@FEW
@given(case=token_soups())
def test_token_soups(folder, case):
    check_loader(folder, *case)


# --------------------------------------------------------------------------------------
# The per-format readers and writers of dmd_jax.io (issue 56): PLY headers whose lines
# are duplicated, dropped or swapped (a property or element declared twice must be
# refused, never read as one of them), big-endian and mixed-list binary PLY, and the
# writers at any scale and offset (an STL float32 cannot hold is refused, never written).
# --------------------------------------------------------------------------------------


def _binary_ply(order: str, mixed: bool) -> bytes:
    import struct

    v, f = tetrahedron()
    head = (
        f"ply\nformat binary_{'little' if order == '<' else 'big'}_endian 1.0\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f) - int(mixed)}\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    ).encode()
    body = b"".join(struct.pack(order + "3d", *p) for p in np.asarray(v, float))
    faces = [list(x) for x in f]
    if mixed:  # a quad and triangles: the record-by-record path
        faces = [[0, 1, 2, 3]] + faces[2:]
    body += b"".join(struct.pack(order + "B" + "i" * len(x), len(x), *x) for x in faces)
    return head + body


PLY_SEEDS = SEEDS[".ply"] + [_binary_ply(o, m) for o in "<>" for m in (False, True)]


@st.composite
def ply_header_edits(draw):
    """A PLY seed whose header lines are duplicated, dropped or swapped."""
    data = draw(st.sampled_from(PLY_SEEDS))
    end = data.index(b"end_header")
    lines = data[:end].split(b"\n")[:-1]
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(1, len(lines) - 1))
        op = draw(st.sampled_from(["duplicate", "drop", "swap"]))
        if op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "drop" and len(lines) > 2:
            del lines[i]
        else:
            j = draw(st.integers(1, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
    return b"\n".join(lines) + b"\n" + data[end:]


def test_binary_ply_seeds_load(folder):
    v, f = tetrahedron()
    for data in PLY_SEEDS[-4:]:
        check_loader(folder, ".ply", data)
    path = folder / "be.ply"
    path.write_bytes(_binary_ply(">", False))
    np.testing.assert_array_equal(load_mesh(path)[0], v)


@FEW
@given(data=ply_header_edits())
def test_ply_header_edits(folder, data):
    check_loader(folder, ".ply", data)
    head = data[: data.index(b"end_header")].decode()
    per: dict[str, list[str]] = {}
    elements, current = [], None
    for ln in head.splitlines():
        if ln.startswith("element"):
            current = ln.split()[1]
            elements.append(current)
        elif ln.startswith("property") and current is not None:
            per.setdefault(current, []).append(ln.split()[-1])
    twice = len(set(elements)) < len(elements) or any(len(set(p)) < len(p) for p in per.values())
    if twice:  # a repeated element or property is never read as one of them
        with pytest.raises(ValueError, match="twice|header line"):
            load_mesh(folder / "fuzz.ply")


@FEW
@given(
    suffix=st.sampled_from([".obj", ".off", ".ply", ".stl"]),
    scale=st.sampled_from([1e-30, 1e-6, 1.0, 1e6, 1e30, 1e300]),
    offset=st.sampled_from([0.0, 1e3, 1e6, -1e9, 1e40]),
)
def test_writers_round_trip_or_refuse(folder, suffix, scale, offset):
    """`save_mesh` writes what `load_mesh` reads back (exactly, or for STL within 1e-3
    of the median edge), or refuses with a `ValueError` naming the file."""
    from dmd_jax.io import save_mesh

    v, f = tetrahedron()
    v = np.asarray(v, float) * scale + offset
    path = folder / f"w{suffix}"
    if not np.isfinite(v).all() or np.ptp(v, axis=0).max() == 0:
        return
    try:
        save_mesh(path, v, f, overwrite=True)
    except ValueError as exc:
        assert f"w{suffix}" in str(exc)
        return
    back, faces = load_mesh(path)
    if suffix != ".stl":
        np.testing.assert_array_equal(back, v)
        return
    assert np.isfinite(back).all() and len(back) == len(v)
    edge = np.median(np.linalg.norm(v[f] - np.roll(v[f], 1, axis=1), axis=2))
    assert np.abs(np.sort(back, axis=0) - np.sort(v, axis=0)).max() <= 1e-3 * edge


def test_every_seventh_prefix(folder):
    for suffix, files in SEEDS.items():
        for data in files:
            for n in range(0, len(data), 7):
                check_loader(folder, suffix, data[:n])


@pytest.mark.slow
@MANY
@given(suffix=st.sampled_from([".obj", ".off", ".ply", ".stl"]), data=st.binary(max_size=4000))
def test_random_bytes_many(folder, suffix, data):
    check_loader(folder, suffix, data)


@pytest.mark.slow
@MANY
@given(case=mutated_files())
def test_mutated_files_many(folder, case):
    check_loader(folder, *case)


@pytest.mark.slow
@MANY
@given(case=token_soups())
def test_token_soups_many(folder, case):
    check_loader(folder, *case)


@pytest.mark.slow
def test_every_prefix(folder):
    for suffix, files in SEEDS.items():
        for data in files:
            for n in range(len(data) + 1):
                check_loader(folder, suffix, data[:n])


# --------------------------------------------------------------------------------------
# A thousand and more corruptions of mesh and weights files (issue 31), one seeded RNG
# --------------------------------------------------------------------------------------
#
# Each case is one small file corrupted the way files are in practice: flipped bytes or
# bits, a cut, a span deleted, inserted or repeated, a UTF-8 byte-order mark in front, a
# header count off by one, an awkward number; for weights also JSON sections nested
# thousands deep and config fields set to awkward values. The contract: a `ValueError`
# or `OSError` with a message, or a correct result (a valid mesh; the very same mesh
# after a BOM; for weights a bundle whose params fit its config), never another
# exception, never a hang (`CASE_SECONDS` each). Plain NumPy draws rather than
# hypothesis keep 1,500 cases well under a minute on one core.

CASE_SECONDS = 5
MESH_CASES = 1200
WEIGHTS_CASES = 300


def _issue31_seeds() -> list[tuple[str, bytes]]:
    """Every seed file of `SEEDS`, plus what `save_mesh` writes and a mixed-polygon
    binary PLY, as `(suffix, bytes)`."""
    import struct
    import tempfile
    from pathlib import Path

    from dmd_jax.io import save_mesh

    seeds = [(s, d) for s, files in SEEDS.items() for d in files]
    v, f = tetrahedron()
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".obj", ".off", ".ply"):
            path = save_mesh(Path(tmp) / f"t{suffix}", v * 1e-3 + 7.0, f)
            seeds.append((suffix, path.read_bytes()))
    head = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 5\n"
        b"property list uchar int vertex_indices\nend_header\n"
    )
    body = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], "<f4").tobytes()
    for face in ([3, 2, 1, 0], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]):
        body += struct.pack(f"<B{len(face)}i", len(face), *face)
    seeds.append((".ply", head + body))
    return seeds


def _count_off_by_one(suffix: str, data: bytes, rng) -> bytes | None:
    """The file with one header count changed by ±1, or None if it has no header count."""
    delta = int(rng.choice([-1, 1]))
    if suffix == ".ply":
        found = list(re.finditer(rb"element (\w+) (\d+)", data[: data.find(b"end_header")]))
        if not found:
            return None
        m = found[int(rng.integers(len(found)))]
        n = max(int(m.group(2)) + delta, 0)
        return data[: m.start(2)] + str(n).encode() + data[m.end(2) :]
    if suffix == ".off":
        m = re.search(rb"OFF\s+(\d+)\s+(\d+)", data)
        if m is None:
            return None
        g = int(rng.integers(1, 3))
        n = max(int(m.group(g)) + delta, 0)
        return data[: m.start(g)] + str(n).encode() + data[m.end(g) :]
    if suffix == ".stl" and not data.lstrip().lower().startswith(b"solid"):
        n = int(np.frombuffer(data[80:84], "<u4")[0]) + delta
        return data[:80] + np.uint32(max(n, 0)).tobytes() + data[84:]
    return None


def _corrupt(suffix: str, data: bytes, rng) -> tuple[str, bytes, str]:
    """`(suffix, bytes, kind)` of one corruption; `kind` says what must come back."""
    op = str(
        rng.choice(
            ["flip", "bit", "cut", "delete", "insert", "duplicate", "bom", "count", "number"]
        )
    )
    b = bytearray(data)
    pos = int(rng.integers(len(b))) if b else 0
    if op == "bom":
        # Text files (and PLY, whose header is text) read the same after a BOM; three
        # bytes in front of a binary STL shift its fixed layout, so any clear answer goes.
        binary_stl = suffix == ".stl" and not data.lstrip().lower().startswith(b"solid")
        return suffix, b"\xef\xbb\xbf" + data, "any" if binary_stl else "same"
    if op == "count":
        changed = _count_off_by_one(suffix, data, rng)
        if changed is not None and changed != data:
            return suffix, changed, "error"
        op = "cut"
    if op == "flip":
        b[pos] = int(rng.integers(256))
    elif op == "bit":
        b[pos] ^= 1 << int(rng.integers(8))
    elif op == "cut":
        del b[pos:]
    elif op == "delete":
        del b[pos : pos + int(rng.integers(1, 17))]
    elif op == "insert":
        b[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 17))).astype(np.uint8).tobytes()
    elif op == "duplicate":
        b[pos:pos] = b[pos : pos + int(rng.integers(1, 65))]
    else:
        numbers = list(re.finditer(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?", bytes(b)))
        if numbers:
            m = numbers[int(rng.integers(len(numbers)))]
            b[m.start() : m.end()] = AWKWARD[int(rng.integers(len(AWKWARD)))]
    return suffix, bytes(b), "any"


def _load_or_error(load, path):
    """`load(path)`, or None for a clear `ValueError`/`OSError`; anything else fails."""
    with _time_limit(CASE_SECONDS), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # triangulation notes are legal
        try:
            return load(path)
        except (ValueError, OSError) as exc:
            message = str(exc)
            assert message and "\n" not in message, f"an unclear error: {message!r}"
            assert str(path) in message, f"the error does not name the file: {message}"
            return None


def test_issue31_thousand_mesh_corruptions(tmp_path):
    rng = np.random.default_rng(31)
    seeds = _issue31_seeds()
    originals = {}
    for i, (suffix, data) in enumerate(seeds):
        path = tmp_path / f"seed{i}{suffix}"
        path.write_bytes(data)
        originals[i] = _load_or_error(load_mesh, path)
        assert originals[i] is not None, f"seed {i} ({suffix}) does not load"
    counts = {"error": 0, "mesh": 0}
    for case in range(MESH_CASES):
        i = int(rng.integers(len(seeds)))
        suffix, data, kind = _corrupt(*seeds[i], rng)
        path = tmp_path / f"case{case % 50}{suffix}"
        path.write_bytes(data)
        try:
            got = _load_or_error(load_mesh, path)
        except AssertionError as exc:
            raise AssertionError(f"case {case} ({kind}, seed {i}, {data[:80]!r}): {exc}") from exc
        counts["error" if got is None else "mesh"] += 1
        if kind == "same":
            assert got is not None, f"case {case}: a BOM made seed {i} unreadable"
            np.testing.assert_array_equal(got[0], originals[i][0])
            np.testing.assert_array_equal(got[1], originals[i][1])
        elif kind == "error":
            assert got is None, f"case {case}: a header count off by one loaded (seed {i})"
        if got is not None:
            v, f = got
            assert v.dtype == np.float64 and f.dtype == np.int32
            validate_mesh(v, f)
    # Both outcomes occur: the corruptions are neither all fatal nor all harmless.
    assert counts["error"] > 200 and counts["mesh"] > 200, counts


def _small_weights(tmp_path):
    import jax

    from dmd_jax import checkpoints
    from dmd_jax.config import preset
    from dmd_jax.model import init_params

    config = preset("test")
    config = config.with_edits({"model": {"width": 4, "stn_width": 4}})
    params = init_params(config.model, jax.random.PRNGKey(0))
    return checkpoints.save_weights(tmp_path / "seed.msgpack", params, config, {"n": 1})


def _corrupt_weights(data: bytes, rng) -> bytes:
    """One corruption of a weights file: its bytes, or one of its JSON sections."""
    import json

    from flax import serialization

    # A config field edit that stays valid builds a new config, whose param shapes are
    # traced once (about a second): a smaller share of those keeps the test quick.
    ops = ["flip", "cut", "insert", "nested", "field", "json-byte"]
    op = str(rng.choice(ops, p=[0.2, 0.15, 0.15, 0.2, 0.1, 0.2]))
    b = bytearray(data)
    pos = int(rng.integers(len(b)))
    if op == "flip":
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(len(b)))] = int(rng.integers(256))
        return bytes(b)
    if op == "cut":
        return bytes(b[:pos])
    if op == "insert":
        b[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 9))).astype(np.uint8).tobytes()
        return bytes(b)
    payload = serialization.msgpack_restore(data)
    sections = [k for k in ("config", "meta", "policy") if k in payload]
    section = sections[int(rng.integers(len(sections)))]
    if op == "nested":
        depth = int(rng.choice([10, 1000, 5000, 100_000]))
        opener, closer = ('{"a":', "}") if rng.integers(2) else ("[", "]")
        payload[section] = opener * depth + ("1" if opener != "[" else "") + closer * depth
    elif op == "field":
        config = json.loads(payload["config"])
        part = config[str(rng.choice(["model", "loss", "train"]))]
        name = sorted(part)[int(rng.integers(len(part)))]
        awkward = [10**7, 10**30, -1, 0, 1e-300, 1e300, "Infinity", "x", None, [], {}, True]
        value = awkward[int(rng.integers(len(awkward)))]
        part[name] = float("inf") if value == "Infinity" else value
        payload["config"] = json.dumps(config)
    else:
        text = bytearray(payload[section].encode())
        text[int(rng.integers(len(text)))] = int(rng.integers(32, 127))
        payload[section] = text.decode("ascii", errors="replace")
    return serialization.msgpack_serialize(payload)


def test_issue31_weights_corruptions(tmp_path):
    from dmd_jax import checkpoints

    seed = _small_weights(tmp_path)
    data = seed.read_bytes()
    assert _load_or_error(checkpoints.load_weights, seed) is not None
    rng = np.random.default_rng(31)
    loaded = 0
    for case in range(WEIGHTS_CASES):
        path = tmp_path / "case.msgpack"
        corrupted = _corrupt_weights(data, rng)
        path.write_bytes(corrupted)
        try:
            bundle = _load_or_error(checkpoints.load_weights, path)
        except AssertionError as exc:
            raise AssertionError(f"weights case {case}: {exc}") from exc
        if bundle is not None:
            loaded += 1
            # A file that loads is a model that can run: its params fit its config.
            checkpoints.check_params(bundle.params, bundle.config, "loaded")
    assert 0 < loaded < WEIGHTS_CASES
