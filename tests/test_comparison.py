"""Per-shape comparison measures (`dmd_jax.comparison`) against hand-built cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from conftest import icosphere

from dmd_jax import comparison
from dmd_jax.mesh import edge_dihedral_angles


def _box(subdivisions: int = 2):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    for _ in range(subdivisions):
        box = box.subdivide()
    return np.asarray(box.vertices), np.asarray(box.faces)


def _grid(k: int = 6):
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1), indexing="ij")
    a = (i * k + j).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + k], 1), np.stack([a + 1, a + k + 1, a + k], 1)])
    x, y = np.meshgrid(np.arange(k, dtype=float), np.arange(k, dtype=float), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(k * k)], 1), f


def test_edge_dihedral_angles_of_a_box_are_0_or_90():
    v, f = _box()
    a, b, angle = edge_dihedral_angles(v, f)
    assert len(a) == 3 * len(f) // 2  # closed: every edge has two faces
    np.testing.assert_allclose(np.sort(np.unique(np.round(angle, 6))), [0.0, 90.0], atol=1e-6)


def test_crease_faces_are_the_faces_along_the_box_edges():
    v, f = _box(subdivisions=2)
    crease = comparison.crease_faces(v, f)
    # A face is on a crease iff one of its edges lies on a box edge: both ends on one.
    centre = v.mean(0)
    half = np.abs(v - centre).max(0)
    on_face_planes = np.isclose(np.abs(v - centre), half)  # [n_vertex, 3]
    on_box_edge = on_face_planes.sum(1) >= 2
    edges = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1)  # [n_face, 3, 2]
    both = on_box_edge[edges].all(-1)  # an edge along a box edge (or a diagonal corner)
    same_plane_pair = (on_face_planes[edges[..., 0]] & on_face_planes[edges[..., 1]]).sum(-1)
    expected = (both & (same_plane_pair >= 2)).any(1)
    np.testing.assert_array_equal(crease, expected)
    assert 0 < crease.sum() < len(f)
    v2, f2 = _grid()
    assert not comparison.crease_faces(v2, f2).any()


def test_is_cad_tells_a_box_from_a_sphere():
    assert comparison.is_cad(*_box())
    assert not comparison.is_cad(*icosphere(3))
    flat, crease = comparison.surface_shares(*icosphere(3))
    assert flat == 0.0 and crease == 0.0  # every edge of a fine sphere bends a little
    flat, crease = comparison.surface_shares(*_box())
    assert flat > 0.8 and crease > 0.05


def test_region_errors_split_by_the_mask():
    errors = np.array([1.0, 2.0, 3.0, np.nan, 10.0])
    crease = np.array([True, True, False, False, False])
    assert comparison.region_errors(errors, crease) == (1.5, 6.5)
    c, flat = comparison.region_errors(errors, np.zeros(5, bool))
    assert math.isnan(c) and flat == pytest.approx(16 / 4)
    with pytest.raises(ValueError, match="must be equal"):
        comparison.region_errors(errors, crease[:3])


def test_ratios_geometric_mean_and_share():
    errors = {
        "a": {"dmd": 1.0, "bnf": 2.0, "cnr": 4.0},
        "b": {"dmd": 3.0, "bnf": 2.0, "cnr": 1.5},
        "c": {"dmd": 1.02, "bnf": 1.0},
        "d": {"bnf": 1.0},  # no DMD-Net row: not a case
    }
    ratios = comparison.ratios_to_best_other(errors, "dmd", ["dmd", "bnf", "cnr"])
    assert ratios == {"a": 0.5, "b": 2.0, "c": pytest.approx(1.02)}
    assert comparison.geometric_mean([0.5, 2.0]) == pytest.approx(1.0)
    assert comparison.geometric_mean(ratios.values()) == pytest.approx(1.02 ** (1 / 3))
    assert comparison.share_within(ratios.values()) == pytest.approx(2 / 3)
    assert math.isnan(comparison.geometric_mean([]))
    with pytest.raises(ValueError, match="positive"):
        comparison.geometric_mean([1.0, 0.0])
    with pytest.raises(ValueError, match="no method other than"):
        comparison.ratios_to_best_other(errors, "dmd", ["dmd"])
    zero = comparison.ratios_to_best_other({"z": {"dmd": 0.0, "bnf": 0.0}}, "dmd", ["bnf"])
    assert zero == {"z": 1.0}
