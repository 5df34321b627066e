"""`dmd_jax.geometry` against analytic values, Gauss–Bonnet, trimesh, pymeshlab and a
face-by-face NumPy transcription of Meyer et al. (2003)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from conftest import icosphere, shared_mesh_path, tetrahedron
from jax.test_util import check_grads

from dmd_jax import geometry as G
from dmd_jax.io import load_mesh

ALL_FUNCTIONS = (
    "face_cross",
    "face_normals",
    "face_areas",
    "vertex_normals",
    "interior_angles",
    "cotangents",
    "cotangent_laplacian",
    "mixed_voronoi_area",
    "mean_curvature_normal",
    "mean_curvature",
    "signed_mean_curvature",
    "angle_defect",
    "gaussian_curvature",
    "vertex_features",
)


# These programs are tiny and run once: XLA's backend optimisations would only double
# the compile time that dominates this file.
fast_jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


@functools.cache
def _jitted(names):
    return fast_jit(lambda v, f: {name: getattr(G, name)(v, f) for name in names})


def geo(names, v, f):
    """`{name: geometry.<name>(v, f)}` as NumPy, all in one jitted program (one compile
    per mesh shape keeps the file fast); a single name gives its array."""
    single = isinstance(names, str)
    out = _jitted((names,) if single else tuple(names))(jnp.asarray(v), jnp.asarray(f))
    out = {k: np.asarray(x) for k, x in out.items()}
    return out[names] if single else out


# --------------------------------------------------------------------------------------
# A face-by-face NumPy reference of Meyer et al. (2003)
# --------------------------------------------------------------------------------------


def _angle(a, b):
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return np.arccos(np.clip(c, -1.0, 1.0))


def meyer_reference(v, f):
    """`(angles [f, 3], A_mixed [n], Laplacian Σ w (p_v − p_u) [n, 3])`, one face at a time.

    Written from the paper's pseudo-code (Fig. 4 of Meyer et al.): Voronoi area
    `(|PR|² cot Q + |PQ|² cot R) / 8` at P on a non-obtuse triangle; otherwise half the
    area at the obtuse corner and a quarter at the others. Angles by arccos.
    """
    n = len(v)
    angles = np.zeros((len(f), 3))
    area = np.zeros(n)
    lap = np.zeros((n, 3))
    for t, face in enumerate(f):
        p = v[face]
        ang = [_angle(p[(i + 1) % 3] - p[i], p[(i + 2) % 3] - p[i]) for i in range(3)]
        angles[t] = ang
        tri_area = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            # Edge (j, k) lies opposite corner i.
            w = 1.0 / np.tan(ang[i])
            lap[face[j]] += w * (p[j] - p[k])
            lap[face[k]] += w * (p[k] - p[j])
            if max(ang) <= np.pi / 2:
                area[face[i]] += (
                    np.sum((p[k] - p[i]) ** 2) / np.tan(ang[j])
                    + np.sum((p[j] - p[i]) ** 2) / np.tan(ang[k])
                ) / 8.0
            elif ang[i] > np.pi / 2:
                area[face[i]] += tri_area / 2.0
            else:
                area[face[i]] += tri_area / 4.0
    return angles, area, lap


@pytest.fixture(scope="module")
def knight():
    v, f = load_mesh(shared_mesh_path("decimated-knight.off"))
    return v, f, geo(ALL_FUNCTIONS, v, f)


@pytest.fixture(scope="module")
def fandisk():
    v, f = load_mesh(shared_mesh_path("fandisk.off"))
    return v, f, geo(ALL_FUNCTIONS, v, f)


def perturbed_icosphere(subdivisions=1, scale=0.05, seed=0):
    v, f = icosphere(subdivisions)
    return v + scale * np.random.default_rng(seed).normal(size=v.shape), f


def test_meyer_reference_per_vertex(knight):
    v, f, g = knight
    angles, area, lap = meyer_reference(v, f)
    # The knight has obtuse triangles, so both branches of A_mixed are exercised.
    assert (angles > np.pi / 2).any(axis=1).mean() > 0.1
    np.testing.assert_allclose(g["interior_angles"], angles, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g["mixed_voronoi_area"], area, rtol=1e-9)
    np.testing.assert_allclose(g["cotangent_laplacian"], lap, rtol=1e-8, atol=1e-12)
    mean = np.linalg.norm(lap, axis=1) / (4 * area)
    np.testing.assert_allclose(g["mean_curvature"], mean, rtol=1e-8)
    np.testing.assert_allclose(
        g["mean_curvature_normal"], lap / (2 * area[:, None]), rtol=1e-8, atol=1e-12
    )
    defect = 2 * np.pi - np.bincount(f.ravel(), angles.ravel(), minlength=len(v))
    np.testing.assert_allclose(g["angle_defect"], defect, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g["gaussian_curvature"], defect / area, rtol=1e-8)
    feats = g["vertex_features"]
    assert feats.shape == (len(v), 5)
    np.testing.assert_allclose(feats[:, 3], mean, rtol=1e-8)
    np.testing.assert_allclose(feats[:, 4], defect / area, rtol=1e-8)
    np.testing.assert_allclose(feats[:, :3], g["vertex_normals"])


def test_cotangent_laplacian_of_other_values_is_the_cotan_matrix():
    v, f = perturbed_icosphere()
    g = geo(("cotangents", "interior_angles", "cotangent_laplacian"), v, f)
    cot = g["cotangents"]
    # Assemble L = Σ_f cot α (e_u - e_w)(e_u - e_w)^T densely, edge by edge.
    lmat = np.zeros((len(v), len(v)))
    for face, c in zip(f, cot, strict=True):
        for i in range(3):
            u, w = face[(i + 1) % 3], face[(i + 2) % 3]
            lmat[u, u] += c[i]
            lmat[w, w] += c[i]
            lmat[u, w] -= c[i]
            lmat[w, u] -= c[i]
    x = np.random.default_rng(3).normal(size=(len(v), 4))
    lap_x = fast_jit(G.cotangent_laplacian)(v, f, x)
    np.testing.assert_allclose(lap_x, lmat @ x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g["cotangent_laplacian"], lmat @ v, atol=1e-12)
    # The cotangent of each corner is cos/sin of its angle.
    np.testing.assert_allclose(cot, 1 / np.tan(g["interior_angles"]), rtol=1e-10)


# --------------------------------------------------------------------------------------
# Analytic surfaces
# --------------------------------------------------------------------------------------


def test_icosphere_curvature_within_two_percent():
    radius = 2.5
    v, f = icosphere(4, radius)
    g = geo(ALL_FUNCTIONS, v, f)
    h = g["mean_curvature"]
    k = g["gaussian_curvature"]
    # Measured: 2e-6 (H) and 1.2e-3 (K) relative; the bound is 2 %.
    assert np.mean(np.abs(h - 1 / radius)) * radius < 0.02
    assert np.mean(np.abs(k - 1 / radius**2)) * radius**2 < 0.02
    signed = g["signed_mean_curvature"]
    np.testing.assert_allclose(signed, h)  # outward normals: H = +1/r
    flipped = f[:, ::-1]
    np.testing.assert_allclose(geo(ALL_FUNCTIONS, v, flipped)["signed_mean_curvature"], -h)
    # The mean-curvature normal is 2 H n and points outward on a sphere.
    kn = g["mean_curvature_normal"]
    normals = g["vertex_normals"]
    np.testing.assert_allclose(np.linalg.norm(kn, axis=1), 2 * h, rtol=1e-12)
    assert np.all(np.sum(kn * normals, axis=1) > 0.999 * 2 * h)
    np.testing.assert_allclose(normals, v / radius, atol=1e-2)


def torus(big_r, small_r, n_u, n_v):
    """Closed torus grid `[n_u · n_v, 3]`, and each vertex's tube angle `v`."""
    u = np.arange(n_u) * 2 * np.pi / n_u
    w = np.arange(n_v) * 2 * np.pi / n_v
    uu, ww = np.meshgrid(u, w, indexing="ij")
    ring = big_r + small_r * np.cos(ww)
    verts = np.stack([ring * np.cos(uu), ring * np.sin(uu), small_r * np.sin(ww)], -1)
    idx = np.arange(n_u * n_v).reshape(n_u, n_v)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(b, -1, 1), np.roll(idx, -1, 1)
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    return verts.reshape(-1, 3), faces.astype(np.int32), ww.ravel()


def test_torus_curvature_matches_analytic():
    big_r, small_r = 3.0, 1.0
    errors = {}
    for n_u, n_v in ((60, 30), (120, 60)):
        v, f, tube = torus(big_r, small_r, n_u, n_v)
        k_exact = np.cos(tube) / (small_r * (big_r + small_r * np.cos(tube)))
        h_exact = (big_r + 2 * small_r * np.cos(tube)) / (
            2 * small_r * (big_r + small_r * np.cos(tube))
        )
        g = geo(("gaussian_curvature", "mean_curvature", "angle_defect"), v, f)
        k, h = g["gaussian_curvature"], g["mean_curvature"]
        errors[n_u] = np.abs(k - k_exact).max()
        # Gauss–Bonnet: a torus has χ = 0.
        assert abs(g["angle_defect"].sum()) < 1e-9
    # On the 120 × 60 grid (|K| ≤ 0.5) we measured max |K − K_exact| = 5.1e-4 and
    # max |H − H_exact| = 1.8e-4; the bounds leave a factor of 2.
    assert errors[120] < 1e-3
    assert np.abs(h - h_exact).max() < 4e-4
    # Second order: halving the spacing divides the error by about 4 (measured 3.98).
    assert errors[60] / errors[120] > 3.5


# --------------------------------------------------------------------------------------
# Gauss–Bonnet on the shared meshes
# --------------------------------------------------------------------------------------

# Genus from the shared README: χ = 2 − 2g.
KNOWN_EULER = {"fertility.off": -6, "3holes.off": -4}
CLOSED = [
    "3holes.off",
    "block.obj",
    "bunny.off",
    "cow.off",
    "decimated-knight.off",
    "fandisk.off",
    "fertility.off",
    "screwdriver.off",
]


@pytest.mark.parametrize("name", CLOSED)
def test_gauss_bonnet_on_closed_meshes(name):
    v, f = load_mesh(shared_mesh_path(name))
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight
    chi = mesh.euler_number
    assert chi == KNOWN_EULER.get(name, chi)
    defect = geo("angle_defect", v, f)
    np.testing.assert_allclose(defect.sum(), 2 * np.pi * chi, rtol=1e-6, atol=1e-9)
    # trimesh's discrete Gaussian curvature measure at radius 0 sums the angle defects
    # of all vertices at the query point: cow.off has two vertices at one position.
    measure = trimesh.curvature.discrete_gaussian_curvature_measure(mesh, v, 0.0)
    _, same_point = np.unique(v, axis=0, return_inverse=True)
    same_point = same_point.ravel()
    at_point = np.bincount(same_point, defect)[same_point]
    np.testing.assert_allclose(at_point, measure, atol=1e-10)


@pytest.mark.parametrize("name", ["camel_b.obj", "lion.off"])
def test_gauss_bonnet_with_boundary(name):
    # The boundary convention (same formula on boundary vertices) turns each boundary
    # vertex's geodesic-curvature term π − Σθ into 2π − Σθ: the total gains π per
    # boundary vertex.
    v, f = load_mesh(shared_mesh_path(name))
    mesh = trimesh.Trimesh(v, f, process=False)
    boundary = np.unique(mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, 1)])
    total = geo("angle_defect", v, f).sum()
    expected = 2 * np.pi * mesh.euler_number + np.pi * boundary.size
    np.testing.assert_allclose(total, expected, rtol=1e-9)


# --------------------------------------------------------------------------------------
# trimesh and pymeshlab
# --------------------------------------------------------------------------------------


def test_normals_and_areas_match_trimesh(fandisk):
    v, f, g = fandisk
    mesh = trimesh.Trimesh(v, f, process=False)
    np.testing.assert_allclose(g["face_normals"], mesh.face_normals, atol=1e-12)
    np.testing.assert_allclose(g["face_areas"], mesh.area_faces, rtol=1e-12)
    np.testing.assert_allclose(
        g["face_cross"], 2 * mesh.area_faces[:, None] * mesh.face_normals, atol=1e-12
    )
    area_weighted = trimesh.geometry.mean_vertex_normals(
        len(v), f, mesh.face_normals * mesh.area_faces[:, None]
    )
    np.testing.assert_allclose(g["vertex_normals"], area_weighted, atol=1e-12)
    np.testing.assert_allclose(g["angle_defect"], mesh.vertex_defects, atol=1e-10)
    np.testing.assert_allclose(g["interior_angles"], mesh.face_angles, rtol=1e-9, atol=1e-12)


def test_curvature_matches_pymeshlab(knight):
    pymeshlab = pytest.importorskip("pymeshlab")
    v, f, g = knight
    ours = {
        "Mean Curvature": g["signed_mean_curvature"],
        "Gaussian Curvature": g["gaussian_curvature"],
    }
    for kind, value in ours.items():
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(v, f))
        ms.compute_scalar_by_discrete_curvature_per_vertex(curvaturetype=kind)
        theirs = ms.current_mesh().vertex_scalar_array()
        # MeshLab implements the same Meyer et al. operators; it works in single
        # precision internally (measured relative difference ≤ 4e-7 of the largest value).
        np.testing.assert_allclose(value, theirs, atol=1e-5 * np.abs(theirs).max(), err_msg=kind)


# --------------------------------------------------------------------------------------
# Identities
# --------------------------------------------------------------------------------------


def test_mixed_area_sums_to_total_area_and_angles_to_pi(fandisk):
    v, f = perturbed_icosphere(2, 0.1)
    for g in (fandisk[2], geo(ALL_FUNCTIONS, v, f)):
        angles = g["interior_angles"]
        assert (angles > np.pi / 2).any()  # obtuse triangles exercise the other branch
        np.testing.assert_allclose(angles.sum(axis=1), np.pi, rtol=1e-12)
        total = g["face_areas"].sum()
        area = g["mixed_voronoi_area"]
        assert (area > 0).all()
        np.testing.assert_allclose(area.sum(), total, rtol=1e-12)


def test_isolated_vertices_get_zeros():
    v, f = tetrahedron()
    v = np.concatenate([v, [[5.0, 5.0, 5.0]]])
    g = geo(ALL_FUNCTIONS, v, f)
    for name in (
        "vertex_normals",
        "mixed_voronoi_area",
        "mean_curvature",
        "gaussian_curvature",
        "angle_defect",
        "vertex_features",
    ):
        np.testing.assert_array_equal(g[name][4], 0.0, err_msg=name)


def test_safe_norm_and_normalize_at_zero():
    x = jnp.zeros((2, 3)).at[1].set(jnp.array([3.0, 4.0, 0.0]))
    np.testing.assert_allclose(G.safe_norm(x), [0.0, 5.0])
    np.testing.assert_allclose(G.safe_normalize(x), [[0, 0, 0], [0.6, 0.8, 0]])
    for fn in (G.safe_norm, lambda x: G.safe_normalize(x).sum(-1)):
        grad = jax.grad(lambda x, fn=fn: fn(x).sum())(x)
        assert jnp.isfinite(grad).all()
        np.testing.assert_array_equal(grad[0], 0.0)


def test_written_out_forms_match_the_reductions():
    # dot3, corner_sum and the size-3 branch of safe_norm / safe_normalize are the plain
    # reductions written out for XLA's CPU fusion: same values, same gradients.
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 7, 4, 3))
    np.testing.assert_allclose(G.dot3(a, b), np.sum(a * b, -1), rtol=1e-12)
    f = rng.integers(0, 7, size=(5, 3))
    x = rng.normal(size=(7, 2, 3))
    np.testing.assert_allclose(G.corner_sum(x, f), x[f].sum(1), rtol=1e-12)
    x = jnp.asarray(rng.normal(size=(6, 3)))
    np.testing.assert_allclose(G.safe_norm(x), np.linalg.norm(x, axis=-1), rtol=1e-12)
    np.testing.assert_allclose(G.safe_norm(x, keepdims=True)[:, 0], G.safe_norm(x))
    np.testing.assert_allclose(G.safe_norm(x.T, axis=0), G.safe_norm(x), rtol=1e-12)
    np.testing.assert_allclose(
        G.safe_normalize(x), x / np.linalg.norm(x, axis=-1, keepdims=True), rtol=1e-12
    )
    np.testing.assert_allclose(G.safe_normalize(x.T, axis=0).T, G.safe_normalize(x), rtol=1e-12)
    check_grads(G.safe_normalize, (x,), order=2, modes=["rev"])


# --------------------------------------------------------------------------------------
# Degenerate faces and gradients
# --------------------------------------------------------------------------------------


def degenerate_mesh():
    """A unit square, then: a collinear (zero-area) face, a face with two coincident
    vertices, a face with three coincident vertices and one with a collapsed edge."""
    v = np.array(
        [
            [0, 0, 0],
            [1, 0, 0],
            [1, 1, 0],
            [0, 1, 0],
            [2, 0, 0],  # 4: on the line through 1 and 5
            [3, 0, 0],
            [1, 1, 0],  # 6: coincides with 2
            [5, 5, 5],
            [5, 5, 5],
            [5, 5, 5],  # 7, 8, 9 coincide
            [4, 4, 4],
        ],
        np.float64,
    )
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [2, 6, 3], [7, 8, 9], [7, 8, 10], [1, 5, 2]])
    return v, f


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_degenerate_faces_give_finite_values_and_gradients(dtype):
    v, f = degenerate_mesh()
    x = jnp.asarray(v, dtype)
    values = _jitted(ALL_FUNCTIONS)(x, jnp.asarray(f))
    rng = np.random.default_rng(4)
    weights = {k: jnp.asarray(rng.normal(size=a.shape), dtype) for k, a in values.items()}

    @fast_jit
    def grads(x, f):
        # One program for all gradients (a compile per function would dominate).
        return {
            name: jax.grad(lambda x, name=name: jnp.sum(getattr(G, name)(x, f) * weights[name]))(x)
            for name in ALL_FUNCTIONS
        }

    for name, grad in grads(x, jnp.asarray(f)).items():
        assert values[name].dtype == dtype, name
        assert jnp.isfinite(values[name]).all(), name
        assert jnp.isfinite(grad).all(), name
    angles = np.asarray(values["interior_angles"])
    np.testing.assert_allclose(angles.sum(axis=1), np.pi, rtol=1e-6)
    np.testing.assert_allclose(angles[2], [0, np.pi, 0], atol=1e-6)  # collinear
    np.testing.assert_allclose(angles[3], [np.pi / 2, np.pi / 2, 0], atol=1e-6)
    np.testing.assert_allclose(angles[4], np.pi / 3, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(values["face_normals"])[2:6], 0.0)
    np.testing.assert_array_equal(np.asarray(values["face_areas"])[2:6], 0.0)
    # The square's own normals and areas are untouched by its degenerate neighbours.
    np.testing.assert_allclose(np.asarray(values["face_normals"])[:2], [[0, 0, 1]] * 2)


def test_gradients_float64():
    v, f = perturbed_icosphere(0)
    x = jnp.asarray(v)
    assert x.dtype == jnp.float64

    # Order 1 in one jitted program: order 2 costs about a minute of compiling on 2 cores.
    @jax.jit
    def fn(x):
        return jnp.concatenate(
            [
                G.mean_curvature(x, f),
                G.gaussian_curvature(x, f),
                G.face_normals(x, f).ravel(),
            ]
        )

    check_grads(fn, (x,), order=1, modes=("fwd", "rev"), rtol=1e-5)
