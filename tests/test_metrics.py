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


def test_mesh_metrics_padding_changes_nothing():
    """`mesh_metrics` pads to a size bucket (one program per bucket); the numbers are the
    unpadded losses, with or without extra rows (`min_rows`)."""
    from dmd_jax import losses
    from dmd_jax.metrics import _in_gt_frame

    v, f = icosphere(2)
    noisy = v + 0.01 * np.random.default_rng(0).standard_normal(v.shape)
    pred, gt, ff = _in_gt_frame(noisy, v, f)
    ref = {
        "vertex": float(losses.vertex_loss(pred, gt)),
        "normal_deg": float(losses.normal_loss(pred, gt, ff, degrees=True)),
        "chamfer": float(losses.chamfer_distance(pred, gt)),
    }
    for min_rows in (0, 3000):
        got = mesh_metrics(noisy, v, f, min_rows=min_rows)
        for key, value in ref.items():
            np.testing.assert_allclose(got[key], value, rtol=1e-5, err_msg=key)
