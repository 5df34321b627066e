"""Hostile inputs, round 3 (issue 65, families 2-8): number syntax and line breaks of
the text readers, arguments of every public function, meshes with nothing to denoise,
folder mode onto itself, the experiments runner's paths, and clear messages.

Property tests where the input space is large (number tokens, line breaks), then the
round-3 cases of `tests/hostile_cases.py` (`round3()`): a quick sample by default, all
of them under `-m slow`. The rules are in docs/refusals.md.
"""

from __future__ import annotations

import math
import shutil

import hostile_cases as hc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmd_jax.io import _syntax, load_mesh

FEW = settings(
    max_examples=25,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _fresh(tmp_path, name: str):
    folder = tmp_path / name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir()
    return folder


def _c_strtod(token: str) -> float | None:
    """What C strtod reads when it consumes all of `token` (the reference grammar:
    ASCII decimal, hexadecimal, inf/infinity/nan[(chars)]), else None."""
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.strtod.restype = ctypes.c_double
    libc.strtod.argtypes = [ctypes.c_char_p, ctypes.POINTER(ctypes.c_char_p)]
    if not token or not token.isascii() or token[0] in " \t\n\v\f\r":
        return None
    raw = token.encode()
    end = ctypes.c_char_p()
    value = libc.strtod(raw, ctypes.byref(end))
    used = (
        ctypes.cast(end, ctypes.c_void_p).value
        - ctypes.cast(ctypes.c_char_p(raw), ctypes.c_void_p).value
    )
    return value if used == len(raw) else None


NUMBER_CHARS = "0123456789+-.eExXpPaAfFinIN_()\u00a0\uff11\u0661 "


# --------------------------------------------------------------------------------------
# Family 2: number tokens are read as C reads them, or refused
# --------------------------------------------------------------------------------------


@FEW
@given(
    token=st.one_of(
        st.text(alphabet=NUMBER_CHARS, min_size=1, max_size=8),
        st.floats(allow_nan=False).map(repr),
        st.floats(allow_nan=False).map(float.hex),
        st.integers(-(10**20), 10**20).map(str),
    )
)
def test_family2_float_tokens_follow_strtod(token):
    """Every token: the value C strtod reads whole, or a refusal naming the token."""
    expected = _c_strtod(token.strip(" ")) if token.strip(" ") == token else None
    try:
        got = _syntax.float_of(token)
    except ValueError as exc:
        assert expected is None, f"{token!r}: refused, strtod reads {expected}"
        assert "is not a number" in str(exc)
        return
    assert expected is not None, f"{token!r}: read as {got}, strtod refuses it"
    assert got == expected or (math.isnan(got) and math.isnan(expected))


@FEW
@given(token=st.text(alphabet="0123456789+-_ \u00a0\uff11\u0661xe.", min_size=1, max_size=6))
def test_family2_integer_tokens_follow_strtol(token):
    import re

    ok = re.fullmatch(r"[+-]?[0-9]+", token) is not None
    try:
        got = _syntax.int_of(token)
    except ValueError:
        assert not ok, token
        return
    assert ok and got == int(token), token


@FEW
@given(
    fmt=st.sampled_from(["obj", "off", "ply", "stl"]),
    token=st.sampled_from(hc.BAD_NUMBERS),
    where=st.sampled_from(["coordinate", "index"]),
)
def test_family2_every_text_reader_refuses_python_only_numbers(tmp_path, fmt, token, where):
    if fmt == "stl" and where == "index":
        where = "coordinate"  # STL has no indices
    folder = _fresh(tmp_path, "n")
    p = folder / f"n.{fmt}"
    p.write_bytes(hc.text_mesh(fmt, token, where))
    with pytest.raises(ValueError, match=rf"n\.{fmt}: line \d+: .*not (a number|an integer)"):
        load_mesh(p)


@pytest.mark.parametrize("fmt", ["obj", "off", "ply", "stl"])
def test_family2_cli_refuses_python_only_numbers(tmp_path, fmt):
    hc._r3_number(fmt, "1_0", "coordinate", "cli")(tmp_path)


@pytest.mark.parametrize("fmt", ["obj", "off", "ply", "stl"])
def test_family2_c_numbers_read_as_c_reads_them(tmp_path, fmt):
    for token, value in (("0x1p-2", 0.25), ("+1e0", 1.0), ("-.5E1", -5.0)):
        hc._r3_good_number(fmt, token, value)(_fresh(tmp_path, "g"))


# --------------------------------------------------------------------------------------
# Family 3: lines end at \n, \r\n and \r only
# --------------------------------------------------------------------------------------


@FEW
@given(
    fmt=st.sampled_from(["obj", "off", "ply"]),
    brk=st.sampled_from(hc.BREAKS + ("\u000b\u2028", "\x1f", "\u0085\u2029")),
)
def test_family3_a_unicode_break_in_a_comment_hides_nothing(tmp_path, fmt, brk):
    hc._r3_break_in_comment(fmt, brk)(_fresh(tmp_path, "c"))


@pytest.mark.parametrize("brk", ["\n", "\r\n", "\r"])
def test_family3_real_line_breaks_still_end_lines(tmp_path, brk):
    text = hc.text_mesh("obj").decode().replace("\n", brk)
    p = tmp_path / "m.obj"
    p.write_text(text, newline="")
    v, f = load_mesh(p)
    assert v.shape == (4, 3) and f.shape == (4, 3)
    # A real break after a comment does start a statement.
    p.write_text("# note" + brk + text, newline="")
    assert load_mesh(p)[0].shape == (4, 3)


def test_family3_the_syntax_helpers():
    assert _syntax.lines("a\u2028b\x0cc\rd\r\ne\nf") == ["a\u2028b\x0cc", "d", "e", "f"]
    assert _syntax.tokens(" v\t1\x0b2\xa03 ") == ["v", "1", "2\xa03"]


# --------------------------------------------------------------------------------------
# Family 4: every public function checks its arguments
# --------------------------------------------------------------------------------------

FAMILY4 = [c for c in hc.round3() if c.family == 4]


@pytest.mark.parametrize("case", FAMILY4, ids=[c.name for c in FAMILY4])
def test_family4_public_functions_check_their_arguments(tmp_path, case):
    why = hc.run_case(case, tmp_path)
    assert why is None, f"{case.name}: {why}"


def test_family4_a_huge_or_tiny_view_is_a_direction():
    import dmd_jax

    v, f = hc.V, hc.F
    ref = dmd_jax.add_noise(3, v, f, "scanner", 0.5, view=[1.0, 1.0, 0.0])
    for scale in (1e300, 1e-300):
        got = dmd_jax.add_noise(3, v, f, "scanner", 0.5, view=[scale, scale, 0.0])
        np.testing.assert_array_equal(got, ref)
    assert np.abs(ref - v).max() > 0


def test_family4_cli_add_noise_refuses_a_bad_seed(tmp_path):
    src = hc.write(tmp_path / "in.obj")
    hc.refused_quietly(
        tmp_path,
        ["add-noise", src, "-o", tmp_path / "o.obj", "--level", "0.1", "--seed", "1.5"],
        "--seed",
    )


# --------------------------------------------------------------------------------------
# Family 5: nothing to denoise, nothing changes
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kind",
    [
        "tetrahedron",
        "irregular-tetrahedron",
        "octahedron",
        "icosahedron",
        "one-triangle",
        "collinear",
        "two-tetrahedra",
    ],
)
def test_family5_every_classic_method_leaves_it(kind):
    for method in (*hc.CLASSIC, "cnr"):
        hc._r3_still(kind, method)(None)


@pytest.mark.parametrize("kind", ["icosahedron", "collinear"])
def test_family5_dmd_leaves_it_and_says_why(kind):
    import dmd_jax

    v, f = hc.still_mesh(kind)
    out, info = dmd_jax.denoise(v, f, return_info=True)
    np.testing.assert_array_equal(out, v)
    assert info.path == "unchanged" and "nothing to denoise" in info.unchanged
    assert info.passes == 0 and info.still_vertices == len(v)


def test_family5_a_still_part_beside_a_noisy_one_is_held_exactly():
    import dmd_jax

    noisy = hc.V + 0.02 * np.random.default_rng(0).standard_normal(hc.V.shape)
    tv, tf = hc.tetrahedron()
    v = np.concatenate([noisy, tv * 0.3 + 5.0])
    f = np.concatenate([hc.F, tf + len(hc.V)])
    for method in ("laplacian", "bnf"):
        out = dmd_jax.denoise_with(method, v, f)
        np.testing.assert_array_equal(out[len(hc.V) :], v[len(hc.V) :])
        assert np.abs(out[: len(hc.V)] - noisy).max() > 1e-3  # the noisy part is denoised


def test_family5_cli_writes_a_tetrahedron_unchanged(tmp_path):
    v, f = hc.tetrahedron()
    src = hc.write(tmp_path / "t.ply", v, f)
    code, _, err = hc.cli("denoise", src, "-o", tmp_path / "o.ply", "--method", "taubin")
    assert code == 0, err
    np.testing.assert_array_equal(load_mesh(tmp_path / "o.ply")[0], v)


def test_family5_a_noisy_mesh_is_never_still():
    from dmd_jax.consistency import still_faces

    rng = np.random.default_rng(1)
    for level in (0.01, 0.1, 0.5):
        v = hc.V + level * rng.standard_normal(hc.V.shape)
        assert not still_faces(v, hc.F).any()
    v2, f2 = hc.sphere(3)
    assert not still_faces(v2 + 0.3 * rng.standard_normal(v2.shape), f2).any()


# --------------------------------------------------------------------------------------
# Families 6, 7, 8
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["same", "dot", "dotdot"])
def test_family6_skip_existing_onto_the_input_folder_is_refused(tmp_path, how):
    hc._r3_folder_onto_itself(how)(tmp_path)


@pytest.mark.parametrize("command", ["aggregate", "index"])
@pytest.mark.parametrize("where", ["missing", "empty", "file", "bad-json"])
def test_family7_experiments_paths_are_one_line(tmp_path, command, where):
    import contextlib
    import io

    from experiments.__main__ import main

    (tmp_path / "empty").mkdir()
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "bad" / "p").mkdir(parents=True)
    (tmp_path / "bad" / "plan.json").write_text("{not json")
    (tmp_path / "bad" / "p" / "summary.json").write_text("[1,")
    path = {"missing": "nothing", "empty": "empty", "file": "file.txt", "bad-json": "bad"}
    before = hc.snapshot(tmp_path)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main([command, str(tmp_path / path[where])])
    hc.refused((code, "", err.getvalue()), path[where])
    assert hc.snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "kind",
    [
        "gzip-stl",
        "gzip-obj",
        "off-in-obj",
        "ply-faces-element",
        "max-memory:1e3",
        "max-memory:1e400GB",
        "max-memory:0.5",
        "unwritable",
    ],
)
def test_family8_messages_say_what_is_wrong(tmp_path, kind):
    hc._r3_message(kind)(tmp_path)


def test_family8_max_memory_in_the_api():
    from dmd_jax.memory_plan import parse_memory

    assert parse_memory("1e3") == 1000 and parse_memory("2E3MB") == 2 * 10**9
    for bad, words in (("1e400GB", "more than any"), ("0.5", "less than one"), (1e300, "more")):
        with pytest.raises(ValueError, match=f"max_memory.*{words}"):
            parse_memory(bad)


# --------------------------------------------------------------------------------------
# The generator's round 3: a sample by default, all of it under -m slow
# --------------------------------------------------------------------------------------

ROUND3 = hc.round3()
# Cases that run the network, or a subprocess (seconds each): left out of the sample.
_SLOW = ("-dmd", "r3-f7-")
QUICK = [c for c in ROUND3 if not c.name.endswith(_SLOW) and not c.name.startswith(_SLOW)][::5]


def test_round3_holds_every_family():
    assert len(ROUND3) >= 150 and len({c.name for c in ROUND3}) == len(ROUND3)
    assert {c.family for c in ROUND3} == {2, 3, 4, 5, 6, 7, 8}


@pytest.mark.parametrize("case", QUICK, ids=[c.name for c in QUICK])
def test_round3_sample(tmp_path, case):
    why = hc.run_case(case, tmp_path)
    assert why is None, f"{case.name}: {why}"


@pytest.mark.slow
@pytest.mark.parametrize("case", ROUND3, ids=[c.name for c in ROUND3])
def test_round3_case(tmp_path, case):
    why = hc.run_case(case, tmp_path)
    assert why is None, f"{case.name}: {why}"
