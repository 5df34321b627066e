"""Building blocks of the shape categories: manifold3d solids (boxes, cylinders,
revolved profiles, booleans), parametric grids, tubes swept along curves with parallel
transport frames, and marching cubes of smooth fields. A builder that draws an unusable
shape raises `_Reject`, and the generator draws the next attempt."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from dmd_jax.data.repair import _orient_outward


class _Reject(Exception):
    """A drawn shape is unusable (split apart, self-touching, ...); draw the next attempt."""


# --------------------------------------------------------------------------------------
# Small geometry helpers
# --------------------------------------------------------------------------------------

_HOLE_SEGMENTS = 96  # circles in CAD parts: 3.75 degrees per facet, far below feature_angle
_REVOLVE_SEGMENTS = 128


def _manifold():
    import manifold3d

    return manifold3d


def _arrays(man) -> tuple[np.ndarray, np.ndarray]:
    """Vertices float64 `[n, 3]` and faces int64 `[f, 3]` of a manifold3d solid."""
    if man.is_empty():
        raise _Reject(f"empty solid ({man.status()})")
    mesh = man.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3].copy()
    f = np.asarray(mesh.tri_verts, dtype=np.int64).copy()
    return v, f


def _one_piece(man):
    """Rejects a solid that fell apart into several bodies."""
    if man.is_empty():
        raise _Reject("empty solid")
    if len(man.decompose()) != 1:
        raise _Reject("solid has several connected bodies")
    return man


def _union(parts):
    m = _manifold()
    return m.Manifold.batch_boolean(list(parts), m.OpType.Add)


def _cylinder(height: float, radius: float, *, axis: int = 2, center=(0.0, 0.0, 0.0)):
    """A centred cylinder along `axis` (0, 1, 2) with fine facets."""
    m = _manifold()
    c = m.Manifold.cylinder(height, radius, -1.0, _HOLE_SEGMENTS, True)
    if axis == 0:
        c = c.rotate((0.0, 90.0, 0.0))
    elif axis == 1:
        c = c.rotate((90.0, 0.0, 0.0))
    return c.translate(tuple(float(x) for x in center))


def _box(size, center=(0.0, 0.0, 0.0)):
    m = _manifold()
    return m.Manifold.cube(tuple(float(s) for s in size), True).translate(
        tuple(float(x) for x in center)
    )


def _cross_section(points):
    m = _manifold()
    return m.CrossSection([np.asarray(points, dtype=np.float64)])


def _revolve(profile, segments: int = _REVOLVE_SEGMENTS):
    """Revolves a closed profile polygon `[(radius, height), ...]` around the z axis."""
    m = _manifold()
    cs = _cross_section(profile)
    if cs.is_empty() or cs.area() <= 0:
        raise _Reject("empty profile")
    return m.Manifold.revolve(cs, segments)


def _grid_faces(n_rows: int, n_cols: int, *, wrap_rows: bool, wrap_cols: bool) -> np.ndarray:
    """Two triangles per cell of a `[n_rows, n_cols]` vertex grid (row-major indices).

    The triangles `(a, b, c)` and `(a, c, d)` of a cell with corners `a = (i, j)`,
    `b = (i + 1, j)`, `c = (i + 1, j + 1)`, `d = (i, j + 1)` are wound consistently.
    """
    rows = np.arange(n_rows if wrap_rows else n_rows - 1)
    cols = np.arange(n_cols if wrap_cols else n_cols - 1)
    i, j = np.meshgrid(rows, cols, indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1, j1 = (i + 1) % n_rows, (j + 1) % n_cols
    a, b, c, d = i * n_cols + j, i1 * n_cols + j, i1 * n_cols + j1, i * n_cols + j1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


# --------------------------------------------------------------------------------------
# Tubes (torus, knots, swept curves)
# --------------------------------------------------------------------------------------


def _parallel_transport_frames(points: np.ndarray, closed: bool):
    """Tangents and rotation-minimising normals along a polyline `[m, 3]`.

    For a closed curve the holonomy (the angle the transported normal is off by after one
    loop) is spread evenly along the curve so the frame closes up without a seam.
    """
    if closed:
        t = np.roll(points, -1, 0) - np.roll(points, 1, 0)
    else:
        t = np.gradient(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    m = points.shape[0]
    seed_axis = np.eye(3)[np.argmin(np.abs(t[0]))]
    n = np.empty_like(points)
    n[0] = np.cross(t[0], seed_axis)
    n[0] /= np.linalg.norm(n[0])
    for k in range(1, m):
        v = n[k - 1] - np.dot(n[k - 1], t[k]) * t[k]
        n[k] = v / np.linalg.norm(v)
    if closed:
        back = n[-1] - np.dot(n[-1], t[0]) * t[0]
        back /= np.linalg.norm(back)
        angle = np.arctan2(np.dot(np.cross(back, n[0]), t[0]), np.dot(back, n[0]))
        phi = angle * np.arange(m) / m
        b = np.cross(t, n)
        n = np.cos(phi)[:, None] * n + np.sin(phi)[:, None] * b
    b = np.cross(t, n)
    return t, n, b


def _check_tube_clearance(points: np.ndarray, radius: np.ndarray, closed: bool) -> None:
    """Rejects a tube that would touch itself: bends tighter than its radius or strands
    that come closer than twice the radius."""
    from scipy.spatial import cKDTree

    ends = np.concatenate([points, points[:1]]) if closed else points
    seg = np.linalg.norm(np.diff(ends, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])[: points.shape[0]]
    total = seg.sum()
    t, _, _ = _parallel_transport_frames(points, closed)
    dt = np.linalg.norm(np.gradient(t, axis=0), axis=1) / np.maximum(np.gradient(s), 1e-12)
    if not closed:
        dt = dt[1:-1]
    r_max = float(radius.max())
    if np.any(dt * 1.5 * r_max > 1.0):
        raise _Reject("tube bends tighter than its radius")
    pairs = cKDTree(points).query_pairs(2.2 * r_max, output_type="ndarray")
    if pairs.size:
        gap = np.abs(s[pairs[:, 0]] - s[pairs[:, 1]])
        if closed:
            gap = np.minimum(gap, total - gap)
        if np.any(gap > 4.0 * r_max):
            raise _Reject("tube strands come too close")


def _sweep_tube(
    points: np.ndarray,
    radius: np.ndarray,
    *,
    closed: bool,
    n_around: int = 48,
    aspect: float = 1.0,
    caps: str = "round",
) -> tuple[np.ndarray, np.ndarray]:
    """A tube of (elliptic) cross-section swept along a polyline.

    Args:
      points: `[m, 3]` curve samples (the last sample is not repeated for closed curves).
      radius: `[m]` tube radius at each sample.
      closed: the curve is a loop (a torus-like surface) rather than an open path.
      n_around: vertices around each cross-section ring.
      aspect: ratio of the cross-section's two semi-axes.
      caps: `"round"` (hemispheres) or `"flat"` (discs) closing an open tube.

    Returns:
      `(vertices [n, 3], faces [f, 3])`, a closed consistently wound surface.
    """
    t, n, b = _parallel_transport_frames(points, closed)
    theta = 2 * np.pi * np.arange(n_around) / n_around
    centres, radii_a, radii_b, normals, binormals = [points], [radius], [radius * aspect], [n], [b]
    if not closed and caps == "round":
        # Extra rings shrinking along the end tangents turn the ends into half-ellipsoids.
        k = 8
        phi = np.pi / 2 * np.arange(1, k) / k
        r0, r1 = radius[0], radius[-1]
        start = points[0] - np.outer(np.sin(phi), t[0]) * r0
        end = points[-1] + np.outer(np.sin(phi), t[-1]) * r1
        centres = [start[::-1], points, end]
        radii_a = [r0 * np.cos(phi)[::-1], radius, r1 * np.cos(phi)]
        radii_b = [a * aspect for a in radii_a]
        normals = [np.repeat(n[:1], k - 1, 0), n, np.repeat(n[-1:], k - 1, 0)]
        binormals = [np.repeat(b[:1], k - 1, 0), b, np.repeat(b[-1:], k - 1, 0)]
    c = np.concatenate(centres)
    ra, rb = np.concatenate(radii_a), np.concatenate(radii_b)
    nn, bb = np.concatenate(normals), np.concatenate(binormals)
    rings = (
        c[:, None, :]
        + (ra[:, None, None] * np.cos(theta)[None, :, None]) * nn[:, None, :]
        + (rb[:, None, None] * np.sin(theta)[None, :, None]) * bb[:, None, :]
    )
    m = rings.shape[0]
    v = rings.reshape(-1, 3)
    f = _grid_faces(m, n_around, wrap_rows=closed, wrap_cols=True)
    if not closed:
        if caps == "round":
            first = points[0] - t[0] * radius[0]
            last = points[-1] + t[-1] * radius[-1]
        else:
            first, last = c[0], c[-1]
        i0, i1 = v.shape[0], v.shape[0] + 1
        v = np.concatenate([v, first[None], last[None]])
        j = np.arange(n_around)
        jn = (j + 1) % n_around
        start_cap = np.stack([np.full(n_around, i0), j, jn], 1)
        end_cap = np.stack(
            [np.full(n_around, i1), (m - 1) * n_around + jn, (m - 1) * n_around + j], 1
        )
        f = np.concatenate([f, start_cap, end_cap])
    return v, _orient_outward(v, f)


# --------------------------------------------------------------------------------------
# Fields and marching cubes
# --------------------------------------------------------------------------------------


def _marching_cubes(
    field: Callable[[np.ndarray], np.ndarray], lo, hi, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """The zero level set of `field` (positive inside) as a closed triangle mesh.

    Args:
      field: maps points `[..., 3]` to values `[...]`, positive inside the solid.
      lo, hi: `[3]` corners of a box holding the solid with some margin.
      spacing: grid step.
    """
    from skimage.measure import marching_cubes

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.arange(lo[k], hi[k] + spacing, spacing) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = field(grid)
    # A border of "outside" guarantees the level set closes inside the grid.
    values = np.pad(values, 1, constant_values=-1.0)
    if values.max() <= 0:
        raise _Reject("field has no interior")
    v, f, _, _ = marching_cubes(values, level=0.0, spacing=(spacing,) * 3, allow_degenerate=False)
    v = v.astype(np.float64) + lo - spacing
    return v, _orient_outward(v, f.astype(np.int64))


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (Quilez): blends two distance fields over width `k`."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _torus_sdf(p: np.ndarray, big_r: float, small_r: float) -> np.ndarray:
    q = np.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2) - big_r
    return np.sqrt(q**2 + p[..., 2] ** 2) - small_r


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _star_polygon(rng: np.random.Generator, n: int) -> np.ndarray:
    angles = 2 * np.pi * (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / n
    radii = rng.uniform(0.45, 1.0, n)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1)


@functools.lru_cache(maxsize=2)
def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(s.vertices, dtype=np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.asarray(s.faces, dtype=np.int64)
