"""`dmd_jax.presmooth` against independent references, and `denoise`'s use of it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import icosphere, rules_only

from dmd_jax import baselines, load_pretrained
from dmd_jax.inference import denoise
from dmd_jax.presmooth import MAX_STEPS, bend_share, laplacian_steps, roughness, steps_for


def _noisy_sphere(sigma: float, seed: int = 0):
    v, f = icosphere(3)
    rng = np.random.default_rng(seed)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
    return v, v + sigma * edge * rng.standard_normal(v.shape), f


@pytest.mark.parametrize("open_boundary", [False, True])
def test_laplacian_steps_equal_the_laplacian_baseline(open_boundary):
    _, noisy, f = _noisy_sphere(0.5)
    if open_boundary:  # a cap removed: boundary vertices average along the boundary only
        f = f[noisy[f].mean(axis=1)[:, 2] < 0.6]
    ours = laplacian_steps(noisy, f, 7)
    reference = np.asarray(baselines.laplacian(noisy, f, lam=0.5, iterations=7), np.float64)
    np.testing.assert_allclose(ours, reference, atol=1e-6)


def test_laplacian_steps_leave_the_input_alone_and_isolated_vertices_in_place():
    _, noisy, f = _noisy_sphere(0.5)
    extra = np.vstack([noisy, [[5.0, 5.0, 5.0]]])  # an isolated vertex
    before = extra.copy()
    out = laplacian_steps(extra, f, 3)
    np.testing.assert_array_equal(extra, before)
    np.testing.assert_array_equal(out[-1], extra[-1])
    np.testing.assert_array_equal(laplacian_steps(extra, f, 0), extra)


def test_roughness_is_trimesh_median_adjacency_angle():
    _, noisy, f = _noisy_sphere(0.4)
    mesh = trimesh.Trimesh(noisy, f, process=False)
    expected = float(np.degrees(np.median(mesh.face_adjacency_angles)))
    assert roughness(noisy, f) == pytest.approx(expected, abs=1e-6)


def test_sampled_roughness_of_a_large_mesh_is_close_to_the_exact_one(monkeypatch):
    from dmd_jax import presmooth

    _, noisy, f = _noisy_sphere(0.4)
    exact = roughness(noisy, f)
    monkeypatch.setattr(presmooth, "EXACT_MAX_FACES", 100)
    monkeypatch.setattr(presmooth, "SAMPLED_HALF_EDGES", 1000)
    a, b = presmooth._edge_pairs(f, len(noisy))
    assert 300 < len(a) < 700 and np.all(a != b)  # about 500 of the 1,920 pairs
    assert roughness(noisy, f) == pytest.approx(exact, abs=3.0)


def test_roughness_is_scale_translation_and_rotation_free():
    _, noisy, f = _noisy_sphere(0.4)
    q, _ = np.linalg.qr(np.random.default_rng(1).standard_normal((3, 3)))
    moved = 37.0 * noisy @ q.T + np.array([3.0, -2.0, 10.0])
    assert roughness(moved, f) == pytest.approx(roughness(noisy, f), abs=1e-6)


def test_roughness_grows_with_noise_and_ignores_degenerate_faces():
    clean, _, f = _noisy_sphere(0.0)
    values = [roughness(_noisy_sphere(s)[1], f) for s in (0.0, 0.2, 1.0, 3.0)]
    assert values == sorted(values) and values[0] < 10 < 60 < values[-1]
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert roughness(tri, np.array([[0, 1, 2]])) == 0.0  # no adjacent pair
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    assert roughness(flat, np.array([[0, 1, 2], [0, 2, 3]])) == 0.0  # one face degenerate


@pytest.mark.parametrize(
    "rough, expected",
    [(10.0, 0), (25.0, 0), (27.4, 0), (27.6, 1), (60.0, 7), (130.0, MAX_STEPS)],
)
def test_steps_for_is_a_clipped_straight_line(rough, expected):
    assert steps_for(rough, 25.0, 5.0) == expected
    assert steps_for(rough, 0.0, 5.0) == 0  # start 0: no pre-smoothing


@pytest.fixture(scope="module")
def bundle():
    # The rule under test, whether or not the bundled weights let a controller choose.
    return rules_only(load_pretrained())


def test_denoise_follows_the_bundled_policy(bundle):
    policy = bundle.policy
    assert policy.presmooth_start > 0
    clean, heavy, f = _noisy_sphere(2.0)
    _, info = denoise(clean, f, bundle, return_info=True)
    assert info.presmooth_steps == 0  # a clean mesh is left to the network
    # Noise of two edges per coordinate, heavier than any training example: the rule.
    _, info = denoise(heavy, f, bundle, return_info=True)
    expected = steps_for(roughness(heavy, f), policy.presmooth_start, policy.presmooth_per_step)
    assert expected > 0
    assert info.presmooth_steps == expected
    assert info.roughness == pytest.approx(roughness(heavy, f))
    # The policy's steps are the explicit argument's.
    np.testing.assert_allclose(
        denoise(heavy, f, bundle), denoise(heavy, f, bundle, presmooth=expected), atol=1e-6
    )


def test_presmoothed_denoise_stays_translation_and_scale_equivariant(bundle):
    _, heavy, f = _noisy_sphere(2.0)
    out, info = denoise(heavy, f, bundle, return_info=True)
    assert info.presmooth_steps > 0
    shift, scale = np.array([40.0, -7.0, 3.0]), 250.0
    moved = denoise(scale * heavy + shift, f, bundle)
    edge = np.linalg.norm(out[f[:, 0]] - out[f[:, 1]], axis=1).mean()
    assert np.abs((moved - shift) / scale - out).max() < 1e-4 * edge


def test_presmoothing_helps_heavy_noise(bundle):
    clean, heavy, f = _noisy_sphere(2.0)

    def error(x):
        a = trimesh.Trimesh(x, f, process=False).face_normals
        b = trimesh.Trimesh(clean, f, process=False).face_normals
        return float(np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1))).mean())

    assert error(denoise(heavy, f, bundle)) < 0.5 * error(denoise(heavy, f, bundle, presmooth=0))


@pytest.mark.parametrize("bad", [-1, 1.5, True, "3"])
def test_denoise_rejects_bad_presmooth(bundle, bad):
    v, f = icosphere(1)
    with pytest.raises((ValueError, TypeError), match="presmooth"):
        denoise(v, f, bundle, presmooth=bad)


def _convex_solids():
    octa = (
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
    )
    tetra = (
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]],
    )
    ico = trimesh.creation.icosphere(0)
    return {
        "tetrahedron": tetra,
        "octahedron": octa,
        "icosahedron": (ico.vertices, ico.faces),
    }


def test_bend_share_against_a_brute_force_count():
    rng = np.random.default_rng(3)
    v, f = icosphere(2)
    x = v + 0.02 * rng.standard_normal(v.shape)
    m = trimesh.Trimesh(x, f, process=False)
    bent = m.face_adjacency_angles > np.radians(1.0)
    convex = m.face_adjacency_convex[bent].mean()  # trimesh's own test of each edge
    assert bend_share(x, f) == pytest.approx(min(convex, 1 - convex))
    assert bend_share(v, f) == 0.0  # a clean sphere bends one way only
    assert bend_share(v, f[:1]) == 0.5  # no pair: nothing to tell


@pytest.mark.parametrize("name", ["tetrahedron", "octahedron", "icosahedron"])
def test_a_coarse_convex_solid_is_not_smoothed_to_a_point(bundle, name):
    v, f = (np.asarray(a) for a in _convex_solids()[name])
    v = v.astype(np.float64)
    assert roughness(v, f) > bundle.policy.presmooth_start  # the rule alone would smooth it
    assert bend_share(v, f) == 0.0
    out, info = denoise(v, f, bundle, return_info=True)
    assert info.presmooth_steps == 0
    assert np.ptp(out, axis=0).max() > 0.9 * np.ptp(v, axis=0).max()  # was 0.001 (octahedron)


@pytest.mark.parametrize("level", [0.3, 0.6, 1.0])
def test_noise_bends_both_ways(level):
    v, f = icosphere(3)
    x = v + level * 0.05 * np.random.default_rng(0).standard_normal(v.shape)
    assert bend_share(x, f) > 0.3
