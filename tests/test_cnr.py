"""CNR baseline: descriptor against a loop-by-loop reference, invariances, training, weights."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import crop_mesh, icosphere, shared_mesh_path, tetrahedron

from dmd_jax import baselines
from dmd_jax.baselines import cascaded_regression as C
from dmd_jax.baselines._common import TRACE_COUNTS
from dmd_jax.baselines.cascaded_regression import features as CF
from dmd_jax.baselines.cascaded_regression import model as CM
from dmd_jax.io import load_mesh
from dmd_jax.metrics import mesh_metrics
from dmd_jax.noise import add_noise_jax

TINY = C.CNRConfig(
    sigma_s=(1.0, 2.0), sigma_r=(0.35, None), iterations=(1, 2), guide=(1, 1, 1),
    feature=(0, 0, 1), hidden=(8,), n_stages=2, vertex_iterations=5,
)  # fmt: skip


def _noisy(v, f, level, seed=0):
    return np.asarray(
        add_noise_jax(jax.random.PRNGKey(seed), v, f, "gaussian", level, units="edge"), np.float64
    )


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _untrained(cfg):
    """Freshly initialised weights: zero output layer, so each stage is one filter step."""
    d = jnp.zeros((1, cfg.descriptor_dim))
    b = jnp.zeros((1, 3))
    params = [
        C.CNRRegressor(cfg.hidden).init(jax.random.PRNGKey(i), d, b)["params"]
        for i in range(cfg.n_stages)
    ]
    return C.CNRWeights(params=tuple(params), config=cfg, meta={})


@pytest.fixture(scope="module")
def knight():
    v, f = load_mesh(shared_mesh_path("decimated-knight.off"))
    return v, f, _noisy(v, f, 0.3)


# --------------------------------------------------------------------------------------
# Descriptor
# --------------------------------------------------------------------------------------


def _reference_filtered(v, f, sigma_s, sigma_r, iterations):
    """Bilateral normal filtering written face by face with Python loops."""
    p = v[f]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    c = p.mean(axis=1)
    ring = [[j for j in range(len(f)) if set(f[i]) & set(f[j])] for i in range(len(f))]
    dists = []
    for i in range(len(f)):
        for j in range(i + 1, len(f)):
            if len(set(f[i]) & set(f[j])) == 2:
                dists.append(np.linalg.norm(c[i] - c[j]))
    d_bar = np.mean(dists)
    out = {}
    for it in range(1, max(iterations) + 1):
        new = np.empty_like(n)
        for i in range(len(f)):
            acc = np.zeros(3)
            for j in ring[i]:
                w = area[j] * np.exp(-np.sum((c[i] - c[j]) ** 2) / (2 * (sigma_s * d_bar) ** 2))
                if sigma_r is not None:
                    w *= np.exp(-np.sum((n[i] - n[j]) ** 2) / (2 * sigma_r**2))
                acc += w * n[j]
            new[i] = acc / np.linalg.norm(acc)
        n = new
        if it in iterations:
            out[it] = n.copy()
    return out


def test_descriptor_matches_loop_reference():
    v, f = icosphere(1)
    v = _noisy(v, f, 0.2) * np.array([1.0, 0.8, 0.6])
    desc, frames = C.fnd(v, f, config=TINY)
    assert desc.shape == (f.shape[0], TINY.descriptor_dim)
    local = desc.reshape(f.shape[0], -1, 3)
    world = np.einsum("fji,fkj->fki", frames, local)  # frames are orthonormal: Rᵀ
    p = v[f]
    raw = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    np.testing.assert_allclose(world[:, 0], raw / np.linalg.norm(raw, axis=1, keepdims=True))
    for i_s, s in enumerate(TINY.sigma_s):
        for i_r, r in enumerate(TINY.sigma_r):
            ref = _reference_filtered(v, f, s, r, TINY.iterations)
            for i_it, it in enumerate(TINY.iterations):
                k = TINY.normal_index((i_s, i_r, i_it))
                np.testing.assert_allclose(world[:, k], ref[it], atol=1e-12)


def test_frames_are_right_handed_and_built_from_guide_and_feature_normals(knight):
    _, f, noisy = knight
    cfg = C.CNRConfig()
    desc, frames = C.fnd(noisy, f, config=cfg)
    eye = np.einsum("fij,fkj->fik", frames, frames)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    local = desc.reshape(f.shape[0], -1, 3)
    # The guide normal is the local z axis; the feature normal leans to +x.
    np.testing.assert_allclose(
        local[:, cfg.normal_index(cfg.guide)], [[0, 0, 1]] * len(f), atol=1e-12
    )
    assert np.all(local[:, cfg.normal_index(cfg.feature), 0] >= -1e-12)


def test_descriptor_is_invariant_to_rotation_scale_and_translation(knight):
    _, f, noisy = knight
    rot = _rotation(3)
    d1, r1 = C.fnd(noisy, f)
    d2, r2 = C.fnd(7.5 * noisy @ rot.T + np.array([3.0, -40.0, 2.0]), f)
    np.testing.assert_allclose(d2, d1, atol=1e-9)
    np.testing.assert_allclose(r2, np.einsum("fij,kj->fik", r1, rot), atol=1e-9)


# --------------------------------------------------------------------------------------
# Stages, training, weights
# --------------------------------------------------------------------------------------


def test_untrained_stage_moves_vertices_onto_the_feature_normals(knight):
    """Zero-initialised output layer: the regressed normal is the feature normal."""
    _, f, noisy = knight
    w = _untrained(TINY)
    desc, frames = C.fnd(noisy, f, config=TINY)
    k = TINY.normal_index(TINY.feature)
    feature = np.einsum("fji,fj->fi", frames, desc.reshape(len(f), -1, 3)[:, k])
    arr, vp = C.prepare_mesh(f, noisy.shape[0])
    from dmd_jax.mesh import canonical_frame

    x = canonical_frame(noisy).apply(noisy)
    _, normals = CM.stage_jit(
        w.params[0], jnp.asarray(CF.pad_rows(x, vp)), CF.to_jax(arr, jnp.float64), TINY
    )
    np.testing.assert_allclose(np.asarray(normals)[: len(f)], feature, atol=1e-12)
    np.testing.assert_allclose(np.asarray(normals)[len(f) :], 0.0)


def test_training_reduces_the_loss_on_a_tiny_set(knight):
    v, f, _ = knight
    arr, vp = C.prepare_mesh(f, v.shape[0])
    noisy = _noisy(v, f, 0.4, seed=5)
    samples = C.stage_samples(
        jnp.asarray(CF.pad_rows(noisy, vp)), jnp.asarray(CF.pad_rows(v, vp)),
        CF.to_jax(arr, jnp.float64), len(f), TINY, np.arange(len(f)),
    )  # fmt: skip
    assert samples.desc.shape == (len(f), TINY.descriptor_dim)
    params, losses = C.fit_stage(samples, TINY, steps=60, batch_size=256, seed=0)
    assert len(losses) == 60 and np.all(np.isfinite(losses))
    init = _untrained(TINY).params[0]
    before = float(C.stage_loss(init, TINY, samples.desc, samples.base, samples.target))
    after = float(C.stage_loss(params, TINY, samples.desc, samples.base, samples.target))
    assert after < 0.8 * before


def test_train_cnr_fits_every_stage(knight):
    v, f, _ = knight
    w = C.train_cnr([(v, f)], config=TINY, faces_per_mesh=200, steps=20, seed=1)
    assert len(w.params) == TINY.n_stages and w.config == TINY
    for p in w.params:
        CM.check_stage_params(p, TINY, "trained")
    assert all(np.isfinite(s["last_100"]) for s in w.meta["stage_losses"])
    out = C.cnr(_noisy(v, f, 0.3, seed=2), f, weights=w)
    assert out.shape == v.shape and np.all(np.isfinite(out))


def test_weights_round_trip_and_reject_bad_files(tmp_path):
    w = _untrained(TINY)._replace(meta={"note": "test"})
    path = C.save_cnr_weights(tmp_path / "w.msgpack", w)
    back = C.load_cnr_weights(path)
    assert back.config == TINY and back.meta == {"note": "test"}
    for a, b in zip(jax.tree.leaves(w.params), jax.tree.leaves(back.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a, np.float32), b)
    with pytest.raises(FileExistsError):
        C.save_cnr_weights(path, w)
    (tmp_path / "junk.msgpack").write_bytes(b"\x00\x01garbage")
    with pytest.raises(ValueError):
        C.load_cnr_weights(tmp_path / "junk.msgpack")
    wrong = w._replace(config=C.CNRConfig(**{**TINY.to_dict(), "hidden": [9]}))
    C.save_cnr_weights(tmp_path / "wrong.msgpack", wrong)
    with pytest.raises(ValueError, match="do not match"):
        C.load_cnr_weights(tmp_path / "wrong.msgpack")


@pytest.mark.parametrize(
    "bad",
    [
        {"sigma_s": (0.0,)},
        {"sigma_r": (-1.0, None)},
        {"iterations": (3, 1)},
        {"guide": (2, 0, 0)},
        {"hidden": (0,)},
        {"n_stages": 0},
        {"unknown": 1},
    ],
)
def test_config_rejects_bad_settings(bad):
    with pytest.raises(ValueError):
        C.CNRConfig.from_dict({**C.CNRConfig().to_dict(), **bad})


# --------------------------------------------------------------------------------------
# Denoising with the bundled weights
# --------------------------------------------------------------------------------------


def test_the_split_package_keeps_every_public_name_at_the_old_module_path():
    """`cascaded_regression` became a package (config, features, model, train); users
    import from it, the CLI's `train-cnr` and `baselines.LEARNED` as before."""
    for name in C.__all__:
        assert getattr(C, name) is not None, name
    assert C.cnr is baselines.LEARNED["cnr"] is CM.cnr
    assert C.fnd is CF.fnd and C.CNRWeights is CM.CNRWeights
    from dmd_jax.baselines.cascaded_regression import train_main  # dmd-jax train-cnr

    assert callable(train_main)


@pytest.fixture(scope="module")
def bundled():
    if not C.bundled_weights_path().is_file():
        pytest.skip("bundled CNR weights are absent")
    return C.load_bundled_cnr()


def test_bundled_cnr_reduces_the_normal_error(bundled):
    """A fandisk corner (1604 faces) at 0.3 × mean edge noise: 35.8° → 10.7° measured."""
    v, f = load_mesh(shared_mesh_path("fandisk.off"))
    v, f = crop_mesh(v, f, np.array([3.5, 14.3, -1.4]), 1.2)
    noisy = _noisy(v, f, 0.3)
    out = baselines.run_baseline("cnr", noisy, f)
    assert out.shape == v.shape and np.all(np.isfinite(out))
    before = mesh_metrics(noisy, v, f)["normal_deg"]
    after = mesh_metrics(out, v, f)["normal_deg"]
    one_stage = mesh_metrics(C.cnr(noisy, f, stages=1), v, f)["normal_deg"]
    assert after < 0.4 * before
    assert after < one_stage
    # No stage: only the round trip through the canonical frame.
    np.testing.assert_allclose(C.cnr(noisy, f, stages=0), noisy, rtol=0, atol=1e-12)


def test_cnr_is_translation_and_scale_equivariant(knight, bundled):
    _, f, noisy = knight
    scale, shift = 37.5, np.array([4.0, -120.0, 9.0])
    out = C.cnr(noisy, f)
    moved = C.cnr(scale * noisy + shift, f)
    extent = np.ptp(noisy, axis=0).max()
    np.testing.assert_allclose(moved, scale * out + shift, atol=1e-9 * scale * extent)


def test_cnr_is_nearly_rotation_equivariant(knight, bundled):
    """The descriptor is rotation invariant, so only rounding separates the results."""
    v, f, noisy = knight
    rot = _rotation(2)
    out = C.cnr(noisy, f)
    turned = C.cnr(noisy @ rot.T, f)
    np.testing.assert_allclose(turned, out @ rot.T, atol=1e-7 * np.ptp(v, axis=0).max())


def test_same_bucket_reuses_the_compiled_stage(knight):
    v, f, noisy = knight
    w = _untrained(TINY)
    C.cnr(noisy, f, weights=w)
    traces = TRACE_COUNTS["cnr"]
    C.cnr(_noisy(v, f, 0.2, seed=9), f, weights=w)
    assert TRACE_COUNTS["cnr"] == traces


@pytest.mark.parametrize("mesh", ["tetrahedron", "single", "isolated"])
def test_small_and_odd_meshes_give_finite_output(mesh):
    tv, tf = tetrahedron()
    v, f = {
        "tetrahedron": (tv, tf),
        "single": (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0.2]]), np.array([[0, 1, 2]])),
        "isolated": (np.vstack([tv, [[5.0, 5.0, 5.0]]]), tf),
    }[mesh]
    out = C.cnr(v, f, weights=_untrained(TINY))
    assert out.shape == v.shape and out.dtype == np.float64 and np.all(np.isfinite(out))
    if mesh == "isolated":
        np.testing.assert_allclose(out[-1], v[-1])


def test_bad_arguments_raise():
    v, f = tetrahedron()
    with pytest.raises(ValueError, match="stages"):
        C.cnr(v, f, weights=_untrained(TINY), stages=3)
    with pytest.raises(ValueError, match="weights"):
        C.cnr(v, f, weights=42)
    with pytest.raises(ValueError, match="unknown parameter"):
        baselines.run_baseline("cnr", v, f, sigma=1.0)
