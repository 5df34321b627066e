"""The depth-camera simulator `dmd_jax.scan`: geometry, ground truth, noise, bad input."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from conftest import icosphere

import dmd_jax
from dmd_jax import noise
from dmd_jax.mesh import mean_edge_length
from dmd_jax.scan import (
    MAX_RESOLUTION,
    Scan,
    render_depth,
    simulate_scan,
    view_basis,
)


def _box(size=(1.0, 1.0, 1.0), centre=(0.0, 0.0, 0.0)):
    import trimesh

    b = trimesh.creation.box(extents=size)
    return np.asarray(b.vertices, np.float64) + np.asarray(centre), np.asarray(b.faces, np.int32)


def _boundary_edges(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int(np.sum(counts == 1))


def _ray_cast_depth(v, f, basis, origins):
    """Brute-force Möller-Trumbore: nearest hit depth of rays `origins + t d` (inf: miss)."""
    d = basis[2]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("fk,fk->f", e1, p)
    out = np.full(origins.shape[0], np.inf)
    ok = np.abs(det) > 1e-14
    for i, o in enumerate(origins):
        s = o - a
        u = np.einsum("fk,fk->f", s, p) / np.where(ok, det, 1)
        q = np.cross(s, e1)
        w = (q @ d) / np.where(ok, det, 1)
        t = np.einsum("fk,fk->f", e2, q) / np.where(ok, det, 1)
        hit = ok & (u >= -1e-9) & (w >= -1e-9) & (u + w <= 1 + 1e-9)
        if hit.any():
            out[i] = t[hit].min()
    return out


def test_issue_example_returns_one_shape_and_open_boundaries():
    v, f = icosphere(3)
    scan = simulate_scan(3, v, f)
    assert isinstance(scan, Scan)
    assert scan.clean.shape == scan.noisy.shape and scan.clean.shape[1] == 3
    assert scan.faces.dtype == np.int32 and scan.faces.min() >= 0
    assert scan.faces.max() == scan.clean.shape[0] - 1
    assert np.unique(scan.faces).size == scan.clean.shape[0]  # every vertex used
    assert _boundary_edges(scan.faces) > 0
    assert np.linalg.norm(scan.view) == pytest.approx(1.0)
    assert not np.array_equal(scan.clean, scan.noisy)


def test_depth_map_matches_brute_force_ray_casting():
    """The rasteriser's nearest hit per pixel against independent ray-triangle tests."""
    v, f = icosphere(1)
    v = v * np.array([1.0, 0.6, 0.8]) + np.array([0.2, -0.1, 0.3])
    basis = view_basis([0.3, -0.5, 0.8])
    dm = render_depth(v, f.astype(np.int64), basis, 24)
    ny, nx = dm.depth.shape
    p = v @ basis[:2].T
    lo, hi = p.min(0), p.max(0)
    origin = (lo + hi) / 2 - dm.pixel * np.array([nx, ny]) / 2
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    centres = origin + (np.stack([jj.ravel(), ii.ravel()], 1) + 0.5) * dm.pixel
    far = -10.0  # ray origins behind the mesh along the view
    origins = centres @ basis[:2] + far * basis[2]
    ref = _ray_cast_depth(v, f, basis, origins) + far
    got = dm.depth.ravel()
    assert np.array_equal(np.isfinite(ref), np.isfinite(got))
    np.testing.assert_allclose(got[np.isfinite(got)], ref[np.isfinite(ref)], atol=1e-9)


def test_clean_points_lie_on_the_surface_and_see_the_front_only():
    # A box seen along a diagonal: every clean point is on the box (max-norm 0.5), on a
    # face turned to the sensor.
    v, f = _box()
    view = np.array([1.0, 0.7, -0.4])
    scan = simulate_scan(0, v, f, view=view, resolution=64, level=0.0)
    np.testing.assert_allclose(np.abs(scan.clean).max(axis=1), 0.5, atol=1e-12)
    d = scan.view
    for axis in range(3):
        on = np.isclose(np.abs(scan.clean[:, axis]), 0.5)
        # The faces seen have outward normals against the view.
        assert np.all(np.sign(scan.clean[on, axis]) * d[axis] <= 0)
    np.testing.assert_array_equal(scan.noisy, scan.clean)
    # Faces are oriented towards the sensor.
    tri = scan.clean[scan.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(n @ d < 0)


def test_occlusion_leaves_a_hole_and_no_triangle_across_the_jump():
    # A small box in front of a large one: the large box's hidden part is missing and no
    # triangle joins the two.
    front, f_front = _box((0.5, 0.5, 0.5), (0.0, 0.0, 2.0))
    back, f_back = _box((2.0, 2.0, 0.2), (0.0, 0.0, 0.0))
    v = np.concatenate([front, back])
    f = np.concatenate([f_front, f_back + front.shape[0]])
    scan = simulate_scan(0, v, f, view=(0, 0, -1), resolution=80, level=0.0)
    z = scan.clean[:, 2]
    on_back = np.isclose(z, 0.1)
    on_front = np.isclose(z, 2.25)
    assert on_back.any() and on_front.any()
    assert on_back.sum() + on_front.sum() == z.size  # only the two faces seen head-on
    hidden = on_back & (np.abs(scan.clean[:, 0]) < 0.2) & (np.abs(scan.clean[:, 1]) < 0.2)
    assert not hidden.any()
    mixed = on_back[scan.faces].any(axis=1) & on_front[scan.faces].any(axis=1)
    assert not mixed.any()
    assert _boundary_edges(scan.faces) > 0


def test_grazing_surfaces_are_dropped():
    v, f = icosphere(4)
    view = np.array([0.0, 0.0, 1.0])
    scan = simulate_scan(0, v, f, view=view, resolution=128, level=0.0, max_grazing_deg=60.0)
    cos = np.abs(scan.clean @ view) / np.linalg.norm(scan.clean, axis=1)
    # Sphere normals are radial; the faceted icosphere's deviate by a few degrees.
    assert cos.min() > math.cos(math.radians(63.0))
    wide = simulate_scan(0, v, f, view=view, resolution=128, level=0.0)
    cos = np.abs(wide.clean @ view) / np.linalg.norm(wide.clean, axis=1)
    assert cos.min() < math.cos(math.radians(70.0))  # slivers up to 80° stay by default


def test_noise_is_the_scanner_kind_along_the_view_on_the_scan():
    v, f = icosphere(3)
    scan = simulate_scan(5, v, f, resolution=96, level=0.5)
    h = mean_edge_length(scan.clean, scan.faces)
    rng = noise.host_rng(jax.random.PRNGKey(5))
    drawn = noise.random_view(rng)
    np.testing.assert_allclose(drawn, scan.view)
    moved, _ = noise.scanner_displacement(rng, scan.clean, scan.faces, 0.5, h, view=scan.view)
    np.testing.assert_array_equal(scan.noisy, scan.clean + moved)
    d = scan.noisy - scan.clean
    assert np.abs(d - np.outer(d @ scan.view, scan.view)).max() < 1e-12
    rms = np.sqrt(np.mean(np.sum(d * d, axis=1)))
    assert rms == pytest.approx(0.5 * h, rel=0.3)
    # The scan's mean edge is about the pixel size (grid edges and diagonals).
    assert 0.5 < h / (2.0 * 1.04 / 96) < 2.0


def test_same_seed_same_scan_and_seeds_draw_views():
    v, f = icosphere(2)
    a, b = simulate_scan(7, v, f, resolution=48), simulate_scan(7, v, f, resolution=48)
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x, y)
    c = simulate_scan(8, v, f, resolution=48)
    assert not np.allclose(a.view, c.view)
    given = simulate_scan(7, v, f, view=a.view * 3.0, resolution=48)
    np.testing.assert_allclose(given.view, a.view)
    # The same scan up to the rounding of the view's normalisation.
    np.testing.assert_allclose(given.clean, a.clean, atol=1e-12)


def test_bad_input_raises_one_clear_error():
    v, f = icosphere(1)
    plate = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    plate_f = np.array([[0, 1, 2], [1, 3, 2]])
    with pytest.raises(ValueError, match="no surface in view"):
        simulate_scan(0, plate, plate_f, view=(1, 0, 0))
    with pytest.raises(ValueError, match="view"):
        simulate_scan(0, v, f, view=(0, 0, 0))
    with pytest.raises(ValueError, match="view"):
        simulate_scan(0, v, f, view=(0, 1))
    for res in (0, 10**6, 2.5, True):
        with pytest.raises(ValueError, match="resolution"):
            simulate_scan(0, v, f, resolution=res)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="vertices"):
        simulate_scan(0, bad, f)
    with pytest.raises(ValueError, match="faces"):
        simulate_scan(0, v, f + 1000)
    with pytest.raises(ValueError, match="level"):
        simulate_scan(0, v, f, level=-1.0)
    with pytest.raises(ValueError, match="max_grazing_deg"):
        simulate_scan(0, v, f, max_grazing_deg=0.0)
    assert MAX_RESOLUTION < 10**6


def test_package_root_exports_simulate_scan():
    assert dmd_jax.simulate_scan is simulate_scan
    assert "simulate_scan" in dmd_jax.__all__


def test_a_scan_trains_through_the_pipeline_with_its_view():
    from dmd_jax.config import NoiseConfig
    from dmd_jax.pipeline import evaluation_batches, make_examples

    v, f = icosphere(2)
    scan = simulate_scan(1, v, f, resolution=32)
    (ex,) = make_examples([(scan.clean, scan.faces, scan.view)])
    np.testing.assert_array_equal(ex.view, scan.view)
    ((batch, spec),) = evaluation_batches([ex], seed=0, noise=NoiseConfig(), rotate=True)
    assert spec.kind == "scanner"
    n = int(batch.graph.n_vertex_per_graph[0])
    d = np.asarray(batch.noisy[:n], np.float64) - np.asarray(batch.clean[:n], np.float64)
    # Rotated with the mesh, the view is still one direction: rank-1 displacements.
    s = np.linalg.svd(d, compute_uv=False)
    assert s[1] < 1e-3 * s[0]


def test_scan_validation_splits_of_the_validation_patches():
    from conftest import crop_mesh

    from dmd_jax.config import NoiseConfig
    from dmd_jax.data import training_sets as ts
    from dmd_jax.pipeline import evaluation_batches, make_examples

    v, f = icosphere(3)
    patches = [crop_mesh(v, f, np.array(c), 0.7) for c in ([0, 0, 1.0], [1.0, 0, 0])]
    splits = ts.scan_validation(patches, resolution=32, seed=0)
    assert set(splits) == {ts.REAL_VAL_SCANNER, ts.REAL_VAL_SCAN}
    for (pv, pf), (sv, sf, view), (cv, cf, cview) in zip(
        patches, splits[ts.REAL_VAL_SCANNER], splits[ts.REAL_VAL_SCAN], strict=True
    ):
        assert sv is pv and sf is pf
        np.testing.assert_allclose(cview, view)
        # The view looks at the cap's front: against its mean outward normal.
        assert view @ pv.mean(axis=0) < 0
        assert np.all(np.abs(np.linalg.norm(cv, axis=1) - 1.0) < 0.02) and cf.shape[0] > 50
    batches = evaluation_batches(
        make_examples(splits[ts.REAL_VAL_SCAN]), seed=1, noise=NoiseConfig(), rotate=True
    )
    assert all(spec.kind == "scanner" for _, spec in batches)
    again = ts.scan_validation(patches, resolution=32, seed=0)
    assert np.array_equal(again[ts.REAL_VAL_SCAN][0][0], splits[ts.REAL_VAL_SCAN][0][0])


def test_depth_map_is_the_same_in_small_chunks(monkeypatch):
    """Chunks cut through faces (a face's candidate pixels split between chunks) and
    still give the same depth map, bit for bit."""
    from dmd_jax import scan as scan_mod

    v, f = icosphere(1)
    basis = view_basis([0.2, 0.9, -0.3])
    whole = render_depth(v, f.astype(np.int64), basis, 40)
    monkeypatch.setattr(scan_mod, "_CHUNK_CANDIDATES", 7)
    parts = render_depth(v, f.astype(np.int64), basis, 40)
    for a, b in zip(whole[:3], parts[:3], strict=True):
        np.testing.assert_array_equal(a, b)
