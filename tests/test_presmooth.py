"""`dmd_jax.presmooth` against independent references, and `denoise`'s use of it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import icosphere

from dmd_jax import baselines, load_pretrained
from dmd_jax.inference import denoise
from dmd_jax.presmooth import MAX_STEPS, laplacian_steps, roughness, steps_for


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
    return load_pretrained()


def test_denoise_follows_the_bundled_policy(bundle):
    from dmd_jax.presmooth import learned_option, noise_features

    policy = bundle.policy
    # The bundled weights carry a learned choice, and the fitted rule beside it.
    assert policy.learns_presmoothing and policy.presmooth_start > 0
    clean, heavy, f = _noisy_sphere(2.0)
    _, info = denoise(clean, f, bundle, return_info=True)
    assert info.presmooth_steps == 0  # a clean mesh is left to the network
    # Light noise: the learned choice.
    _, light, _ = _noisy_sphere(0.3)
    _, info = denoise(light, f, bundle, return_info=True)
    grid = policy.presmooth_grid
    fields = (
        len(grid) + len(policy.route_sigmas),  # the counts, then the routes
        policy.presmooth_center,
        policy.presmooth_scale,
        policy.presmooth_examples,
        policy.presmooth_regrets,
        policy.presmooth_neighbours,
    )
    option = learned_option(noise_features(light, f), *fields)
    assert option < len(grid)  # a noisy sphere is no case for a route
    assert info.presmooth_steps == grid[option] and info.route is None
    # Noise of two edges per coordinate, heavier than any training example: the choice
    # is its largest count, and the rule asks for more.
    _, info = denoise(heavy, f, bundle, return_info=True)
    assert grid[learned_option(noise_features(heavy, f), *fields)] == max(grid)
    expected = steps_for(roughness(heavy, f), policy.presmooth_start, policy.presmooth_per_step)
    assert expected > max(policy.presmooth_grid)
    assert info.presmooth_steps == expected
    assert info.roughness == pytest.approx(roughness(heavy, f))
    # The policy's steps are the explicit argument's (the review after the network, which
    # a fixed count skips, left out).
    unreviewed = bundle._replace(policy=policy.without_review())
    np.testing.assert_allclose(
        denoise(heavy, f, unreviewed), denoise(heavy, f, bundle, presmooth=expected), atol=1e-6
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


# --------------------------------------------------------------------------------------
# The learned choice: what it reads, and how it picks
# --------------------------------------------------------------------------------------


def _features_reference(v, f):
    """`noise_features` written out with trimesh's adjacency angles and the baseline's
    Laplacian steps."""

    def angles(x):
        return np.degrees(trimesh.Trimesh(x, f, process=False).face_adjacency_angles)

    q = np.percentile(angles(v), [25, 50, 75, 90]) + 0.5
    edge = trimesh.Trimesh(v, f, process=False).edges_unique_length.mean()
    out = list(np.log(q))
    moved = {}
    for k in (1, 2, 4, 8):
        x = baselines.run_baseline("laplacian", v, f, iterations=k)
        out.append(np.log((np.median(angles(x)) + 0.5) / q[1]))
        moved[k] = np.log(np.linalg.norm(x - v, axis=1).mean() / edge + 1e-4)
    return np.array(out + [moved[1], moved[2], moved[4]])


def test_noise_features_match_a_trimesh_reference():
    from dmd_jax.presmooth import FEATURE_NAMES, noise_features

    _, noisy, f = _noisy_sphere(0.3)
    got = noise_features(noisy, f)
    assert got.shape == (len(FEATURE_NAMES),)
    # The mean edge: each interior edge counted twice here, once in trimesh; a closed
    # mesh has every edge twice, so the two agree.
    np.testing.assert_allclose(got, _features_reference(noisy, f), atol=1e-6)


def test_noise_features_are_scale_translation_and_rotation_free_and_see_noise():
    from dmd_jax.presmooth import noise_features

    clean, noisy, f = _noisy_sphere(0.3)
    q, _ = np.linalg.qr(np.random.default_rng(1).standard_normal((3, 3)))
    moved = 37.0 * noisy @ q.T + np.array([3.0, -2.0, 10.0])
    np.testing.assert_allclose(noise_features(moved, f), noise_features(noisy, f), atol=1e-6)
    # Smoothing lowers a noisy mesh's angles far more than a clean one's.
    assert noise_features(noisy, f)[4] < noise_features(clean, f)[4] - 0.3
    flat = noise_features(*_grid(8))
    assert np.all(np.isfinite(flat))


def _grid(n):
    ij = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1)
    v = np.concatenate([ij.reshape(-1, 2), np.zeros(((n + 1) ** 2, 1))], 1).astype(float)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
    f = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return v, f


def test_noise_features_of_a_large_mesh_read_its_first_faces(monkeypatch):
    from dmd_jax import presmooth

    _, noisy, f = _noisy_sphere(0.3)
    monkeypatch.setattr(presmooth, "FEATURE_MAX_FACES", 600)
    used, sub = np.unique(f[:600], return_inverse=True)
    np.testing.assert_allclose(
        presmooth.noise_features(noisy, f),
        presmooth.noise_features(noisy[used], sub.reshape(-1, 3)),
    )
    # Faces in no useful order: the whole mesh is read instead.
    shuffled = f[np.random.default_rng(0).permutation(len(f))]
    monkeypatch.setattr(presmooth, "FEATURE_MAX_FACES", 10**9)
    whole = presmooth.noise_features(noisy, shuffled)
    monkeypatch.setattr(presmooth, "FEATURE_MAX_FACES", 600)
    np.testing.assert_allclose(presmooth.noise_features(noisy, shuffled), whole)
    with pytest.raises(ValueError, match="no two faces with an area sharing an edge"):
        presmooth.noise_features(noisy, f[:1])


def test_learned_steps_is_the_mean_regret_of_the_nearest_examples():
    from dmd_jax.presmooth import learned_steps

    rng = np.random.default_rng(0)
    grid = (0, 2, 5)
    examples = rng.normal(size=(30, 4))
    regrets = rng.uniform(0, 1, size=(30, 3))
    center, scale = rng.normal(size=4), rng.uniform(0.5, 2, size=4)
    for _ in range(20):
        x = rng.normal(size=4) * scale + center
        z = (x - center) / scale
        nearest = np.argsort(np.linalg.norm(examples - z, axis=1))[:7]
        expected = grid[int(np.argmin(regrets[nearest].mean(axis=0)))]
        got = learned_steps(x, grid, center, scale, examples.ravel(), regrets.ravel(), 7)
        assert got == expected
    # Equal regrets: the fewest steps.
    flat = np.zeros((30, 3))
    assert learned_steps(center, grid, center, scale, examples.ravel(), flat.ravel(), 5) == 0
