"""Bounded fuzzing of the mesh loaders: any bytes give a valid mesh or a `ValueError`.

Inputs are raw random bytes, lines of random keywords and numbers, and mutations of
valid OBJ / OFF / PLY (ASCII, binary) / STL (ASCII, binary) files: flipped, deleted,
inserted and duplicated bytes, cuts, and numbers replaced by awkward ones (NaN, huge
counts, negative indices...). Anything
other than a valid mesh or a `ValueError` fails: another exception type, a hang (a
20 s alarm per file) or a crash of the worker. The default suite runs a few dozen
inputs; `make test-slow` runs thousands and every prefix of every seed file.
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
