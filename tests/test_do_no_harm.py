"""Issue 56, families 1 and 2: a clean mesh comes out unchanged, and inconsistent input
(flipped winding, parts of very different sizes) does not change the answer.

The clean shapes are built here with trimesh and NumPy (a fan disc of valence 128, a cone
with a sharp apex, a box, a thin plate, the subdivided stress family of
`dmd_jax.data.stress`); the change is the mean angle between each face's normal before
and after, with trimesh's face normals as the reference.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import icosphere
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dmd_jax
from dmd_jax.consistency import exact_vertices, oriented_faces, scale_groups
from dmd_jax.inference import denoise

# Issue 56's bound on a clean mesh's mean face-normal change, degrees.
CLEAN_BOUND = 2.0


def mean_normal_change(a, b, faces) -> float:
    na = trimesh.Trimesh(a, faces, process=False).face_normals
    nb = trimesh.Trimesh(b, faces, process=False).face_normals
    return float(np.degrees(np.arccos(np.clip((na * nb).sum(1), -1, 1))).mean())


def fan_disc(valence: int):
    t = np.linspace(0, 2 * np.pi, valence, endpoint=False)
    v = np.concatenate([[[0.0, 0.0, 0.0]], np.c_[np.cos(t), np.sin(t), 0 * t]])
    f = np.array([[0, 1 + i, 1 + (i + 1) % valence] for i in range(valence)])
    return v, f


def _mesh(m):
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces)


def pyramid(sides: int = 4, height: float = 0.7):
    """A pyramid of `sides` triangles on a fanned `sides`-gon base: 2·sides − 2 faces."""
    t = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    v = np.concatenate([np.c_[np.cos(t), np.sin(t), 0 * t], [[0.0, 0.0, height]]])
    base = [[0, i + 1, i] for i in range(1, sides - 1)]
    side = [[i, (i + 1) % sides, sides] for i in range(sides)]
    return v, np.array(base + side)


def spiked_disc(height: float):
    """A flat disc (a centre, 7 then 14 vertices on two rings: no three of the first
    ring collinear) whose centre is moved by `height` along the normal."""
    t1 = 2 * np.pi * np.arange(7) / 7
    t2 = 2 * np.pi * np.arange(14) / 14
    v = np.concatenate(
        [
            [[0.0, 0.0, height]],
            np.c_[np.cos(t1), np.sin(t1), 0 * t1],
            np.c_[2 * np.cos(t2), 2 * np.sin(t2), 0 * t2],
        ]
    )
    r1 = lambda i: 1 + i % 7  # noqa: E731
    r2 = lambda i: 8 + i % 14  # noqa: E731
    f = [[0, r1(i), r1(i + 1)] for i in range(7)]
    for i in range(7):
        f += [[r1(i), r2(2 * i), r2(2 * i + 1)], [r1(i), r2(2 * i + 1), r2(2 * i + 2)]]
        f += [[r1(i), r2(2 * i + 2), r1(i + 1)]]
    return v, np.array(f), 0


CLEAN = {
    "fan disc, valence 128": lambda: fan_disc(128),
    "cone, 64 sections": lambda: _mesh(trimesh.creation.cone(radius=1.0, height=2.0, sections=64)),
    "cube": lambda: _mesh(trimesh.creation.box(extents=(1, 1, 1))),
    "thin plate 100:1": lambda: _mesh(trimesh.creation.box(extents=(10, 10, 0.1))),
    "pyramid, 6 faces": pyramid,
}


@pytest.fixture(scope="module")
def bundle():
    return dmd_jax.load_pretrained()


@pytest.mark.parametrize("name", sorted(CLEAN))
def test_clean_cad_meshes_come_out_unchanged(bundle, name):
    v, f = CLEAN[name]()
    out, info = denoise(v, f, bundle, return_info=True)
    assert mean_normal_change(v, out, f) <= CLEAN_BOUND
    assert info.exact_vertices > 0 and info.presmooth_steps == 0


@pytest.mark.parametrize("name", ["pyramid", "sharp_cone", "fan_disc", "thin_plate"])
def test_the_stress_family_comes_out_unchanged(bundle, name):
    from dmd_jax.data.stress import stress_shape

    v, f = stress_shape(name)
    out = denoise(v, f, bundle)
    assert mean_normal_change(v, out, f) <= CLEAN_BOUND


@pytest.mark.parametrize("name", sorted(CLEAN))
def test_the_cli_leaves_a_clean_part_unchanged(tmp_path, name):
    from dmd_jax.cli import main
    from dmd_jax.io import load_mesh, save_mesh

    v, f = CLEAN[name]()
    save_mesh(tmp_path / "part.ply", v, f)
    assert main(["denoise", str(tmp_path / "part.ply"), "-o", str(tmp_path / "out.ply")]) == 0
    out, faces = load_mesh(tmp_path / "out.ply")
    assert mean_normal_change(v, out, faces) <= CLEAN_BOUND


def test_a_noisy_mesh_has_no_exact_vertex_and_runs_as_before():
    v, f = icosphere(3)
    noisy = v + 0.002 * np.random.default_rng(0).standard_normal(v.shape)
    assert not exact_vertices(noisy, f).any()
    assert not exact_vertices(v, f).any()  # a clean smooth sphere: no two faces coplanar
    assert oriented_faces(f, len(v))[1] == 0


@pytest.mark.parametrize("sides", [3, 4, 5, 8])
@pytest.mark.parametrize("height", [0.05, 0.7, 20.0, -0.7])
def test_a_solid_tip_is_held_and_comes_out_unchanged(bundle, sides, height):
    v, f = pyramid(sides, height)
    if height < 0:
        f = f[:, ::-1]  # the apex below the base: wound outward again
    assert trimesh.Trimesh(v, f, process=False).is_volume
    held = exact_vertices(v, f)
    assert held[-1] == (sides > 3)  # a triangular base has no coplanar pair: nothing held
    if sides > 3:
        np.testing.assert_allclose(denoise(v, f, bundle), v, rtol=0, atol=1e-9 * abs(height))


@pytest.mark.parametrize("height", [0.3, -0.3, 2.0])
def test_a_spike_on_a_flat_is_no_tip_and_is_denoised(bundle, height):
    v, f, centre = spiked_disc(height)
    held = exact_vertices(v, f)
    assert not held[centre] and held.sum() == len(v) - 1
    out = denoise(v, f, bundle)
    assert abs(out[centre, 2]) < 0.5 * abs(height)  # pulled back toward the flat
    np.testing.assert_allclose(np.delete(out, centre, 0), np.delete(v, centre, 0), atol=1e-12)


def test_exact_vertices_against_a_brute_force_plane_count():
    v, f = _mesh(trimesh.creation.box(extents=(2, 1, 1)))
    v, f = trimesh.remesh.subdivide(v, f)
    normals = trimesh.Trimesh(v, f, process=False).face_normals
    held = exact_vertices(v, f)
    for i in range(len(v)):
        planes = {tuple(np.round(normals[j], 6)) for j in np.flatnonzero((f == i).any(1))}
        assert held[i] == (len(planes) <= 4)  # every face of a box has a coplanar neighbour


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**16),
    share=st.floats(0.02, 0.5),
    level=st.sampled_from([0, 1, 2]),
)
def test_flipped_faces_are_oriented_back(seed, share, level):
    v, f = icosphere(level)
    rng = np.random.default_rng(seed)
    flip = rng.random(len(f)) < share
    if flip.sum() * 2 >= len(f):  # the majority's winding is kept: keep it the original's
        flip[:] = False
    wrong = f.copy()
    wrong[flip] = wrong[flip][:, ::-1]
    fixed, count = oriented_faces(wrong, len(v))
    np.testing.assert_array_equal(fixed, f)
    assert count == flip.sum()


def test_a_mobius_strip_is_left_as_it_is():
    # Top vertices 0..n-1, bottom n..2n-1; the last quad joins top to bottom: a half twist.
    n = 16
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    tilt = np.c_[np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)] * 0.3
    centre = np.c_[np.cos(t), np.sin(t), np.zeros(n)]
    v = np.concatenate([centre + tilt, centre - tilt])
    f = []
    for i in range(n):
        top, bottom = i, n + i
        nxt_top, nxt_bottom = (i + 1, n + i + 1) if i < n - 1 else (n, 0)
        f += [[top, bottom, nxt_top], [bottom, nxt_bottom, nxt_top]]
    f = np.array(f)
    assert not trimesh.Trimesh(v, f, process=False).is_winding_consistent
    out, count = oriented_faces(f, len(v))
    assert count == 0 and np.array_equal(out, f)


@pytest.mark.parametrize("share", [0.1])
def test_flipped_winding_does_not_change_the_result(bundle, share):
    v, f = icosphere(3)
    noisy = dmd_jax.add_noise(0, v, f, "gaussian", 0.2, units="edge", direction="normal")
    flip = np.random.default_rng(1).random(len(f)) < share
    wrong = f.copy()
    wrong[flip] = wrong[flip][:, ::-1]
    expected = denoise(noisy, f, bundle)
    out, info = denoise(noisy, wrong, bundle, return_info=True)
    assert info.flipped_faces == flip.sum()
    np.testing.assert_allclose(out, expected, atol=1e-6)


@pytest.mark.parametrize("small, large", [(1e-6, 1e6), (1e-3, 10.0)])
def test_parts_of_very_different_sizes_each_denoise_as_alone(bundle, small, large):
    v, f = icosphere(2)
    v = v.astype(np.float64)  # float32 could not hold the small part beside the large one
    noisy = dmd_jax.add_noise(3, v, f, "gaussian", 0.2, units="edge", direction="normal")
    shift = np.array([3.0, 0.0, 0.0])
    both_v = np.concatenate([noisy * large, noisy * small + shift * large])
    both_f = np.concatenate([f, f + len(v)])
    groups = scale_groups(both_v, both_f)
    assert groups is not None and len(groups) == 2
    out, info = denoise(both_v, both_f, bundle, return_info=True)
    assert info.scale_groups == 2
    # Each part as if it were denoised alone, at its own (float64-rounded) coordinates.
    n = len(v)
    np.testing.assert_array_equal(out[:n], denoise(both_v[:n], f, bundle))
    np.testing.assert_array_equal(out[n:], denoise(both_v[n:], f, bundle))
    # The small part keeps its shape (it used to collapse to a point) and is denoised.
    error = mean_normal_change(v, (out[n:] - shift * large) / small, f)
    assert error < mean_normal_change(v, noisy, f) / 2


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    extents=st.tuples(*[st.floats(0.05, 10.0)] * 3),
    scale=st.sampled_from([1e-6, 1.0, 1e5]),
    offset=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**16),
)
def test_any_clean_box_anywhere_comes_out_unchanged(bundle, extents, scale, offset, seed):
    import jax

    from dmd_jax.pipeline import random_rotation

    v, f = _mesh(trimesh.creation.box(extents=extents))
    v = (v @ random_rotation(jax.random.PRNGKey(seed)).T + offset) * scale
    out = denoise(v, f, bundle)
    # Measured at unit scale: trimesh calls faces of 1e-7 degenerate.
    assert mean_normal_change(v / scale, out / scale, f) <= CLEAN_BOUND


def test_the_tolerance_is_the_input_precision():
    from dmd_jax.consistency import EXACT_TOLERANCE_CAP, EXACT_TOLERANCE_FLOOR, exact_tolerance

    v, f = _mesh(trimesh.creation.box(extents=(1, 1, 1)))
    assert exact_tolerance(np.float64, v, f) == EXACT_TOLERANCE_FLOOR
    assert exact_tolerance(np.int32, v, f) == EXACT_TOLERANCE_FLOOR
    single = exact_tolerance(np.float32, v, f)
    assert EXACT_TOLERANCE_FLOOR < single < EXACT_TOLERANCE_CAP
    # float32 coordinates a thousand parts away from the origin: no plane is certain.
    assert exact_tolerance(np.float32, v + 1e4, f) == 0.0
    assert not exact_vertices(v, f, 0.0).any()
