"""The stress family: simple CAD shapes every user has, generated in code (no files).

Eight closed, consistently oriented, genus-0 meshes that a denoiser must not hurt
(issue 53: a 7x loss on one pyramid must show in the benchmark, not hide in a mean):

* `pyramid`: a square pyramid, five planes meeting at 4 creases and an apex;
* `cube`: six planes, right-angle creases and corners;
* `star_prism`: a five-pointed star extruded: concave creases beside convex ones;
* `sharp_cone`: a cone whose apex angle is 2·atan(0.25) ≈ 28°, the apex joined to
  `CONE_SEGMENTS` side faces;
* `fan_disc`: a thin coin whose caps are fans around one vertex each of valence
  `FAN_VALENCE` (CAD exporters fan a disc like this: long slivers, one huge valence);
* `cylinder`: fan caps and a side band, creases at the rims;
* `chamfered_box`: a box whose twelve edges are cut at 45°, two 135° creases per edge;
* `thin_plate`: a plate 50 times longer than thick: two sheets a few edges apart.

Each coarse solid is refined by midpoint subdivision (`subdivide`: every triangle into
four), which keeps flat faces flat, creases sharp and the valence of the original
vertices, so the shapes stay exact CAD geometry at a few thousand faces, the size of the
benchmark's meshes. Deterministic: no random draws. `tests/test_stress_shapes.py` checks
every shape is closed, oriented outwards, manifold and free of degenerate faces, with
trimesh's checks as the independent reference.
"""

from __future__ import annotations

import numpy as np

# The shapes, in table order.
STRESS_SHAPES = (
    "pyramid",
    "cube",
    "star_prism",
    "sharp_cone",
    "fan_disc",
    "cylinder",
    "chamfered_box",
    "thin_plate",
)
# The valence of each fan centre of `fan_disc` (issue 53: "valence ~100").
FAN_VALENCE = 100
# Side faces of `sharp_cone` meeting at its apex.
CONE_SEGMENTS = 32
# Faces around `cylinder`.
CYLINDER_SEGMENTS = 48
# `chamfered_box`: the cut, as a fraction of the box's shortest half-side.
CHAMFER = 0.25
# `thin_plate`: length / thickness.
PLATE_ASPECT = 50.0


def subdivide(vertices, faces, levels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint subdivision: every triangle into four, `levels` times (vectorised).

    New vertices are edge midpoints (shared by the edge's two faces), so planes stay
    planar and the mesh stays closed and oriented; old vertices keep their valence.

    Args:
      vertices: `[n_vertex, 3]`.
      faces: `[n_face, 3]` int.
      levels: how many times; 0 returns the input.

    Returns:
      `(vertices [n', 3] float64, faces [4^levels · n_face, 3] int32)`.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    for _ in range(int(levels)):
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        unique, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
        mid = v.shape[0] + inverse.reshape(3, -1).T  # [n_face, 3]: midpoints of 01, 12, 20
        v = np.concatenate([v, v[unique].mean(axis=1)])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
        f = np.concatenate(
            [
                np.stack([a, m01, m20], 1),
                np.stack([b, m12, m01], 1),
                np.stack([c, m20, m12], 1),
                np.stack([m01, m12, m20], 1),
            ]
        )
    return v, f.astype(np.int32)


def _hull(points) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull's triangles `(vertices, faces)`, oriented outwards."""
    from scipy.spatial import ConvexHull

    p = np.asarray(points, np.float64)
    hull = ConvexHull(p)
    f = hull.simplices.copy()
    tri = p[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = np.einsum("fk,fk->f", normal, tri.mean(axis=1) - p.mean(axis=0)) > 0
    f[~outward] = f[~outward][:, ::-1]
    used, inverse = np.unique(f, return_inverse=True)
    return p[used], inverse.reshape(-1, 3)


def _prism(outline, height: float, centre_caps: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A polygon `[k, 2]` (counter-clockwise, star-shaped about the origin) extruded along
    z from 0 to `height`, caps fanned around a centre vertex each."""
    poly = np.asarray(outline, np.float64)
    k = poly.shape[0]
    bottom = np.column_stack([poly, np.zeros(k)])
    top = np.column_stack([poly, np.full(k, height)])
    v = np.concatenate([bottom, top, [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    i = np.arange(k)
    j = (i + 1) % k
    cb, ct = 2 * k, 2 * k + 1
    side = np.concatenate([np.stack([i, j, k + j], 1), np.stack([i, k + j, k + i], 1)])
    caps = np.concatenate(
        [np.stack([np.full(k, cb), j, i], 1), np.stack([np.full(k, ct), k + i, k + j], 1)]
    )
    return v, np.concatenate([side, caps])


def _circle(n: int, radius: float = 1.0) -> np.ndarray:
    t = 2.0 * np.pi * np.arange(n) / n
    return radius * np.column_stack([np.cos(t), np.sin(t)])


def _box_points(a: float, b: float, c: float) -> np.ndarray:
    return np.array([[x, y, z] for x in (-a, a) for y in (-b, b) for z in (-c, c)])


def _pyramid():
    base = _box_points(0.5, 0.5, 0.0)[::2]  # the four corners at z = 0
    return subdivide(*_hull(np.concatenate([base, [[0.0, 0.0, 0.7]]])), 4)


def _cube():
    return subdivide(*_hull(_box_points(0.5, 0.5, 0.5)), 4)


def _star_prism():
    t = np.pi / 2 + np.pi * np.arange(10) / 5
    radius = np.where(np.arange(10) % 2 == 0, 0.5, 0.2)
    return subdivide(*_prism(radius[:, None] * np.column_stack([np.cos(t), np.sin(t)]), 0.3), 3)


def _sharp_cone():
    ring = np.column_stack([_circle(CONE_SEGMENTS, 0.25), np.zeros(CONE_SEGMENTS)])
    v = np.concatenate([ring, [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]])
    i = np.arange(CONE_SEGMENTS)
    j = (i + 1) % CONE_SEGMENTS
    apex, centre = CONE_SEGMENTS, CONE_SEGMENTS + 1
    f = np.concatenate(
        [np.stack([i, j, np.full_like(i, apex)], 1), np.stack([np.full_like(i, centre), j, i], 1)]
    )
    return subdivide(v, f, 3)


def _fan_disc():
    return subdivide(*_prism(_circle(FAN_VALENCE, 0.5), 0.04), 1)


def _cylinder():
    return subdivide(*_prism(_circle(CYLINDER_SEGMENTS, 0.3), 0.8), 2)


def _chamfered_box():
    a, b, c = 0.5, 0.35, 0.25
    t = CHAMFER * min(a, b, c)
    pts = np.concatenate(
        [_box_points(a, b - t, c - t), _box_points(a - t, b, c - t), _box_points(a - t, b - t, c)]
    )
    return subdivide(*_hull(pts), 3)


def _thin_plate():
    return subdivide(*_hull(_box_points(0.5, 0.3, 0.5 / PLATE_ASPECT)), 4)


_BUILDERS = {
    "pyramid": _pyramid,
    "cube": _cube,
    "star_prism": _star_prism,
    "sharp_cone": _sharp_cone,
    "fan_disc": _fan_disc,
    "cylinder": _cylinder,
    "chamfered_box": _chamfered_box,
    "thin_plate": _thin_plate,
}


def stress_shape(name: str) -> tuple[np.ndarray, np.ndarray]:
    """One shape of the stress family: `(vertices [n, 3] float64, faces [f, 3] int32)`.

    Raises:
      ValueError: an unknown name (the names are `STRESS_SHAPES`).
    """
    if name not in _BUILDERS:
        raise ValueError(f"unknown stress shape {name!r}; expected one of {STRESS_SHAPES}")
    v, f = _BUILDERS[name]()
    return np.asarray(v, np.float64), np.asarray(f, np.int32)


def stress_shapes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every shape of the family, `{name: (vertices, faces)}` in `STRESS_SHAPES` order."""
    return {name: stress_shape(name) for name in STRESS_SHAPES}
