"""The stress family of `dmd_jax.data.stress`: closed, oriented, valid CAD shapes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dmd_jax.data.stress import (
    CONE_SEGMENTS,
    FAN_VALENCE,
    STRESS_SHAPES,
    stress_shape,
    stress_shapes,
    subdivide,
)


@pytest.fixture(scope="module")
def shapes():
    return stress_shapes()


def _directed_edges(f):
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


@pytest.mark.parametrize("name", STRESS_SHAPES)
def test_every_shape_is_a_closed_oriented_genus_zero_solid(shapes, name):
    import trimesh

    v, f = shapes[name]
    assert v.dtype == np.float64 and f.dtype == np.int32
    assert 1000 <= f.shape[0] <= 8000, f.shape
    # Every vertex used, none duplicated.
    assert np.unique(f).size == v.shape[0]
    assert np.unique(np.round(v, 12), axis=0).shape[0] == v.shape[0]
    # Closed and consistently oriented: each directed edge once, its reverse once.
    d = _directed_edges(f)
    assert np.unique(d, axis=0).shape[0] == d.shape[0]
    und = np.unique(np.sort(d, axis=1), axis=0)
    assert und.shape[0] * 2 == d.shape[0]
    # Euler characteristic 2: one closed genus-0 surface.
    assert v.shape[0] - und.shape[0] + f.shape[0] == 2
    # No degenerate face; the volume is positive (normals point out).
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.linalg.norm(cross, axis=1).min() > 1e-9
    volume = np.einsum("fk,fk->f", tri[:, 0], cross).sum() / 6.0
    assert volume > 0
    # trimesh as the independent reference.
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    assert mesh.volume == pytest.approx(volume)
    assert len(mesh.split(only_watertight=False)) == 1


def test_known_volumes_and_features(shapes):
    import trimesh

    def volume(name):
        v, f = shapes[name]
        return trimesh.Trimesh(v, f, process=False).volume

    assert volume("cube") == pytest.approx(1.0)
    assert volume("pyramid") == pytest.approx(0.7 / 3.0)
    assert volume("thin_plate") == pytest.approx(1.0 * 0.6 * 0.02)
    # A 45° chamfer of depth t cuts a t²/2 prism off each edge between its corner cubes
    # (t wide); of each corner cube only {u + v + w >= 2t}, t³/6, stays.
    a, b, c, t = 0.5, 0.35, 0.25, 0.0625
    edges = 4 * (t * t / 2) * ((2 * a - 2 * t) + (2 * b - 2 * t) + (2 * c - 2 * t))
    corners = 8 * (5 * t**3 / 6)
    assert volume("chamfered_box") == pytest.approx(8 * a * b * c - edges - corners, rel=1e-9)
    # The fan disc's two centres have the valence ~100; the cone's apex is sharp.
    v, f = shapes["fan_disc"]
    valence = np.bincount(np.unique(np.sort(_directed_edges(f), axis=1), axis=0).ravel())
    assert valence.max() == FAN_VALENCE and np.sum(valence == FAN_VALENCE) == 2
    v, f = shapes["sharp_cone"]
    apex = int(np.argmax(v[:, 2]))
    assert np.sum(np.any(f == apex, axis=1)) == CONE_SEGMENTS
    radius = np.linalg.norm(v[:, :2], axis=1).max()
    assert math.degrees(2 * math.atan(radius / v[apex, 2])) < 30.0


def test_subdivision_keeps_planes_and_quadruples_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v2, f2 = subdivide(v, f, 2)
    assert f2.shape[0] == 16 * 4
    # Every new vertex lies on the plane of its original face (here: the 4 planes).
    on_plane = (
        np.isclose(v2[:, 0], 0) | np.isclose(v2[:, 1], 0) | np.isclose(v2[:, 2], 0)
    ) | np.isclose(v2.sum(axis=1), 1)
    assert on_plane.all()
    np.testing.assert_array_equal(subdivide(v, f, 0)[1], f)


def test_shapes_are_deterministic_and_names_are_checked():
    for name in ("cube", "fan_disc"):
        a, b = stress_shape(name), stress_shape(name)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    with pytest.raises(ValueError, match="unknown stress shape"):
        stress_shape("teapot")
