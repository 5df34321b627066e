"""`dmd_jax.metrics` against NumPy / scipy computations in the ground truth's frame."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from conftest import icosphere, shared_mesh_path
from scipy.spatial import cKDTree

from dmd_jax.io import load_mesh
from dmd_jax.metrics import face_normal_errors_deg, mesh_metrics
from dmd_jax.noise import add_noise_jax


def np_metrics(pred, gt, faces):
    """Independent reference: frame from the GT bounding box, loops-free NumPy + cKDTree."""
    lo, hi = gt.min(axis=0), gt.max(axis=0)
    centre, scale = (lo + hi) / 2, (hi - lo).max()
    p, g = (pred - centre) / scale, (gt - centre) / scale
    vertex = np.mean(np.sum((p - g) ** 2, axis=1))

    def normals(v):
        c = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        return c / np.linalg.norm(c, axis=1, keepdims=True)

    per_face = np.degrees(np.arccos(np.clip(np.sum(normals(p) * normals(g), axis=1), -1, 1)))
    d_pg, _ = cKDTree(g).query(p)
    d_gp, _ = cKDTree(p).query(g)
    chamfer = np.mean(d_pg**2) + np.mean(d_gp**2)
    return {"vertex": vertex, "normal_deg": per_face.mean(), "chamfer": chamfer}, per_face


@pytest.fixture(scope="module")
def bunny_pair():
    v, f = load_mesh(shared_mesh_path("bunny.off"))
    noisy = np.asarray(add_noise_jax(jax.random.PRNGKey(0), v, f, "gaussian", 0.3, units="edge"))
    return noisy, v, f


def test_zero_on_identical_meshes():
    v, f = icosphere(2)
    m = mesh_metrics(v, v, f)
    assert m == {"vertex": 0.0, "vertex_per_coord": 0.0, "normal_deg": 0.0, "chamfer": 0.0}
    assert np.all(face_normal_errors_deg(v, v, f) == 0.0)


def test_matches_numpy_and_scipy(bunny_pair):
    noisy, gt, f = bunny_pair
    ref, ref_faces = np_metrics(noisy, gt, f)
    m = mesh_metrics(noisy, gt, f)
    for k, value in ref.items():
        np.testing.assert_allclose(m[k], value, rtol=1e-9, err_msg=k)
    np.testing.assert_allclose(m["vertex_per_coord"], ref["vertex"] / 3, rtol=1e-12)
    np.testing.assert_allclose(face_normal_errors_deg(noisy, gt, f), ref_faces, atol=1e-7)
    # The noise is real: tens of degrees at 0.3 × the mean edge length.
    assert 5.0 < m["normal_deg"] < 60.0


def test_per_face_errors_average_to_the_normal_metric(bunny_pair):
    noisy, gt, f = bunny_pair
    per_face = face_normal_errors_deg(noisy, gt, f)
    assert per_face.shape == (len(f),) and per_face.dtype == np.float64
    assert np.all((per_face >= 0) & (per_face <= 180))
    np.testing.assert_allclose(per_face.mean(), mesh_metrics(noisy, gt, f)["normal_deg"])


def test_symmetric_where_it_should_be():
    gt, f = icosphere(2, radius=0.5)
    rng = np.random.default_rng(0)
    pred = gt + 0.01 * rng.normal(size=gt.shape)
    # Same bounding box for both, so both orders use the same frame.
    lo, hi = pred.min(axis=0), pred.max(axis=0)
    pred = (pred - lo) / (hi - lo) * (gt.max(axis=0) - gt.min(axis=0)) + gt.min(axis=0)
    a, b = mesh_metrics(pred, gt, f), mesh_metrics(gt, pred, f)
    for k in ["vertex", "normal_deg", "chamfer"]:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-12, err_msg=k)
    np.testing.assert_allclose(
        face_normal_errors_deg(pred, gt, f), face_normal_errors_deg(gt, pred, f), atol=1e-12
    )


def test_invariant_to_translating_and_scaling_both(bunny_pair):
    noisy, gt, f = bunny_pair
    ref = mesh_metrics(noisy, gt, f)
    for scale, shift in [(1e-3, [5.0, 0, -2]), (250.0, [-1e3, 40, 7])]:
        m = mesh_metrics(noisy * scale + shift, gt * scale + shift, f)
        for k in ref:
            np.testing.assert_allclose(m[k], ref[k], rtol=1e-8, err_msg=k)


def test_zero_area_ground_truth_faces():
    gt = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [0, 0, 1]])
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 4, 1]])  # face 1 is collinear in the GT
    pred = gt + np.array([[0, 0, 0.1], [0, 0, 0], [0, 0, 0], [0, 0.2, 0], [0, 0, 0]])
    errors = face_normal_errors_deg(pred, gt, f)
    assert errors[1] == 0.0
    assert math.isnan(face_normal_errors_deg(pred, gt, f, undefined=math.nan)[1])
    m = mesh_metrics(pred, gt, f)
    np.testing.assert_allclose(m["normal_deg"], errors[[0, 2]].mean())


def test_bad_inputs():
    v, f = icosphere(1)
    with pytest.raises(ValueError, match="correspond"):
        mesh_metrics(v[:-1], v, f)
    with pytest.raises(ValueError, match="faces"):
        mesh_metrics(v, v, f.astype(float))
    with pytest.raises(ValueError, match="lie in"):
        mesh_metrics(v, v, f + len(v))
    with pytest.raises(ValueError, match="zero extent"):
        mesh_metrics(np.zeros((3, 3)), np.zeros((3, 3)), np.array([[0, 1, 2]]))


def dense_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """The chamfer distance by an all-pairs search, as the former JAX computation did."""
    d = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)  # [n_a, n_b]
    return float(d.min(axis=1).mean() + d.min(axis=0).mean())


def test_the_losses_definitions_to_float64(key):
    """`mesh_metrics` (NumPy, k-d tree) equals the training losses it stands for
    (`dmd_jax.losses`, float64 under this suite) and an all-pairs chamfer search, in the
    ground truth's frame; `min_rows` and `chamfer_block` are accepted and change nothing."""
    from dmd_jax import losses
    from dmd_jax.mesh import canonical_frame

    v, f = icosphere(2)
    for seed, sigma in enumerate([1e-3, 0.01, 0.1]):
        noisy = v + sigma * np.random.default_rng(seed).standard_normal(v.shape)
        frame = canonical_frame(v)
        pred, gt = frame.apply(noisy), frame.apply(v)
        ref = {
            "vertex": float(losses.vertex_loss(pred, gt)),
            "normal_deg": float(losses.normal_loss(pred, gt, f, degrees=True)),
            "chamfer": float(losses.chamfer_distance(pred, gt)),
        }
        np.testing.assert_allclose(dense_chamfer(pred, gt), ref["chamfer"], rtol=1e-12)
        for kwargs in ({}, {"min_rows": 3000, "chamfer_block": 64}):
            got = mesh_metrics(noisy, v, f, **kwargs)
            for k, value in ref.items():
                np.testing.assert_allclose(got[k], value, rtol=1e-10, err_msg=k)


def test_chamfer_equals_the_all_pairs_search_on_unlike_point_sets():
    """Vertex sets that do not correspond (a shuffled, shrunk and shifted copy), so the
    nearest neighbours are not the corresponding vertices."""
    v, f = icosphere(1)
    rng = np.random.default_rng(3)
    pred = 0.7 * v[rng.permutation(len(v))] + [0.1, -0.2, 0.05]
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre, scale = (lo + hi) / 2, (hi - lo).max()
    ref = dense_chamfer((pred - centre) / scale, (v - centre) / scale)
    np.testing.assert_allclose(mesh_metrics(pred, v, f)["chamfer"], ref, rtol=1e-12)


def test_a_value_too_small_for_its_decimals_is_not_shown_as_zero():
    from dmd_jax.metrics import CHAMFER, NORMAL, VERTEX, format_metric

    assert format_metric(VERTEX, 0.0) == "0.000"
    assert format_metric(VERTEX, 1.234e-4) == "1.234"
    assert format_metric(VERTEX, 6.2e-12) == "6.2e-08"
    assert format_metric(CHAMFER, 3e-20) == "3.0e-16"
    assert format_metric(NORMAL, 1e-5) == "1.0e-05"
