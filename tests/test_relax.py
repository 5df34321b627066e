"""`dmd_jax.relax.relax_tangential` against a loop-by-loop reference and on known shapes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmd_jax.relax import FEATURE_RATIO, relax_tangential


def _grid(n: int = 7):
    """A flat `n × n` grid in z = 0, quads split along one diagonal."""
    u, w = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([u.ravel(), w.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    return v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def _reference_step(x, faces, step, ratio):
    """One relaxation step written vertex by vertex."""
    out = x.copy()
    for i in range(x.shape[0]):
        incident = [f for f in faces if i in f]
        edges = [tuple(sorted((f[k], f[(k + 1) % 3]))) for f in faces for k in range(3)]
        on_boundary = any(edges.count(e) == 1 for e in edges if i in e)
        if not incident or on_boundary:
            continue
        ring = sorted({int(j) for f in incident for j in f if j != i})
        umbrella = x[ring].mean(axis=0) - x[i]
        tensor = np.zeros((3, 3))
        for f in incident:
            c = np.cross(x[f[1]] - x[f[0]], x[f[2]] - x[f[0]])
            area2 = np.linalg.norm(c)
            if area2 > 0:
                tensor += np.outer(c, c) / area2
        val, vec = np.linalg.eigh(tensor)
        for k in range(3):
            if val[2] > 0 and val[k] >= ratio * val[2]:
                umbrella -= vec[:, k] * (vec[:, k] @ umbrella)
        out[i] = x[i] + step * umbrella
    return out


def test_matches_vertex_by_vertex_reference():
    rng = np.random.default_rng(0)
    v, f = _grid(5)
    v = v + rng.normal(0, 0.15, v.shape)
    for ratio in (FEATURE_RATIO, 1.0):
        got = relax_tangential(v, f, 1, step=0.5, feature_ratio=ratio)
        np.testing.assert_allclose(got, _reference_step(v, f, 0.5, ratio), atol=1e-12)


def test_flat_plane_stays_in_its_plane_and_evens_out():
    rng = np.random.default_rng(1)
    v, f = _grid(9)
    jitter = rng.uniform(-0.3, 0.3, v.shape)
    jitter[:, 2] = 0.0
    noisy = v + jitter
    out = relax_tangential(noisy, f, 5)
    np.testing.assert_array_equal(out[:, 2], 0.0)
    interior = (v[:, 0] > 0) & (v[:, 0] < 8) & (v[:, 1] > 0) & (v[:, 1] < 8)
    before = np.linalg.norm(noisy - v, axis=1)[interior].mean()
    after = np.linalg.norm(out - v, axis=1)[interior].mean()
    assert after < 0.6 * before, (before, after)
    boundary = ~interior
    np.testing.assert_array_equal(out[boundary], noisy[boundary])


def test_crease_vertices_move_only_along_the_crease():
    # Two half-planes meeting at 90° along the x axis (z = 0 for y <= 0, y = 0 above).
    v, f = _grid(9)
    y = v[:, 1] - 4.0
    folded = np.stack([v[:, 0], np.minimum(y, 0.0), np.maximum(y, 0.0)], 1)
    on_crease = y == 0
    rng = np.random.default_rng(2)
    moved = folded.copy()
    moved[on_crease, 0] += rng.uniform(-0.3, 0.3, on_crease.sum())  # along the crease only
    out = relax_tangential(moved, f, 4)
    np.testing.assert_allclose(out[on_crease, 1:], 0.0, atol=1e-12)
    # Uniform tangential smoothing (every eigen-direction but the largest free) would round
    # the crease off.
    rounded = relax_tangential(moved, f, 4, feature_ratio=1.0)
    assert np.abs(rounded[on_crease, 1:]).max() > 0.05


def test_identity_cases_and_input_untouched():
    v, f = _grid(4)
    v_isolated = np.vstack([v, [[5.0, 5.0, 5.0]]])
    before = v_isolated.copy()
    out = relax_tangential(v_isolated, f, 3)
    np.testing.assert_array_equal(v_isolated, before)
    np.testing.assert_array_equal(out[-1], [5.0, 5.0, 5.0])  # no faces: not moved
    np.testing.assert_array_equal(relax_tangential(v, f, 0), v)
    assert relax_tangential(v.astype(np.float32), f, 1).dtype == np.float64


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"iterations": -1}, "iterations"),
        ({"iterations": 1.5}, "iterations"),
        ({"step": 0.0}, "step"),
        ({"feature_ratio": 2.0}, "feature_ratio"),
    ],
)
def test_bad_arguments(kwargs, match):
    v, f = _grid(3)
    with pytest.raises(ValueError, match=match):
        relax_tangential(v, f, **kwargs)


def test_bad_meshes():
    v, f = _grid(3)
    with pytest.raises(ValueError, match="vertices"):
        relax_tangential(v[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        relax_tangential(v, f.astype(float))
    with pytest.raises(ValueError, match="outside"):
        relax_tangential(v, f + 100)


def test_denoise_relax_is_the_network_then_relaxation():
    import dmd_jax

    with np.load(Path(__file__).resolve().parent / "data" / "bundled_reference.npz") as data:
        v, f = data["vertices"], data["faces"]
    bundle = dmd_jax.load_pretrained()
    plain = dmd_jax.denoise(v, f, bundle)
    relaxed = dmd_jax.denoise(v, f, bundle, relax=2)
    assert relaxed.dtype == plain.dtype
    np.testing.assert_allclose(relaxed, relax_tangential(plain, f, 2), atol=1e-6)
    assert np.abs(relaxed - plain).max() > 1e-4  # it did something
    via_api = dmd_jax.denoise_with("dmd", v, f, relax=2)
    np.testing.assert_allclose(via_api, relaxed, atol=1e-6)
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="relax"):
            dmd_jax.denoise(v, f, bundle, relax=bad)


def test_cli_relax_only_for_the_network(tmp_path, capsys):
    from dmd_jax import cli
    from dmd_jax.io import save_mesh

    v, f = _grid(4)
    src = save_mesh(tmp_path / "in.obj", v + 0.01, f)
    args = ["denoise", str(src), "-o", str(tmp_path / "o.obj"), "--method", "bnf"]
    assert cli.main([*args, "--relax", "2"]) == 2
    assert "--relax is for --method dmd" in capsys.readouterr().err
    assert not (tmp_path / "o.obj").exists()
