"""Classic denoisers (`dmd_jax.baselines`) against pymeshlab, loop-by-loop NumPy
transcriptions of their papers, and their expected behaviour on a noisy fandisk."""

from __future__ import annotations

import itertools
from collections import defaultdict

import jax
import numpy as np
import pytest
from conftest import crop_mesh, icosphere, shared_mesh_path, tetrahedron
from scipy.spatial.distance import pdist

from dmd_jax import baselines
from dmd_jax.baselines import l0_minimization
from dmd_jax.baselines._common import TRACE_COUNTS
from dmd_jax.graph import face_adjacency
from dmd_jax.io import load_mesh
from dmd_jax.mesh import mean_edge_length
from dmd_jax.metrics import face_normal_errors_deg
from dmd_jax.noise import add_noise_jax

METHODS = ("laplacian", "taubin", "bmd", "nifp", "fefp", "bnf", "gnf", "l0")
FEATURE_PRESERVING = ("bmd", "nifp", "fefp", "bnf", "gnf", "l0")
CORE_NAME = {"laplacian": "lambda_mu", "taubin": "lambda_mu"}


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


def _noisy(v, f, level, seed=0):
    """Gaussian noise of `level` × mean edge length per coordinate (project convention)."""
    key = jax.random.PRNGKey(seed)
    return np.asarray(add_noise_jax(key, v, f, "gaussian", level, units="edge"), np.float64)


@pytest.fixture(scope="module")
def knight():
    v, f = load_mesh(shared_mesh_path("decimated-knight.off"))
    return v, f, _noisy(v, f, 0.3)


@pytest.fixture(scope="module")
def fandisk():
    return load_mesh(shared_mesh_path("fandisk.off"))


@pytest.fixture(scope="module")
def fandisk_crop(fandisk):
    """About 1600 faces of fandisk around a corner: open boundary, 115 sharp edges."""
    v, f = fandisk
    return crop_mesh(v, f, np.array([3.5, 14.3, -1.4]), 1.2)


def _near_sharp_faces(v, f, degrees=60.0):
    """Faces with a vertex on an edge whose two faces' normals differ by > `degrees`."""
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    a, b = face_adjacency(f, v.shape[0])
    angle = np.degrees(np.arccos(np.clip(np.sum(n[a] * n[b], axis=1), -1.0, 1.0)))
    on_sharp = np.zeros(v.shape[0], bool)
    for fa, fb in zip(a[angle > degrees], b[angle > degrees], strict=True):
        on_sharp[np.intersect1d(f[fa], f[fb])] = True
    return on_sharp[f].any(axis=1)


# --------------------------------------------------------------------------------------
# Loop-by-loop NumPy references (deliberately naive: sets, dicts, Python loops)
# --------------------------------------------------------------------------------------


def _normals_np(x, f):
    c = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    return c / np.linalg.norm(c, axis=1, keepdims=True), 0.5 * np.linalg.norm(c, axis=1)


def _edge_faces(f):
    edges = defaultdict(list)
    for i, face in enumerate(f.tolist()):
        for k in range(3):
            edges[tuple(sorted((face[k], face[(k + 1) % 3])))].append(i)
    return edges


def _vertex_faces(f, n):
    vf = [[] for _ in range(n)]
    for i, face in enumerate(f.tolist()):
        for u in face:
            vf[u].append(i)
    return vf


def _face_rings(f, n):
    vf = _vertex_faces(f, n)
    return [sorted({j for u in face for j in vf[u]}) for face in f.tolist()]


def umbrella_reference(v, f, factors, iterations):
    """vcglib's uniform Laplacian with its boundary rule, vertex by vertex."""
    edges = _edge_faces(f)
    nbrs = defaultdict(list)
    boundary_nbrs = defaultdict(list)
    for (a, b), fs in edges.items():
        nbrs[a].append(b)
        nbrs[b].append(a)
        if len(fs) == 1:
            boundary_nbrs[a].append(b)
            boundary_nbrs[b].append(a)
    x = v.copy()
    for _ in range(iterations):
        for lam in factors:
            new = x.copy()
            for i in range(len(x)):
                if boundary_nbrs[i]:
                    avg = (x[i] + x[boundary_nbrs[i]].sum(axis=0)) / (1 + len(boundary_nbrs[i]))
                elif nbrs[i]:
                    avg = x[nbrs[i]].mean(axis=0)
                else:
                    continue
                new[i] = x[i] + lam * (avg - x[i])
            x = new
    return x


def fit_reference(x, f, normals, iterations):
    """Sun et al.'s vertex update, vertex by vertex."""
    vf = _vertex_faces(f, len(x))
    for _ in range(iterations):
        c = x[f].mean(axis=1)
        new = x.copy()
        for i, fs in enumerate(vf):
            if fs:
                step = sum(normals[j] * np.dot(normals[j], c[j] - x[i]) for j in fs)
                new[i] = x[i] + step / len(fs)
        x = new
    return x


def fefp_reference(v, f, threshold, normal_iterations, vertex_iterations):
    rings = _face_rings(f, len(v))
    n, _ = _normals_np(v, f)
    for _ in range(normal_iterations):
        new = np.zeros_like(n)
        for i, ring in enumerate(rings):
            for j in ring:
                d = np.dot(n[i], n[j])
                if d > threshold:
                    new[i] += (d - threshold) ** 2 * n[j]
        n = new / np.linalg.norm(new, axis=1, keepdims=True)
    return fit_reference(v, f, n, vertex_iterations)


def _mean_adjacent_centroid_distance(x, f):
    c = x[f].mean(axis=1)
    pairs = [fs for fs in _edge_faces(f).values() if len(fs) == 2]
    return float(np.mean([np.linalg.norm(c[a] - c[b]) for a, b in pairs]))


def bnf_reference(v, f, sigma_c, sigma_r, normal_iterations, vertex_iterations):
    rings = _face_rings(f, len(v))
    n, area = _normals_np(v, f)
    c = v[f].mean(axis=1)
    sc = sigma_c * _mean_adjacent_centroid_distance(v, f)
    for _ in range(normal_iterations):
        new = np.zeros_like(n)
        for i, ring in enumerate(rings):
            for j in ring:
                if j == i:
                    continue
                ws = np.exp(-np.sum((c[i] - c[j]) ** 2) / (2 * sc**2))
                wr = np.exp(-np.sum((n[i] - n[j]) ** 2) / (2 * sigma_r**2))
                new[i] += area[j] * ws * wr * n[j]
        n = new / np.linalg.norm(new, axis=1, keepdims=True)
    return fit_reference(v, f, n, vertex_iterations)


def gnf_reference(v, f, radius, sigma_s, sigma_r, normal_iterations, vertex_iterations):
    rings = _face_rings(f, len(v))
    adjacent = {tuple(sorted(fs)) for fs in _edge_faces(f).values() if len(fs) == 2}
    c0 = v[f].mean(axis=1)
    r = radius * _mean_adjacent_centroid_distance(v, f)
    omega = [np.flatnonzero(np.linalg.norm(c0 - c0[i], axis=1) <= r) for i in range(len(f))]
    x = v.copy()
    for _ in range(normal_iterations):
        n, area = _normals_np(x, f)
        c = x[f].mean(axis=1)
        ss = sigma_s * _mean_adjacent_centroid_distance(x, f)
        h = np.zeros(len(f))
        mean = np.zeros_like(n)
        for j, patch in enumerate(rings):
            diff = pdist(n[patch]).max() if len(patch) > 1 else 0.0
            inner = [(a, b) for a, b in itertools.combinations(patch, 2) if (a, b) in adjacent]
            phi = [np.linalg.norm(n[a] - n[b]) for a, b in inner]
            h[j] = diff * (max(phi, default=0.0) / (sum(phi) + 1e-9))
            m = sum(area[k] * n[k] for k in patch)
            mean[j] = m / np.linalg.norm(m)
        # Ties go to the smallest face index (the rings are sorted).
        guide = np.array([mean[min(ring, key=lambda j: h[j])] for ring in rings])
        new = np.zeros_like(n)
        for i in range(len(f)):
            for j in omega[i]:
                ws = np.exp(-np.sum((c[i] - c[j]) ** 2) / (2 * ss**2))
                wr = np.exp(-np.sum((guide[i] - guide[j]) ** 2) / (2 * sigma_r**2))
                new[i] += area[j] * ws * wr * n[j]
        new /= np.linalg.norm(new, axis=1, keepdims=True)
        x = fit_reference(x, f, new, vertex_iterations)
    return x


def bmd_reference(v, f, iterations):
    """Fleishman et al. with σ_c = shortest edge at v, ball neighbourhood of radius 2σ_c."""
    nbrs = defaultdict(set)
    for face in f.tolist():
        for k in range(3):
            nbrs[face[k]].add(face[(k + 1) % 3])
            nbrs[face[(k + 1) % 3]].add(face[k])
    x = v.copy()
    for _ in range(iterations):
        cross = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
        vn = np.zeros_like(x)
        for k in range(3):
            np.add.at(vn, f[:, k], cross)
        vn /= np.linalg.norm(vn, axis=1, keepdims=True)
        new = x.copy()
        for i in range(len(x)):
            sc = min(np.linalg.norm(x[j] - x[i]) for j in nbrs[i])
            d = x - x[i]
            t = np.linalg.norm(d, axis=1)
            inside = t <= 2 * sc
            h = d[inside] @ vn[i]
            ss = h.std()
            w = np.exp(-(t[inside] ** 2) / (2 * sc**2)) * np.exp(-(h**2) / (2 * ss**2))
            new[i] = x[i] + vn[i] * np.sum(w * h) / np.sum(w)
        x = new
    return x


def nifp_reference(v, f, sigma_f, sigma_g):
    """Jones et al. with brute-force distances (no KD-tree)."""
    e = mean_edge_length(v, f)
    sf, sg, sm = sigma_f * e, sigma_g * e, 0.5 * sigma_f * e
    _, area = _normals_np(v, f)
    c = v[f].mean(axis=1)
    dist = np.linalg.norm(v[:, None, :] - c[None, :, :], axis=-1)  # [n, f]
    inside = dist <= 2 * sf
    wm = inside * area * np.exp(-(dist**2) / (2 * sm**2))
    mollified = (wm @ c) / wm.sum(axis=1, keepdims=True)
    nm, _ = _normals_np(mollified, f)
    proj = v[:, None, :] - np.sum((v[:, None, :] - c) * nm, axis=-1, keepdims=True) * nm
    g = np.exp(-np.sum((proj - v[:, None, :]) ** 2, axis=-1) / (2 * sg**2))
    w = inside * area * np.exp(-(dist**2) / (2 * sf**2)) * g
    return np.einsum("vf,vfd->vd", w, proj) / w.sum(axis=1, keepdims=True)


def l0_reference(v, f, alpha, lam, beta, beta_max, rate, decay):
    """He & Schaefer with a dense solve per round; the operator written out per edge."""
    quads = []
    for (p1, p3), fs in _edge_faces(f).items():
        if len(fs) != 2:
            continue
        opp = [next(u for u in f[j] if u not in (p1, p3)) for j in fs]
        quads.append((p1, opp[0], p3, opp[1]))
    quads = np.array(quads)
    n_vertex = len(v)
    normals, _ = _normals_np(v, f)
    edges = [fs for fs in _edge_faces(f).values() if len(fs) == 2]
    gamma = np.mean([np.arccos(np.clip(normals[a] @ normals[b], -1, 1)) for a, b in edges])
    a = alpha * gamma
    lam_abs = lam * mean_edge_length(v, f) ** 2 * gamma
    r = np.array([1.0, -1.0, 1.0, -1.0])
    x = v.copy()
    b = beta
    while b < beta_max:
        p1, p2, p3, p4 = (x[quads[:, k]] for k in range(4))
        s123 = 0.5 * np.linalg.norm(np.cross(p2 - p1, p3 - p1), axis=1)
        s134 = 0.5 * np.linalg.norm(np.cross(p3 - p1, p4 - p1), axis=1)
        s = s123 + s134
        l2 = np.sum((p3 - p1) ** 2, axis=1)

        def dot(u, w):
            return np.sum(u * w, axis=1)

        coef = np.stack(
            [
                (s123 * dot(p4 - p3, p3 - p1) + s134 * dot(p1 - p3, p3 - p2)) / (l2 * s),
                s134 / s,
                (s123 * dot(p3 - p1, p1 - p4) + s134 * dot(p2 - p1, p1 - p3)) / (l2 * s),
                s123 / s,
            ],
            axis=1,
        )
        d = np.einsum("ek,ekd->ed", coef, x[quads])
        delta = np.where(np.sum(d * d, axis=1, keepdims=True) >= lam_abs / b, d, 0.0)
        m = np.eye(n_vertex)
        block = b * coef[:, :, None] * coef[:, None, :] + a * np.outer(r, r)
        np.add.at(m, (quads[:, :, None], quads[:, None, :]), block)
        rhs = v.copy()
        np.add.at(rhs, quads, b * coef[:, :, None] * delta[:, None, :])
        x = np.linalg.solve(m, rhs)
        b *= rate
        a *= decay
    return x


# --------------------------------------------------------------------------------------
# Registry and parameters
# --------------------------------------------------------------------------------------


def test_registry_lists_every_method_with_the_design_defaults():
    assert tuple(baselines.REGISTRY) == METHODS
    d = baselines.DEFAULTS
    assert d["taubin"] == {"lam": 0.5, "mu": -0.53, "iterations": 10}
    assert d["bmd"]["iterations"] == 5
    assert (d["nifp"]["sigma_f"], d["nifp"]["sigma_g"]) == (1.0, 1.0)
    assert (d["fefp"]["threshold"], d["fefp"]["normal_iterations"]) == (0.5, 20)
    assert d["fefp"]["vertex_iterations"] == 50
    assert (d["bnf"]["sigma_c"], d["bnf"]["sigma_r"]) == (1.0, 0.35)
    assert (d["bnf"]["normal_iterations"], d["bnf"]["vertex_iterations"]) == (20, 10)
    assert (d["gnf"]["radius"], d["gnf"]["sigma_s"], d["gnf"]["sigma_r"]) == (2.0, 1.0, 0.35)
    assert (d["gnf"]["normal_iterations"], d["gnf"]["vertex_iterations"]) == (20, 10)
    assert (d["l0"]["alpha"], d["l0"]["lam"], d["l0"]["beta"]) == (0.1, 0.2, 1e-3)
    assert d["l0"]["beta_max"] == 1e3 and d["l0"]["beta_rate"] == pytest.approx(2**0.5)


def test_old_name_denoise_with_still_works_with_a_deprecation_warning():
    with pytest.warns(DeprecationWarning, match="run_baseline"):
        assert baselines.denoise_with is baselines.run_baseline
    assert "denoise_with" not in baselines.__all__
    with pytest.raises(AttributeError, match="no attribute 'denoise'"):
        baselines.denoise  # noqa: B018


def test_run_baseline_rejects_unknown_methods_parameters_and_values():
    v, f = icosphere(1)
    with pytest.raises(ValueError, match="unknown denoiser 'median'"):
        baselines.run_baseline("median", v, f)
    with pytest.raises(ValueError, match="unknown parameter.*sigma"):
        baselines.run_baseline("taubin", v, f, sigma=1.0)
    with pytest.raises(ValueError, match="iterations"):
        baselines.run_baseline("laplacian", v, f, iterations=-1)
    with pytest.raises(ValueError, match="threshold"):
        baselines.run_baseline("fefp", v, f, threshold=1.5)
    with pytest.raises(ValueError, match="sigma_r"):
        baselines.run_baseline("gnf", v, f, sigma_r=0.0)
    with pytest.raises(ValueError, match="neighbourhood"):
        baselines.run_baseline("fefp", v, f, neighbourhood="ring")
    with pytest.raises(ValueError, match="faces"):
        baselines.run_baseline("bnf", v, f[:, :2])


# --------------------------------------------------------------------------------------
# pymeshlab cross-checks
# --------------------------------------------------------------------------------------


def _pymeshlab(v, f, filter_name, **params):
    pymeshlab = pytest.importorskip("pymeshlab")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(v, np.float64), np.asarray(f, np.int32)))
    getattr(ms, filter_name)(**params)
    out = ms.current_mesh().vertex_matrix()
    assert out.shape == v.shape  # pymeshlab kept every vertex, in order
    return out


def _bbox(v):
    return float(np.ptp(v, axis=0).max())


def test_meshlab_reference_filters_are_pymeshlabs_with_the_listed_settings(fandisk_crop):
    from dmd_jax.baselines.meshlab import PYMESHLAB_FILTERS, pymeshlab_filter

    v, f = fandisk_crop
    noisy = _noisy(v, f, 0.3)
    for name, (filter_name, params) in PYMESHLAB_FILTERS.items():
        out = pymeshlab_filter(noisy, f, name)
        assert out.dtype == np.float64
        np.testing.assert_array_equal(out, _pymeshlab(noisy, f, filter_name, **params))
    with pytest.raises(ValueError, match="unknown pymeshlab filter"):
        pymeshlab_filter(noisy, f, "laplacian")


@pytest.mark.parametrize("mesh", ["knight", "fandisk_crop"])
def test_taubin_matches_pymeshlab(mesh, request):
    if mesh == "knight":
        _, f, noisy = request.getfixturevalue("knight")
    else:
        v, f = request.getfixturevalue("fandisk_crop")  # open boundary
        noisy = _noisy(v, f, 0.3)
    ref = _pymeshlab(
        noisy, f, "apply_coord_taubin_smoothing", lambda_=0.5, mu=-0.53, stepsmoothnum=10
    )
    out = baselines.taubin(noisy, f)
    # Same weights and boundary rule: agreement to rounding (pymeshlab passes λ, μ as
    # C++ floats, μ = -0.53f differs from -0.53 by 1e-8).
    assert np.abs(out - ref).max() < 1e-8 * _bbox(noisy)
    assert np.abs(out - noisy).max() > 1e-3 * _bbox(noisy)


def test_fefp_meshlab_neighbourhood_matches_pymeshlab_two_step(fandisk_crop, fandisk):
    for v, f in (fandisk_crop, fandisk):
        noisy = _noisy(v, f, 0.3)
        ref = _pymeshlab(
            noisy,
            f,
            "apply_coord_two_steps_smoothing",
            stepsmoothnum=1,
            normalthr=60.0,
            stepnormalnum=20,
            stepfitnum=50,
        )
        out = baselines.fefp(noisy, f, neighbourhood="meshlab")
        assert np.linalg.norm(out - ref, axis=1).max() < 1e-9 * _bbox(noisy)


def test_fefp_paper_neighbourhood_beats_pymeshlab_two_step(fandisk):
    """Same settings, different neighbourhoods: the paper's full vertex ring vs
    vcglib's half ring (each face sees only the lower-index faces around its vertices,
    see `fefp`). The half ring leaves low-index faces almost unfiltered, so pymeshlab
    ends far from the paper's result (0.35 mean edge lengths apart on average here)
    and with a much larger normal error (measured: 3.4° vs 14.7°)."""
    v, f = fandisk
    noisy = _noisy(v, f, 0.2)
    params = dict(stepsmoothnum=1, normalthr=60.0, stepnormalnum=20, stepfitnum=50)
    ref = _pymeshlab(noisy, f, "apply_coord_two_steps_smoothing", **params)
    err_noisy = face_normal_errors_deg(noisy, v, f).mean()
    err_ours = face_normal_errors_deg(baselines.fefp(noisy, f), v, f).mean()
    err_meshlab = face_normal_errors_deg(ref, v, f).mean()
    assert err_ours < 0.5 * err_meshlab < 0.5 * err_noisy
    assert err_ours < 0.2 * err_noisy


# --------------------------------------------------------------------------------------
# Against loop-by-loop transcriptions of the papers
# --------------------------------------------------------------------------------------


def test_laplacian_and_taubin_match_vertex_loops(knight, fandisk_crop):
    _, f, noisy = knight
    tol = 1e-10 * _bbox(noisy)
    np.testing.assert_allclose(
        baselines.laplacian(noisy, f, lam=0.3, iterations=4),
        umbrella_reference(noisy, f, [0.3], 4),
        atol=tol,
    )
    v, f = fandisk_crop
    noisy = _noisy(v, f, 0.2)
    np.testing.assert_allclose(
        baselines.taubin(noisy, f, lam=0.6, mu=-0.65, iterations=3),
        umbrella_reference(noisy, f, [0.6, -0.65], 3),
        atol=1e-10 * _bbox(noisy),
    )


def test_fefp_matches_face_loops(knight):
    _, f, noisy = knight
    np.testing.assert_allclose(
        baselines.fefp(noisy, f, threshold=0.4, normal_iterations=4, vertex_iterations=6),
        fefp_reference(noisy, f, 0.4, 4, 6),
        atol=1e-10 * _bbox(noisy),
    )


def test_bnf_matches_face_loops(knight):
    _, f, noisy = knight
    np.testing.assert_allclose(
        baselines.bnf(noisy, f, sigma_c=1.3, sigma_r=0.3, normal_iterations=3, vertex_iterations=4),
        bnf_reference(noisy, f, 1.3, 0.3, 3, 4),
        atol=1e-10 * _bbox(noisy),
    )


def test_gnf_matches_face_loops(knight):
    _, f, noisy = knight
    np.testing.assert_allclose(
        baselines.gnf(noisy, f, normal_iterations=2, vertex_iterations=3),
        gnf_reference(noisy, f, 2.0, 1.0, 0.35, 2, 3),
        atol=1e-10 * _bbox(noisy),
    )


def test_bmd_matches_vertex_loops(knight):
    _, f, noisy = knight
    np.testing.assert_allclose(
        baselines.bmd(noisy, f, iterations=2),
        bmd_reference(noisy, f, 2),
        atol=1e-10 * _bbox(noisy),
    )


def test_nifp_matches_brute_force(knight):
    _, f, noisy = knight
    np.testing.assert_allclose(
        baselines.nifp(noisy, f, sigma_f=1.2, sigma_g=0.8),
        nifp_reference(noisy, f, 1.2, 0.8),
        atol=1e-10 * _bbox(noisy),
    )


def test_l0_matches_dense_solve(knight):
    _, f, noisy = knight
    params = dict(alpha=0.1, lam=0.2, beta=1e-3, beta_max=1e3, beta_rate=2**0.5, alpha_decay=0.5)
    np.testing.assert_allclose(
        baselines.l0(noisy, f, **params),
        l0_reference(noisy, f, *params.values()),
        atol=1e-8 * _bbox(noisy),
    )


def test_l0_edge_operator_vanishes_on_flat_pairs_and_ignores_translation():
    rng = np.random.default_rng(3)
    quads = np.array([[0, 1, 2, 3]], np.int32)
    for _ in range(5):
        flat = np.c_[rng.normal(size=(4, 2)), np.zeros(4)]
        flat[[1, 3], 1] = [abs(flat[1, 1]) + 1, -abs(flat[3, 1]) - 1]  # p2, p4 on either side
        flat[[0, 2], 1] = 0.0
        assert np.abs(np.asarray(l0_minimization.edge_operator(flat, quads))).max() < 1e-12
        bent = flat.copy()
        bent[3, 2] = 0.7
        coef = np.asarray(l0_minimization.edge_operator_coefficients(bent, quads))
        assert coef.sum() == pytest.approx(0.0, abs=1e-12)
        assert np.linalg.norm(np.asarray(l0_minimization.edge_operator(bent, quads))) > 1e-3


# --------------------------------------------------------------------------------------
# Behaviour on a noisy fandisk
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def crop_results(fandisk_crop):
    """Every method with its defaults on the crop at 0.1 and 0.3 × mean edge noise."""
    v, f = fandisk_crop
    out = {}
    for level in (0.1, 0.3):
        noisy = _noisy(v, f, level)
        out[level] = {"noisy": noisy}
        for name in METHODS:
            out[level][name] = baselines.run_baseline(name, noisy, f)
    return out


@pytest.mark.parametrize("name", METHODS)
def test_each_method_reduces_the_normal_error(name, fandisk_crop, crop_results):
    v, f = fandisk_crop
    noisy = crop_results[0.3]["noisy"]
    before = face_normal_errors_deg(noisy, v, f).mean()
    after = face_normal_errors_deg(crop_results[0.3][name], v, f).mean()
    assert np.isfinite(after) and after < 0.7 * before


def _laplacian_at_matched_smoothing(v, f, noisy, near, flat_target):
    """Near-edge error of the first Laplacian iterate whose flat-face error reaches
    `flat_target` (or of the smoothest iterate, if none does)."""
    x = noisy
    best = None
    for _ in range(40):
        x = baselines.laplacian(x, f, iterations=1)
        err = face_normal_errors_deg(x, v, f)
        flat, near_err = err[~near].mean(), err[near].mean()
        if flat <= flat_target:
            return near_err
        if best is None or flat < best[0]:
            best = (flat, near_err)
    return best[1]


@pytest.mark.parametrize("name", FEATURE_PRESERVING)
def test_feature_preserving_methods_keep_sharp_edges_better_than_laplacian(
    name, fandisk_crop, crop_results
):
    v, f = fandisk_crop
    near = _near_sharp_faces(v, f)
    noisy = crop_results[0.1]["noisy"]
    err = face_normal_errors_deg(crop_results[0.1][name], v, f)
    lap_near = _laplacian_at_matched_smoothing(v, f, noisy, near, err[~near].mean())
    assert err[near].mean() < lap_near


@pytest.mark.slow
@pytest.mark.parametrize("name", METHODS)
def test_full_fandisk_quality(name, fandisk):
    """The whole fandisk at 0.3 × mean edge noise (numbers quoted in the docs)."""
    v, f = fandisk
    noisy = _noisy(v, f, 0.3)
    before = face_normal_errors_deg(noisy, v, f).mean()
    after = face_normal_errors_deg(baselines.run_baseline(name, noisy, f), v, f).mean()
    assert after < 0.7 * before


# --------------------------------------------------------------------------------------
# Compilation, equivariance, odd inputs
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", METHODS)
def test_second_call_reuses_the_compiled_core(name, knight):
    _, f, noisy = knight
    core = CORE_NAME.get(name, name)
    first = baselines.run_baseline(name, noisy, f)
    traces = TRACE_COUNTS[core]
    assert traces >= 1
    second = baselines.run_baseline(name, noisy, f)
    np.testing.assert_array_equal(first, second)
    changed = {
        "laplacian": {"lam": 0.25, "iterations": 3},
        "taubin": {"lam": 0.4, "mu": -0.45, "iterations": 2},
        "bmd": {},
        "nifp": {"sigma_f": 0.9, "sigma_g": 1.3},
        "fefp": {"threshold": 0.7, "normal_iterations": 2, "vertex_iterations": 3},
        "bnf": {"sigma_c": 0.8, "normal_iterations": 2, "vertex_iterations": 3},
        "gnf": {"sigma_s": 1.5, "normal_iterations": 2, "vertex_iterations": 3},
        "l0": {"lam": 0.3, "beta_max": 10.0},
    }[name]
    baselines.run_baseline(name, noisy, f, **changed)
    # Parameters and iteration counts are traced values: no new trace. (NIFP's and
    # BMD's pair lists may land in another size bucket; the same settings do not.)
    if name not in ("nifp",):
        assert TRACE_COUNTS[core] == traces


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("name", METHODS)
def test_translation_scale_rotation_equivariance(name, knight):
    _, f, noisy = knight
    rot, scale, shift = _rotation(1), 37.5, np.array([4.0, -120.0, 9.0])
    out = baselines.run_baseline(name, noisy, f)
    moved = baselines.run_baseline(name, scale * noisy @ rot.T + shift, f)
    np.testing.assert_allclose(moved, scale * out @ rot.T + shift, atol=1e-7 * scale * _bbox(noisy))


@pytest.mark.parametrize("name", ["fefp", "bnf", "gnf"])
def test_fix_boundary_holds_open_boundary_vertices(name, fandisk_crop):
    v, f = fandisk_crop
    noisy = _noisy(v, f, 0.2)
    edges = _edge_faces(f)
    boundary = sorted({u for e, fs in edges.items() if len(fs) == 1 for u in e})
    assert len(boundary) > 50
    held = baselines.run_baseline(name, noisy, f, fix_boundary=True)
    free = baselines.run_baseline(name, noisy, f)
    # Held exactly, up to the round trip through the canonical frame.
    np.testing.assert_allclose(held[boundary], noisy[boundary], rtol=0, atol=1e-12 * _bbox(v))
    assert np.abs(free[boundary] - noisy[boundary]).max() > 0.01 * mean_edge_length(v, f)


def _odd_meshes():
    tv, tf = tetrahedron()
    # One triangle: no interior edge, no adjacent faces (empty pair lists everywhere).
    single = (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0.2]]), np.array([[0, 1, 2]]))
    # A closed tetrahedron plus a vertex no face uses.
    isolated = (np.vstack([tv, [[5.0, 5.0, 5.0]]]), tf)
    return {"single": single, "isolated": isolated}


@pytest.mark.parametrize("mesh", ["single", "isolated"])
def test_tiny_open_and_isolated_meshes_give_finite_output(mesh):
    v, f = _odd_meshes()[mesh]
    for name in METHODS:
        out = baselines.run_baseline(name, v, f)
        assert out.shape == v.shape and out.dtype == np.float64
        assert np.all(np.isfinite(out)), name
    if mesh == "isolated":
        # Only NIFP (a point-set method) may move a vertex no face contains.
        for name in METHODS:
            if name != "nifp":
                np.testing.assert_allclose(baselines.run_baseline(name, v, f)[-1], v[-1])
