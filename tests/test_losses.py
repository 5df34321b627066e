"""The losses of `dmd_jax.losses` against independent NumPy / scipy references.

References are written here with plain loops over faces and vertices (Meyer et al.'s
curvatures, per-face normals with `arccos`) and `scipy.spatial.cKDTree` (chamfer), not
with `dmd_jax.geometry`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, tetrahedron
from jax.test_util import check_grads
from scipy.spatial import cKDTree

from dmd_jax import losses
from dmd_jax.config import LossConfig
from dmd_jax.losses import (
    chamfer_distance,
    chamfer_distance_batched,
    curvature_loss,
    face_normal_angles,
    feature_extractor_loss,
    normal_loss,
    total_loss,
    vertex_loss,
)

# --------------------------------------------------------------------------------------
# Meshes and NumPy references
# --------------------------------------------------------------------------------------


def _sphere_pair(seed=0, subdivisions=2, sigma=0.02):
    """A clean icosphere and a perturbed copy, in a canonical-like frame."""
    v, f = icosphere(subdivisions, radius=0.5)
    rng = np.random.default_rng(seed)
    return v + sigma * rng.normal(size=v.shape), v + sigma * rng.normal(size=v.shape), f


def _grid(n=6, seed=0, sigma=0.02):
    """An open, randomly bumped grid patch: a mesh with a boundary."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.stack([xs.ravel(), ys.ravel(), 0.1 * rng.normal(size=n * n)], axis=1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, b, c], [a, c, d]]
    f = np.array(f, np.int32)
    return v + sigma * rng.normal(size=v.shape), v, f


def np_face_normal(p0, p1, p2):
    c = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(c)
    return c / norm if norm > 0 else None


def np_normal_loss(pred, target, faces):
    angles = []
    for face in faces:
        nt = np_face_normal(*target[face])
        if nt is None:
            continue
        n_p = np_face_normal(*pred[face])
        angles.append(math.pi / 2 if n_p is None else math.acos(np.clip(n_p @ nt, -1, 1)))
    return float(np.mean(angles))


def np_curvatures(v, faces):
    """Meyer et al. 2003, one face at a time: `(κ_H [n], κ_G [n])`."""
    n = len(v)
    lap = np.zeros((n, 3))
    area = np.zeros(n)
    angle_sum = np.zeros(n)
    for face in faces:
        p = v[face]
        angle, cot = np.zeros(3), np.zeros(3)
        for c in range(3):
            e1, e2 = p[(c + 1) % 3] - p[c], p[(c + 2) % 3] - p[c]
            cos = e1 @ e2 / (np.linalg.norm(e1) * np.linalg.norm(e2))
            angle[c] = math.acos(np.clip(cos, -1, 1))
            cot[c] = 1 / math.tan(angle[c])
        face_area = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        for c in range(3):
            i, j, k = face[c], face[(c + 1) % 3], face[(c + 2) % 3]
            # cot at corner c weights the opposite edge (j, k).
            lap[j] += cot[c] * (v[j] - v[k])
            lap[k] += cot[c] * (v[k] - v[j])
            angle_sum[i] += angle[c]
            if angle.max() <= math.pi / 2:
                # Voronoi area of corner c: edges to j and k weighted by the opposite cots.
                area[i] += (
                    np.sum((v[j] - v[i]) ** 2) * cot[(c + 2) % 3]
                    + np.sum((v[k] - v[i]) ** 2) * cot[(c + 1) % 3]
                ) / 8
            else:
                area[i] += face_area / 2 if angle[c] > math.pi / 2 else face_area / 4
    kh = np.linalg.norm(lap, axis=1) / (4 * area)
    kg = (2 * math.pi - angle_sum) / area
    return kh, kg


def np_curvature_loss(curv_pred, curv_target, gamma_h, gamma_g):
    (kh_o, kg_o), (kh_g, kg_g) = curv_pred, curv_target
    loss_h = np.mean(np.abs(kh_o - kh_g) * kh_g**2)
    loss_g = np.mean(np.abs(kg_o - kg_g) * kg_g**2)
    return gamma_h * loss_h + gamma_g * loss_g


def np_chamfer_one_way(a, b):
    d, _ = cKDTree(b).query(a)
    return float(np.mean(d**2))


def np_chamfer(a, b):
    return np_chamfer_one_way(a, b) + np_chamfer_one_way(b, a)


def _pad(pred, target, faces, n_extra_v=5, n_extra_f=4, seed=1):
    """Appends junk vertices and padding faces `(p, p, p)`, as `pad_mesh_graph` does."""
    rng = np.random.default_rng(seed)
    n, nf = len(pred), len(faces)
    p2 = np.concatenate([pred, rng.normal(size=(n_extra_v, 3))])
    t2 = np.concatenate([target, rng.normal(size=(n_extra_v, 3))])
    f2 = np.concatenate([faces, np.full((n_extra_f, 3), n, faces.dtype)])
    vm = np.arange(n + n_extra_v) < n
    fm = np.arange(nf + n_extra_f) < nf
    return p2, t2, f2, vm, fm


# --------------------------------------------------------------------------------------
# Values against the references
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mesh", [_sphere_pair, _grid])
def test_vertex_loss_matches_loop(mesh):
    pred, target, _ = mesh()
    ref = np.mean([np.sum((p - t) ** 2) for p, t in zip(pred, target, strict=True)])
    np.testing.assert_allclose(vertex_loss(pred, target), ref, rtol=1e-12)


@pytest.mark.parametrize("mesh", [_sphere_pair, _grid])
def test_normal_loss_matches_arccos_reference(mesh):
    pred, target, faces = mesh()
    ref = np_normal_loss(pred, target, faces)
    np.testing.assert_allclose(normal_loss(pred, target, faces), ref, rtol=1e-9)
    np.testing.assert_allclose(
        normal_loss(pred, target, faces, degrees=True), math.degrees(ref), rtol=1e-9
    )


def test_normal_loss_known_angles():
    # One triangle in the xy-plane, rotated about x by known angles.
    t = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.array([[0, 1, 2]])
    for angle in [0.0, 1e-6, 0.3, math.pi / 2, 3.0, math.pi]:
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        np.testing.assert_allclose(normal_loss(t @ rot.T, t, f), angle, atol=1e-12)


@pytest.mark.parametrize("mesh", [_sphere_pair, _grid])
def test_curvature_loss_matches_meyer_reference(mesh):
    pred, target, faces = mesh()
    curv_pred, curv_target = np_curvatures(pred, faces), np_curvatures(target, faces)
    for gamma_h, gamma_g in [(1e-6, 1.0), (1.0, 0.0), (0.0, 1.0)]:
        ref = np_curvature_loss(curv_pred, curv_target, gamma_h, gamma_g)
        got = curvature_loss(pred, target, faces, gamma_h=gamma_h, gamma_g=gamma_g)
        np.testing.assert_allclose(got, ref, rtol=1e-8)


def test_curvature_of_sphere_is_analytic():
    # Sanity of the reference itself: κ_H → 1/r and κ_G → 1/r² on a fine sphere.
    v, f = icosphere(4, radius=2.0)
    kh, kg = np_curvatures(v, f)
    np.testing.assert_allclose(np.median(kh), 0.5, rtol=2e-3)
    np.testing.assert_allclose(np.median(kg), 0.25, rtol=2e-3)


@pytest.mark.parametrize("n_a, n_b", [(200, 150), (37, 300), (1, 5)])
def test_chamfer_matches_kdtree(n_a, n_b):
    rng = np.random.default_rng(n_a)
    a, b = rng.uniform(size=(n_a, 3)), rng.uniform(size=(n_b, 3))
    np.testing.assert_allclose(chamfer_distance(a, b, block_size=64), np_chamfer(a, b), rtol=1e-10)


@pytest.mark.parametrize("block_size", [1, 7, 64, 199, 200, 201, 5000])
def test_chamfer_blockwise_equals_dense(block_size):
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(200, 3)), rng.normal(size=(173, 3))
    d = np.sum((a[:, None] - b[None]) ** 2, axis=-1)
    dense = d.min(axis=1).mean() + d.min(axis=0).mean()
    np.testing.assert_allclose(chamfer_distance(a, b, block_size=block_size), dense, rtol=1e-10)


def test_chamfer_is_symmetric_and_zero_on_itself():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(90, 3)), rng.normal(size=(60, 3))
    np.testing.assert_allclose(chamfer_distance(a, b), chamfer_distance(b, a), rtol=1e-12)
    assert float(chamfer_distance(a, a)) == 0.0


def test_chamfer_batched_matches_per_mesh_kdtree():
    rng = np.random.default_rng(5)
    sizes = [40, 75, 12]
    a_parts = [rng.normal(size=(s, 3)) for s in sizes]
    b_parts = [x + 0.5 * rng.normal(size=x.shape) for x in a_parts]
    n_pad = 9
    # The meshes overlap in space: only the graph ids keep their points apart.
    a = np.concatenate(a_parts + [rng.normal(size=(n_pad, 3))])
    b = np.concatenate(b_parts + [rng.normal(size=(n_pad, 3))])
    graph = np.concatenate([np.full(s, g) for g, s in enumerate(sizes)] + [np.full(n_pad, 3)])
    mask = graph < 3
    ref = np.mean([np_chamfer(x, y) for x, y in zip(a_parts, b_parts, strict=True)])
    for block in [8, 33, 1024]:
        got = chamfer_distance_batched(a, b, graph, 4, a_mask=mask, b_mask=mask, block_size=block)
        np.testing.assert_allclose(got, ref, rtol=1e-10)
    # The test is meaningful: matching across meshes would give a smaller value.
    a_all, b_all = a[mask], b[mask]
    crossed = np.mean(
        [
            np_chamfer_one_way(x, b_all) + np_chamfer_one_way(y, a_all)
            for x, y in zip(a_parts, b_parts, strict=True)
        ]
    )
    assert crossed < 0.99 * ref


def test_chamfer_batched_different_sizes_per_side():
    rng = np.random.default_rng(6)
    a0, a1 = rng.normal(size=(30, 3)), rng.normal(size=(20, 3))
    b0, b1 = rng.normal(size=(11, 3)), rng.normal(size=(44, 3))
    got = chamfer_distance_batched(
        np.concatenate([a0, a1]),
        np.concatenate([b0, b1]),
        np.repeat([0, 1], [30, 20]),
        2,
        b_graph=np.repeat([0, 1], [11, 44]),
        block_size=16,
    )
    np.testing.assert_allclose(got, (np_chamfer(a0, b0) + np_chamfer(a1, b1)) / 2, rtol=1e-10)


def test_feature_extractor_loss_matches_formula():
    rng = np.random.default_rng(7)
    p, t = rng.normal(size=(50, 5)), rng.normal(size=(50, 5))
    ref = np.mean(
        [
            np.sum((p[i, :3] - t[i, :3]) ** 2) + (p[i, 3] - t[i, 3]) ** 2 + (p[i, 4] - t[i, 4]) ** 2
            for i in range(50)
        ]
    )
    np.testing.assert_allclose(feature_extractor_loss(p, t), ref, rtol=1e-12)


# --------------------------------------------------------------------------------------
# Padding masks
# --------------------------------------------------------------------------------------


def test_masked_padding_changes_nothing():
    pred, target, faces = _sphere_pair(seed=2)
    p2, t2, f2, vm, fm = _pad(pred, target, faces)
    np.testing.assert_allclose(
        vertex_loss(p2, t2, vertex_mask=vm), vertex_loss(pred, target), rtol=1e-12
    )
    np.testing.assert_allclose(
        normal_loss(p2, t2, f2, face_mask=fm), normal_loss(pred, target, faces), rtol=1e-12
    )
    np.testing.assert_allclose(
        curvature_loss(p2, t2, f2, vertex_mask=vm),
        curvature_loss(pred, target, faces),
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        chamfer_distance(p2, t2, a_mask=vm, b_mask=vm, block_size=100),
        chamfer_distance(pred, target),
        rtol=1e-12,
    )
    rng = np.random.default_rng(0)
    fp, ft = rng.normal(size=(len(p2), 5)), rng.normal(size=(len(p2), 5))
    n = len(pred)
    np.testing.assert_allclose(
        feature_extractor_loss(fp, ft, vertex_mask=vm),
        feature_extractor_loss(fp[:n], ft[:n]),
        rtol=1e-12,
    )
    kwargs = dict(weights=LossConfig.all_ones())
    full, parts = total_loss(p2, t2, f2, fp, ft, vertex_mask=vm, face_mask=fm, **kwargs)
    ref, ref_parts = total_loss(pred, target, faces, fp[:n], ft[:n], **kwargs)
    np.testing.assert_allclose(full, ref, rtol=1e-12)
    assert parts.keys() == ref_parts.keys()


def test_total_loss_batched_chamfer_uses_graph_ids():
    pred, target, faces = _sphere_pair(seed=3)
    n, nf = len(pred), len(faces)
    # Two copies of the same mesh at the same place: per-mesh chamfer equals the single one.
    p2, t2 = np.concatenate([pred, pred]), np.concatenate([target, target])
    f2 = np.concatenate([faces, faces + n])
    graph = np.repeat([0, 1], n)
    weights = LossConfig(vertex=0.0, normal=0.0, curvature=0.0, chamfer=1.0, feature=0.0)
    got, parts = total_loss(p2, t2, f2, weights=weights, vertex_graph=graph, n_graph=2)
    np.testing.assert_allclose(got, chamfer_distance(pred, target), rtol=1e-12)
    assert list(parts) == ["chamfer"]
    assert f2.shape == (2 * nf, 3)


# --------------------------------------------------------------------------------------
# Degenerate faces: finite values and gradients
# --------------------------------------------------------------------------------------


def _degenerate_mesh():
    """Tetrahedron plus a collinear face, a face with coincident corners and (p, p, p)."""
    v, f = tetrahedron()
    extra = np.array(
        [
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [4.0, 0.0, 0.0],  # 4, 5, 6 collinear
            [0.0, 2.0, 2.0],
            [0.0, 2.0, 2.0],  # 7 == 8 in position
            [0.5, 0.5, 3.0],  # 9: padding-like vertex
        ]
    )
    v = np.concatenate([v, extra])
    f = np.concatenate([f, [[4, 5, 6], [1, 7, 8], [9, 9, 9], [2, 4, 7]]]).astype(np.int32)
    return v, f


# All five terms at weight 1: a NaN or inf in any term or gradient shows in the total.
# Jitted once at module level, so the three cases below share one compilation.
_total_value_and_grad = jax.jit(
    jax.value_and_grad(
        lambda p, t, f, feats: total_loss(p, t, f, feats, weights=LossConfig.all_ones()),
        argnums=(0, 1),
        has_aux=True,
    )
)


@pytest.mark.parametrize("degenerate_in", ["pred", "target", "both"])
def test_degenerate_faces_give_finite_values_and_grads(degenerate_in):
    v, f = _degenerate_mesh()
    rng = np.random.default_rng(0)
    smooth = v + 0.1 * rng.normal(size=v.shape)  # no degenerate face
    pred = v if degenerate_in in ("pred", "both") else smooth
    target = v if degenerate_in in ("target", "both") else smooth + 0.05
    feats = rng.normal(size=(len(v), 5))
    (value, parts), grads = _total_value_and_grad(pred, target, f, feats)
    assert len(parts) == 5 and all(np.isfinite(x) for x in parts.values()), parts
    assert np.isfinite(value)
    assert all(np.isfinite(g).all() for g in grads)


def test_degenerate_faces_are_handled_as_documented():
    v, f = _degenerate_mesh()
    rng = np.random.default_rng(1)
    smooth = v + 0.1 * rng.normal(size=v.shape)
    angles, target_ok = face_normal_angles(v, smooth, f)
    # Degenerate in pred (collinear, coincident, single point): π/2.
    np.testing.assert_allclose(np.asarray(angles)[4:7], math.pi / 2)
    # (9, 9, 9) is a point whatever the positions.
    assert np.asarray(target_ok).tolist() == [True] * 6 + [False, True]
    _, target_ok = face_normal_angles(smooth, v, f)
    assert np.asarray(target_ok).tolist() == [True] * 4 + [False] * 3 + [True]
    # Zero-area target faces are left out of the mean.
    ref = np_normal_loss(smooth, v, f)
    np.testing.assert_allclose(normal_loss(smooth, v, f), ref, rtol=1e-9)


def test_curvature_unaffected_by_faces_with_coincident_corners():
    # A face whose corners coincide adds nothing to the curvatures of dmd_jax.geometry;
    # the loss routes it away for a finite gradient and must keep the value.
    pred, target, faces = _sphere_pair(seed=4)
    n = len(pred)
    p2 = np.concatenate([pred, pred[:1]])
    t2 = np.concatenate([target, target[:1]])
    f2 = np.concatenate([faces, [[0, n, 1], [n, n, n]]]).astype(np.int32)
    mask = np.arange(n + 1) < n
    curvature = jax.jit(curvature_loss)
    np.testing.assert_allclose(
        curvature(p2, t2, f2, vertex_mask=mask), curvature(pred, target, faces), rtol=1e-12
    )


# --------------------------------------------------------------------------------------
# Gradients, jit, weights
# --------------------------------------------------------------------------------------


def test_check_grads_float64():
    pred, target, faces = _sphere_pair(seed=5, subdivisions=1)
    pred, target = jnp.asarray(pred), jnp.asarray(target)
    assert pred.dtype == jnp.float64
    kw = dict(order=1, modes=("rev",), eps=1e-6)
    # jit: the finite differences call each function many times.
    check_grads(jax.jit(vertex_loss), (pred, target), **kw)
    check_grads(jax.jit(lambda p, t: normal_loss(p, t, faces)), (pred, target), **kw)
    curvature = jax.jit(lambda p, t: curvature_loss(p, t, faces, gamma_h=1e-2))
    check_grads(curvature, (pred, target), **kw)
    chamfer = jax.jit(lambda p: chamfer_distance(p, target, block_size=16))
    check_grads(chamfer, (pred,), **kw)


def test_chamfer_gradient_matches_dense_min():
    rng = np.random.default_rng(8)
    a, b = jnp.asarray(rng.normal(size=(40, 3))), jnp.asarray(rng.normal(size=(30, 3)))

    def dense(a, b):
        d = jnp.sum((a[:, None] - b[None]) ** 2, axis=-1)
        return d.min(axis=1).mean() + d.min(axis=0).mean()

    got = jax.grad(lambda a, b: chamfer_distance(a, b, block_size=7), argnums=(0, 1))(a, b)
    ref = jax.grad(dense, argnums=(0, 1))(a, b)
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-10, atol=1e-14)


def test_total_loss_jits_and_is_the_weighted_sum():
    pred, target, faces = _sphere_pair(seed=6)
    rng = np.random.default_rng(0)
    fp = rng.normal(size=(len(pred), 5))
    ft = rng.normal(size=(len(pred), 5))
    weights = LossConfig()
    fn = jax.jit(lambda p, t, f, a, b: total_loss(p, t, f, a, b, weights=weights))
    total, parts = fn(pred, target, faces, fp, ft)
    expected = {
        "vertex": vertex_loss(pred, target),
        "normal": normal_loss(pred, target, faces),
        "curvature": curvature_loss(pred, target, faces),
        "chamfer": chamfer_distance(pred, target),
        "feature": feature_extractor_loss(fp, ft),
    }
    assert parts.keys() == expected.keys()
    for k in expected:
        np.testing.assert_allclose(parts[k], expected[k], rtol=1e-10)
    ref = sum(getattr(weights, k) * float(v) for k, v in expected.items())
    np.testing.assert_allclose(total, ref, rtol=1e-10)


def test_total_loss_target_features_default_to_geometry():
    from dmd_jax.geometry import vertex_features

    pred, target, faces = _sphere_pair(seed=7)
    fp = np.random.default_rng(0).normal(size=(len(pred), 5))
    w = LossConfig(vertex=0.0, normal=0.0, curvature=0.0, chamfer=0.0, feature=1.0)
    total, _ = total_loss(pred, target, faces, fp, weights=w)
    np.testing.assert_allclose(
        total, feature_extractor_loss(fp, vertex_features(target, faces)), rtol=1e-12
    )


def test_zero_weight_terms_are_not_computed(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("a zero-weight term was computed")

    for name in ["vertex", "normal", "curvature", "chamfer", "feature", "predicted_normal"]:
        monkeypatch.setattr(losses, f"{name}_term", boom)
    pred, target, faces = _sphere_pair()
    w = LossConfig(vertex=0.0, normal=0.0, curvature=0.0, chamfer=0.0, feature=0.0)
    total, parts = total_loss(pred, target, faces, weights=w)
    assert parts == {} and float(total) == 0.0


def test_loss_weights():
    def weights(c):
        return tuple(getattr(c, name) for name in ("vertex", "normal", "curvature", "chamfer"))

    assert weights(LossConfig()) + (LossConfig().feature,) == (1.0, 0.2, 0.01, 0.05, 1.0)
    assert weights(LossConfig.all_ones()) == (1.0,) * 4 and LossConfig.all_ones().feature == 1


def test_terms_of_groups_add_up_to_the_whole_batch():
    """Data-parallel training adds the groups' sums and counts, then divides once."""
    a, b = _sphere_pair(seed=1), _sphere_pair(seed=2)
    n = len(a[0])
    pred, target = np.concatenate([a[0], b[0]]), np.concatenate([a[1], b[1]])
    faces = np.concatenate([a[2], b[2] + n])
    graph = np.repeat(np.arange(2, dtype=np.int32), n)
    weights = LossConfig.all_ones().with_edits({"feature": 0.0})
    whole = losses.loss_terms(pred, target, faces, weights=weights, vertex_graph=graph, n_graph=2)
    parts = [
        losses.loss_terms(p, t, f, weights=weights, vertex_graph=np.zeros(n, np.int32), n_graph=1)
        for p, t, f in (a, b)
    ]
    assert whole.keys() == parts[0].keys() == {"vertex", "normal", "curvature", "chamfer"}
    for k in whole:
        got = parts[0][k].total + parts[1][k].total
        np.testing.assert_allclose(got, whole[k].total, rtol=1e-10)
        assert int(parts[0][k].count) + int(parts[1][k].count) == int(whole[k].count)
    total, means = losses.reduce_terms(whole, weights)
    np.testing.assert_allclose(total, sum(means.values()), rtol=1e-12)
    np.testing.assert_allclose(means["vertex"], vertex_loss(pred, target), rtol=1e-12)


# --------------------------------------------------------------------------------------
# Bad inputs
# --------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_error():
    pred, target, faces = _sphere_pair()
    with pytest.raises(ValueError, match="same shape"):
        vertex_loss(pred, target[:-1])
    with pytest.raises(ValueError, match=r"\[n, 3\]"):
        vertex_loss(pred[:, :2], target[:, :2])
    with pytest.raises(ValueError, match="vertex_mask"):
        vertex_loss(pred, target, vertex_mask=np.ones(3, bool))
    with pytest.raises(ValueError, match="faces"):
        normal_loss(pred, target, faces[:, :2])
    with pytest.raises(ValueError, match="integer"):
        normal_loss(pred, target, faces.astype(np.float64))
    with pytest.raises(ValueError, match="face_mask"):
        normal_loss(pred, target, faces, face_mask=np.ones(2, bool))
    with pytest.raises(ValueError, match=r"\[n, 5\]"):
        feature_extractor_loss(pred, target)
    with pytest.raises(ValueError, match="block_size"):
        chamfer_distance(pred, target, block_size=0)
    with pytest.raises(ValueError, match="a_graph"):
        chamfer_distance_batched(pred, target, np.zeros(3, np.int32), 1)
    with pytest.raises(ValueError, match="pred_features"):
        total_loss(pred, target, faces)
    with pytest.raises(ValueError, match="together"):
        total_loss(pred, target, faces, weights=LossConfig(feature=0.0), n_graph=2)
    with pytest.raises(ValueError, match=">= 0"):
        total_loss(pred, target, faces, weights=LossConfig(vertex=-1.0, feature=0.0))
    with pytest.raises(ValueError, match="loss weight vertex"):
        jax.jit(lambda w: total_loss(pred, target, faces, weights=LossConfig(vertex=w)))(1.0)


# --------------------------------------------------------------------------------------
# Feature-balanced weights (LossConfig.crease_weight)
# --------------------------------------------------------------------------------------


def _folded_grid(n=7, seed=0):
    """A grid folded 60° along a line (a crease between two flats), lightly bumped."""
    rng = np.random.default_rng(seed)
    _, v, f = _grid(n, seed=seed, sigma=0.0)
    v[:, 2] = 0.0
    x = v[:, 0] - 0.5
    fold = x > 0
    v[fold, 0] = 0.5 + x[fold] * math.cos(math.radians(60))
    v[fold, 2] = x[fold] * math.sin(math.radians(60))
    return v + 1e-3 * rng.normal(size=v.shape), f


@pytest.mark.parametrize("mesh", ["folded", "sphere", "tetrahedron"])
def test_crease_face_mask_matches_the_comparison_reference(mesh):
    from dmd_jax.comparison import crease_faces
    from dmd_jax.graph import build_mesh_graph

    if mesh == "folded":
        v, f = _folded_grid()
    elif mesh == "sphere":
        v, f = icosphere(1)
    else:
        v, f = tetrahedron()
    g = build_mesh_graph(f, v.shape[0])
    got = losses.crease_face_mask(v, f, g.face_senders, g.face_receivers)
    want = crease_faces(v, f)
    np.testing.assert_array_equal(np.asarray(got), want)
    # The fold has creases, the fine sphere none, every tetrahedron face is on one.
    assert {"folded": 0 < want.sum() < len(f), "sphere": not want.any()}.get(mesh, want.all())


def test_face_weight_is_a_weighted_mean_of_the_normal_terms():
    from dmd_jax.graph import build_mesh_graph

    target, f = _folded_grid()
    pred = target + 0.01 * np.random.default_rng(3).normal(size=target.shape)
    angles = np.asarray(face_normal_angles(pred, target, f)[0])
    w = np.random.default_rng(4).uniform(0.5, 4.0, len(f))
    term = losses.normal_term(pred, target, f, face_weight=w)
    assert int(term.count) == len(f)
    np.testing.assert_allclose(term.mean(), np.sum(w * angles) / np.sum(w), rtol=1e-6)
    # Weights of 1 are the plain mean; padding faces carry no weight.
    np.testing.assert_allclose(
        losses.normal_term(pred, target, f, face_weight=np.ones(len(f))).mean(),
        normal_loss(pred, target, f),
        rtol=1e-6,
    )
    p2, t2, f2, _, fm = _pad(pred, target, f)
    w2 = np.concatenate([w, np.full(len(f2) - len(f), 100.0)])
    padded = losses.normal_term(p2, t2, f2, face_mask=fm, face_weight=w2)
    np.testing.assert_allclose(padded.mean(), term.mean(), rtol=1e-6)
    # The face-normal term of a normal-first head takes the same weights.
    g = build_mesh_graph(f, len(target))
    crease = np.asarray(losses.crease_face_mask(target, f, g.face_senders, g.face_receivers))
    n_pred = np.asarray(losses.geometry.face_normals(pred, f))
    cw = np.where(crease, 5.0, 1.0)
    pn = losses.predicted_normal_term(n_pred, target, f, face_weight=cw)
    np.testing.assert_allclose(pn.mean(), np.sum(cw * angles) / np.sum(cw), rtol=1e-5)
    with pytest.raises(ValueError, match="face_weight must have shape"):
        losses.normal_term(pred, target, f, face_weight=w[:-1])


def test_crease_weight_config_is_checked():
    assert LossConfig().crease_weight == 1.0
    assert LossConfig(crease_weight=4).crease_weight == 4
    for bad in (0.0, -1.0, float("nan"), float("inf"), "4"):
        with pytest.raises(ValueError, match="crease_weight"):
            LossConfig(crease_weight=bad)
