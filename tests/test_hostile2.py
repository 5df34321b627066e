"""Hostile inputs, round 2 (issue 56, families 3-7): no silent wrong answer, no
traceback, nothing overwritten, bounded work, clear and early errors.

One property-based test per family, then the generator of `tests/hostile_cases.py`
(329 cases): a quick sample by default, every case under `-m slow`. What each refusal
says and why is in docs/refusals.md.
"""

from __future__ import annotations

import json
import os
import shutil

import hostile_cases as hc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmd_jax.io import load_mesh, save_mesh

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


# --------------------------------------------------------------------------------------
# Family 3: number formats
# --------------------------------------------------------------------------------------


@FEW
@given(
    exponent=st.integers(0, 9),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
    axis=st.integers(0, 2),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_family3_stl_is_exact_enough_or_refused(tmp_path, exponent, scale, axis, sign):
    """An STL (float32) keeps a mesh at any offset within 1e-3 of its median edge, or is
    refused naming the file and float32; nothing is ever written silently different."""
    folder = _fresh(tmp_path, "stl")
    v = hc.V * scale
    v[:, axis] += sign * 10.0**exponent
    out = folder / "m.stl"
    try:
        save_mesh(out, v, hc.F)
    except ValueError as exc:
        assert "m.stl" in str(exc) and "float32" in str(exc)
        assert not list(folder.iterdir())
        return
    back, faces = load_mesh(out)
    assert len(back) == len(v)
    edge = np.median(np.linalg.norm(v[hc.F] - np.roll(v[hc.F], 1, axis=1), axis=2))
    assert np.abs(np.sort(back, axis=0) - np.sort(v, axis=0)).max() <= 1e-3 * edge


@pytest.mark.parametrize("value", [3.5e38, -1e39, 1e300, np.finfo(np.float64).max])
def test_family3_stl_beyond_float32_is_refused(tmp_path, value):
    v = hc.V.copy()
    v[3, 1] = value
    with pytest.raises(ValueError, match=r"big\.stl: STL stores float32, whose largest"):
        save_mesh(tmp_path / "big.stl", v, hc.F)
    assert not list(tmp_path.iterdir())
    save_mesh(tmp_path / "big.ply", v, hc.F)  # float64 formats keep it exactly
    np.testing.assert_array_equal(load_mesh(tmp_path / "big.ply")[0], v)


@FEW
@given(
    offset=st.sampled_from([1e4, 1e5, 1e6, 1e7, -1e6]),
    axis=st.integers(0, 2),
    method=st.sampled_from(["laplacian", "taubin", "bnf"]),
)
def test_family3_survey_offsets_are_recentred(offset, axis, method):
    """Classic filters (and the network) run in the mesh's own float64 frame: far from
    the origin the result is the result at the origin, moved (docs/refusals.md)."""
    import dmd_jax

    rng = np.random.default_rng(axis)
    v = hc.V + 1e-3 * rng.standard_normal(hc.V.shape)
    shift = np.zeros(3)
    shift[axis] = offset
    near = dmd_jax.denoise_with(method, v, hc.F)
    far = dmd_jax.denoise_with(method, v + shift, hc.F)
    assert np.abs((far - shift) - near).max() < 1e-6


@FEW
@given(
    fmt=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]),
    dup=st.sampled_from(["x", "y", "z", "vertex_indices"]),
)
def test_family3_ply_duplicated_property_is_refused(tmp_path, fmt, dup):
    path = tmp_path / "dup.ply"
    path.write_bytes(hc._ply_with_duplicate(fmt, dup))
    with pytest.raises(ValueError, match=rf"dup\.ply: header line \d+: property '{dup}' appears"):
        load_mesh(path)


# --------------------------------------------------------------------------------------
# Family 4: nothing the user gave is overwritten
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["same", "relative", "hardlink", "symlink"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_family4_export_weights_never_replaces_its_input(tmp_path, how, overwrite):
    hc._f4_export_onto_input(how, overwrite)(tmp_path)


@pytest.mark.parametrize("ext", [".obj", ".off", ".ply", ".stl"])
def test_family4_folder_mode_skips_temp_files(tmp_path, ext):
    from dmd_jax.io import atomic_write, is_temp_name

    hc._f4_temp_names(ext, complete=True)(tmp_path)
    # The names the atomic writer really uses are the ones skipped.
    seen = []
    atomic_write(tmp_path / f"x{ext}", lambda tmp: seen.append(os.path.basename(tmp)))
    assert is_temp_name(seen[0]) and not is_temp_name(f"x{ext}")


@pytest.mark.parametrize(
    "kind", ["denoise-folder", "add-noise-same", "make-dataset-same", "make-dataset-parent"]
)
def test_family4_no_command_overwrites_its_input(tmp_path, kind):
    hc._f4_own_input(kind)(tmp_path)


# --------------------------------------------------------------------------------------
# Family 5: no traceback
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["loop", "mutual", "dangling", "fifo"])
def test_family5_a_broken_entry_costs_only_itself(tmp_path, kind):
    hc._f5_loop_in_folder(kind)(tmp_path)


@pytest.mark.parametrize("command", ["denoise", "evaluate-gt", "render", "denoise-out"])
def test_family5_a_symlink_loop_is_one_line(tmp_path, command):
    hc._f5_loop_input(command)(tmp_path)


@FEW
@given(
    value=st.one_of(
        st.lists(st.integers(), max_size=3),
        st.integers(),
        st.text(max_size=5),
        st.none(),
        st.booleans(),
        st.floats(allow_nan=False),
    )
)
def test_family5_meta_of_the_wrong_type_is_refused(tmp_path, value):
    hc._f5_meta(json.dumps(value))(_fresh(tmp_path, "meta"))


def test_family5_a_file_beyond_the_budget_is_refused_by_its_size(tmp_path):
    hc._f5_too_big(".ply", 3 * 10**9, "1GB")(tmp_path)


# --------------------------------------------------------------------------------------
# Family 6: bounded work
# --------------------------------------------------------------------------------------


@FEW
@given(
    pair=st.sampled_from([(m, p) for m, ps in hc.API_COUNTS.items() for p in ps]),
    value=st.one_of(st.integers(10_001, 2**70), st.integers(-(2**40), -1)),
)
def test_family6_every_count_of_a_classic_filter_is_bounded(pair, value):
    from dmd_jax.baselines import MAX_COUNT

    method, param = pair
    assert MAX_COUNT == 10_000
    hc._f6_api(method, param, value)(None)


@FEW
@given(method=st.sampled_from(hc.CLASSIC), value=st.integers(1001, 2**80))
def test_family6_passes_are_bounded_before_the_work(tmp_path, method, value):
    hc._f6_denoise_with(method, value)(None)
    folder = _fresh(tmp_path, "cli")
    argv = ["denoise", "{src}", "-o", "{tmp}/o.obj", "--method", method]
    hc._f6_cli([*argv, "--iterations", str(value)], "--iterations")(folder)


@pytest.mark.parametrize(
    "name", ["relax", "presmooth", "per-category", "workers", "cnr-steps", "export-max-passes"]
)
def test_family6_cli_counts_are_bounded(tmp_path, name):
    case = next(c for c in hc.family6() if c.name == f"f6-cli-{name}")
    case.run(tmp_path)


# --------------------------------------------------------------------------------------
# Family 7: one clear line, early
# --------------------------------------------------------------------------------------


@FEW
@given(
    arg=st.sampled_from(["--elev", "--azim"]),
    value=st.one_of(
        st.sampled_from(["nan", "inf", "-inf"]),
        st.floats(360.001, 1e300).map(repr),
        st.floats(-1e300, -360.001).map(repr),
    ),
    ext=st.sampled_from([".png", ".html"]),
)
def test_family7_render_view_is_checked_first(tmp_path, arg, value, ext):
    hc._f7_render_view(arg, value, ext)(_fresh(tmp_path, "render"))


def test_family7_render_api_refuses_absurd_views():
    from dmd_jax.render import check_view

    for bad in (float("nan"), float("inf"), 1e20, -361.0, "up"):
        with pytest.raises(ValueError, match="elev must be an angle"):
            check_view(bad, 0.0)
    check_view(-90.0, 360.0)


@pytest.mark.parametrize(
    "case",
    [
        "f7-long-name-denoise-255",
        "f7-long-name-add-noise-300",
        "f7-long-folder-name-250",
        "f7-max-memory-1KB",
        "f7-url-denoise-https",
        "f7-url-info-s3",
        "f7-version-True",
        "f7-version-'2'",
        "f7-missing-input-one",
        "f7-evaluate-faces-shuffled",
        "f7-evaluate-corners-rotated",
        "f7-folder-names-degenerate",
        "f7-concurrent-denoise",
        "f7-concurrent-make-dataset",
    ],
)
def test_family7_errors_are_one_line_and_early(tmp_path, case):
    (found,) = [c for c in hc.family7() if c.name == case]
    found.run(tmp_path)


def test_family7_max_memory_takes_numpy_numbers():
    from dmd_jax.memory_plan import parse_memory

    for value in (np.int64(8 * 10**9), np.uint64(8 * 10**9), np.float32(8e9), np.int32(10**9)):
        assert parse_memory(value) == int(value)
    for bad in (np.bool_(True), np.float64("nan"), np.int64(0)):
        with pytest.raises(ValueError, match="max_memory"):
            parse_memory(bad)


@pytest.mark.slow  # a network run: ~25 s with its compilation
@pytest.mark.parametrize("kind", ["int64", "uint64", "float32"])
def test_family7_denoise_takes_numpy_max_memory(tmp_path, kind):
    hc._f7_numpy_memory(kind)(tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("fail_at", [1, 6])
def test_family7_demo_on_a_full_disk_leaves_nothing(tmp_path, fail_at):
    hc._f7_demo_full_disk(fail_at)(tmp_path)


# --------------------------------------------------------------------------------------
# The generator: a sample by default, all of it under -m slow
# --------------------------------------------------------------------------------------

ALL = hc.cases()
QUICK = [c for c in ALL if not c.name.startswith(hc.SLOW_PREFIXES)][::7]


def _check(case, tmp_path):
    why = hc.run_case(case, tmp_path)
    assert why is None, f"{case.name}: {why}"


def test_the_generator_holds_at_least_300_cases():
    assert len(ALL) >= 300 and len({c.name for c in ALL}) == len(ALL)
    assert {c.family for c in ALL} == {3, 4, 5, 6, 7}


@pytest.mark.parametrize("case", QUICK, ids=[c.name for c in QUICK])
def test_hostile_case_sample(tmp_path, case):
    _check(case, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("case", ALL, ids=[c.name for c in ALL])
def test_hostile_case(tmp_path, case):
    _check(case, tmp_path)
