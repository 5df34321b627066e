"""Procedural shape categories: the project's stand-in for ShapeNet.

Every shape is a pure function of `(category, seed, instance)`: its parameters come from
`np.random.default_rng([seed, crc32(category), instance, attempt, stream])`, so the same
triple gives the same mesh whatever process builds it, in whatever order. (Bit-identical
results additionally need the same NumPy, manifold3d and pymeshlab builds and the same CPU
floating-point paths; the dataset manifest stores a hash of every mesh so a rebuild can be
checked.)

A shape is built in three steps:

1. a *base* surface, fine enough that its facets are invisible at the final resolution:
   CSG with manifold3d (CAD parts, revolved profiles), explicit parametric grids (tubes,
   tori, height fields, star-shaped surfaces) or marching cubes of a smooth field
   (metaballs, genus-n shapes);
2. pymeshlab isotropic remeshing (`meshing_isotropic_explicit_remeshing`) to a vertex
   count drawn in `[min_vertices, max_vertices]`, with the target edge length computed from
   the area and corrected for a few rounds until the count lands in range. Edges whose
   dihedral angle exceeds the category's feature angle are kept as creases, so CAD parts
   keep their sharp edges;
3. cleaning and checking (no duplicate or unreferenced vertices, no duplicate or
   degenerate faces, one connected component, consistent winding, edge- and vertex-manifold,
   watertight and outward-oriented for closed categories). A shape that fails any check is
   redrawn with the next `attempt` number, so failures are deterministic too.

The result is centred on its bounding box and scaled so its longest side is 1. No random
rotation is applied: rotation augmentation belongs to the input pipeline.

All categories are closed (watertight, outward-oriented, genus fixed by construction where
stated) except `terrain`, which is an open height-field patch with one boundary loop:
real scans have open boundaries (lion, camel) and the network should see some.
"""

from __future__ import annotations

import functools
import zlib
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from dmd_jax.mesh import canonical_frame, validate_mesh

GENERATOR_VERSION = 1


class _Reject(Exception):
    """A drawn shape is unusable (split apart, self-touching, ...); draw the next attempt."""


class CategoryInfo(NamedTuple):
    """What a category promises.

    Attributes:
      name: category name (an entry of `CATEGORIES`).
      closed: watertight, outward-oriented surface; `False` means an open patch.
      feature_angle: dihedral angle in degrees above which remeshing keeps an edge as a
        crease (90 for categories without creases).
      genus: the genus every shape of the category has, or `None` when it varies.
      description: one line.
    """

    name: str
    closed: bool
    feature_angle: float
    genus: int | None
    description: str


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


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _orient_outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Flips all faces of a consistently wound closed surface if it encloses negative volume."""
    return f[:, ::-1].copy() if _signed_volume(v, f) < 0 else f


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


@functools.lru_cache(maxsize=2)
def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(s.vertices, dtype=np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.asarray(s.faces, dtype=np.int64)


# --------------------------------------------------------------------------------------
# Category builders: rng -> base (vertices, faces)
# --------------------------------------------------------------------------------------


def _build_blocks(rng: np.random.Generator):
    """Unions of boxes with pockets, notches and drilled holes.

    Sizes and positions snap to a 1/40 grid, as drawn CAD parts do: faces are then either
    exactly flush or at least a grid step apart, never a sliver apart.
    """

    def snap(x):
        return np.round(np.asarray(x) * 40.0) / 40.0

    dims = snap(rng.uniform(0.5, 1.0, 3))
    parts = [_box(dims)]
    for _ in range(rng.integers(1, 4)):
        axis = rng.integers(3)
        size = snap(dims * rng.uniform(0.3, 0.7, 3))
        centre = rng.uniform(-0.5, 0.5, 3) * (dims - size)
        centre[axis] = rng.choice([-1.0, 1.0]) * (
            dims[axis] / 2 + size[axis] * rng.uniform(0.1, 0.4)
        )
        parts.append(_box(size, snap(centre)))
    body = _union(parts)
    cuts = []
    for _ in range(rng.integers(1, 4)):
        axis = rng.integers(3)
        size = snap(dims * rng.uniform(0.2, 0.45, 3))
        centre = rng.uniform(-0.5, 0.5, 3) * (dims - size)
        centre[axis] = rng.choice([-1.0, 1.0]) * dims[axis] / 2
        cuts.append(_box(size, snap(centre)))
    for _ in range(rng.integers(0, 3)):
        axis = rng.integers(3)
        radius = snap(rng.uniform(0.07, 0.14) * dims.min()) + 0.0125
        centre = snap(rng.uniform(-0.3, 0.3, 3) * dims)
        cuts.append(_cylinder(4.0, radius, axis=axis, center=centre))
    return _arrays(_one_piece(body - _union(cuts)))


def _build_bracket(rng: np.random.Generator):
    """L-brackets with optional gussets, rounded ends, holes and slots."""
    m = _manifold()
    width = rng.uniform(0.4, 0.9)
    t = rng.uniform(0.06, 0.14)
    l1, l2 = rng.uniform(0.7, 1.3), rng.uniform(0.5, 1.2)
    base = _box((l1, width, t), (l1 / 2, 0.0, t / 2))
    wall = _box((t, width, l2), (t / 2, 0.0, l2 / 2))
    parts = [base, wall]
    if rng.random() < 0.5:
        end = m.Manifold.cylinder(t, width / 2, -1.0, _HOLE_SEGMENTS, False).translate((l1, 0, 0))
        parts.append(end)
    if rng.random() < 0.6:
        g = rng.uniform(0.3, 0.7) * min(l1, l2)
        tri = _cross_section([[t * 0.5, t * 0.5], [t + g, t * 0.5], [t * 0.5, t + g]])
        gt = rng.uniform(0.5, 1.0) * t
        gusset = m.Manifold.extrude(tri, gt).rotate((90.0, 0.0, 0.0))
        offsets = [0.0] if rng.random() < 0.5 else [-(width - gt) / 2 * 0.9, (width - gt) / 2 * 0.9]
        for y in offsets:
            parts.append(gusset.translate((0.0, y + gt / 2, 0.0)))
    body = _union(parts)
    cuts = []
    r_max = min(width * 0.18, 0.12)
    for plate_axis, length in ((2, l1), (0, l2)):
        for _ in range(rng.integers(1, 4)):
            r = rng.uniform(0.35, 1.0) * r_max
            along = rng.uniform(t + 2 * r + 0.05, max(length - r, t + 2 * r + 0.06))
            y = rng.uniform(-1, 1) * (width / 2 - 1.8 * r)
            centre = (along, y, 0.0) if plate_axis == 2 else (0.0, y, along)
            if rng.random() < 0.25:
                # A slot: the hull of two holes a little apart.
                shift = np.array([0.0, rng.uniform(1.5, 3.0) * r * np.sign(-y or 1.0), 0.0])
                a = _cylinder(1.0, r, axis=plate_axis, center=centre)
                b = _cylinder(1.0, r, axis=plate_axis, center=np.add(centre, shift))
                cuts.append(m.Manifold.batch_hull([a, b]))
            else:
                cuts.append(_cylinder(1.0, r, axis=plate_axis, center=centre))
    return _arrays(_one_piece(body - _union(cuts)))


def _star_polygon(rng: np.random.Generator, n: int) -> np.ndarray:
    angles = 2 * np.pi * (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / n
    radii = rng.uniform(0.45, 1.0, n)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1)


def _build_extrusion(rng: np.random.Generator):
    """Prisms of random star-shaped or rectilinear outlines, with holes, tapers, roundings."""
    m = _manifold()
    if rng.random() < 0.5:
        cs = _cross_section(_star_polygon(rng, int(rng.integers(3, 12))))
    else:
        cs = m.CrossSection()
        for _ in range(rng.integers(2, 5)):
            w, h = rng.uniform(0.3, 1.2, 2)
            x, y = rng.uniform(-0.4, 0.4, 2)
            cs = cs + m.CrossSection.square((w, h), True).translate((x, y))
    if rng.random() < 0.35:
        r = rng.uniform(0.05, 0.15)
        cs = cs.offset(-r, m.JoinType.Round, 2.0, 64).offset(r, m.JoinType.Round, 2.0, 64)
    if rng.random() < 0.5:
        inner = cs.offset(-rng.uniform(0.12, 0.25), m.JoinType.Miter, 2.0, 64)
        if inner.area() > 0.02 * cs.area():
            cs = cs - inner
    elif rng.random() < 0.5:
        (x0, y0), (x1, y1) = np.asarray(cs.bounds()).reshape(2, 2)
        hole = m.CrossSection.circle(rng.uniform(0.08, 0.2), _HOLE_SEGMENTS)
        hole = hole.translate(((x0 + x1) / 2, (y0 + y1) / 2))
        if (cs - hole).area() < cs.area() - hole.area() * 0.999:
            cs = cs - hole
    if cs.is_empty():
        raise _Reject("empty outline")
    height = rng.uniform(0.15, 1.2)
    scale_top = (1.0, 1.0) if rng.random() < 0.7 else (rng.uniform(0.6, 0.95),) * 2
    return _arrays(_one_piece(m.Manifold.extrude(cs, height, 0, 0.0, scale_top)))


def _build_gear(rng: np.random.Generator):
    """Spur gears: trapezoidal teeth, bore with optional keyway, hub and lightening holes."""
    m = _manifold()
    n_teeth = int(rng.integers(8, 33))
    pitch = 2 * np.pi / n_teeth
    module = 2.0 / n_teeth
    r_tip, r_root = 1.0 + module, 1.0 - 1.25 * module
    base_half, tip_half = rng.uniform(0.22, 0.3) * pitch, rng.uniform(0.08, 0.16) * pitch
    pts = []
    for i in range(n_teeth):
        c = i * pitch
        for angle, r in (
            (c - base_half, r_root),
            (c - tip_half, r_tip),
            (c + tip_half, r_tip),
            (c + base_half, r_root),
        ):
            pts.append((r * np.cos(angle), r * np.sin(angle)))
    thickness = rng.uniform(0.15, 0.5)
    gear = m.Manifold.extrude(_cross_section(pts), thickness).translate((0, 0, -thickness / 2))
    bore = rng.uniform(0.12, 0.3)
    hub_r = min(bore + rng.uniform(0.12, 0.3), 0.7 * r_root)
    parts = [gear]
    if rng.random() < 0.6:
        hub_h = thickness + rng.uniform(0.1, 0.5)
        parts.append(_cylinder(hub_h, hub_r, center=(0, 0, (hub_h - thickness) / 2)))
    body = _union(parts)
    cuts = [_cylinder(4.0, bore)]
    if rng.random() < 0.5:
        key_w = bore * rng.uniform(0.4, 0.6)
        cuts.append(_box((key_w, bore * 0.7, 4.0), (0.0, bore, 0.0)))
    if rng.random() < 0.5 and r_root - hub_r > 0.25:
        # Recessed web on both faces, optionally with lightening holes.
        depth = thickness * rng.uniform(0.15, 0.3)
        rim = r_root - rng.uniform(0.06, 0.1)
        for sign in (-1.0, 1.0):
            ring = _cylinder(2 * depth, rim, center=(0, 0, sign * thickness / 2)) - _cylinder(
                4.0, hub_r + 0.03
            )
            cuts.append(ring)
        if rng.random() < 0.6:
            n_holes = int(rng.integers(3, 7))
            mid = (rim + hub_r) / 2
            r_hole = min((rim - hub_r) * 0.35, mid * np.sin(np.pi / n_holes) * 0.7)
            for k in range(n_holes):
                a = 2 * np.pi * k / n_holes
                cuts.append(_cylinder(4.0, r_hole, center=(mid * np.cos(a), mid * np.sin(a), 0)))
    return _arrays(_one_piece(body - _union(cuts)))


def _build_csg(rng: np.random.Generator):
    """Textbook CSG solids: intersections of boxes, spheres and cylinders minus drillings."""
    m = _manifold()
    kind = rng.integers(3)
    dims = rng.uniform(0.7, 1.0, 3)
    if kind == 0:
        # Box ∩ sphere − three orthogonal cylinders (the classic CSG tree).
        r = np.linalg.norm(dims) / 2 * rng.uniform(0.7, 0.9)
        body = _box(dims) ^ m.Manifold.sphere(r, _REVOLVE_SEGMENTS)
        rc = rng.uniform(0.18, 0.32) * dims.min()
        cuts = [_cylinder(4.0, rc, axis=a) for a in range(3) if rng.random() < 0.85]
    elif kind == 1:
        # Intersection of two or three cylinders (Steinmetz solids), drilled.
        r = dims.min() / 2
        body = _cylinder(4 * r, r, axis=0) ^ _cylinder(4 * r, r * rng.uniform(0.8, 1.2), axis=1)
        if rng.random() < 0.5:
            body = body ^ _cylinder(4 * r, r * rng.uniform(0.85, 1.2), axis=2)
        cuts = [_cylinder(4.0, r * rng.uniform(0.2, 0.4), axis=int(rng.integers(3)))]
    else:
        # A box or cylinder with a sphere or cylinder unioned on and a cavity cut out.
        body = _box(dims) if rng.random() < 0.5 else _cylinder(dims[2], dims[0] / 2)
        cap_r = rng.uniform(0.3, 0.45) * dims.min()
        top = (0.0, 0.0, dims[2] / 2)
        add = (
            m.Manifold.sphere(cap_r, _REVOLVE_SEGMENTS).translate(top)
            if rng.random() < 0.5
            else _cylinder(2 * cap_r, cap_r, axis=int(rng.integers(2)), center=top)
        )
        body = body + add
        cav = rng.uniform(0.15, 0.3) * dims.min()
        side = int(rng.integers(2))
        centre = np.zeros(3)
        centre[side] = dims[side] / 2
        cuts = [m.Manifold.sphere(cav, _REVOLVE_SEGMENTS).translate(tuple(centre))]
        if rng.random() < 0.6:
            cuts.append(_cylinder(4.0, cav * 0.6, axis=1 - side))
    body = body - _union(cuts) if cuts else body
    return _arrays(_one_piece(body))


def _build_fastener(rng: np.random.Generator):
    """Nuts (hex, square, octagonal; chamfered, flanged, countersunk) and bolts."""
    m = _manifold()
    sides = int(rng.choice([4, 6, 6, 6, 8]))
    big_r = 1.0
    height = rng.uniform(0.35, 0.9)
    prism = m.Manifold.extrude(m.CrossSection.circle(big_r, sides), height)
    flats = big_r * np.cos(np.pi / sides)
    ch = rng.uniform(0.85, 0.98) * flats
    dz = (big_r * 1.02 - ch) * np.tan(np.radians(30.0))
    both = rng.random() < 0.6
    profile = [(0.0, 0.0), (ch if both else big_r * 1.02, 0.0)]
    if both:
        profile.append((big_r * 1.02, dz))
    profile += [(big_r * 1.02, height - dz), (ch, height), (0.0, height)]
    body = prism ^ _revolve(profile)
    bolt = rng.random() < 0.3
    parts = [body]
    if rng.random() < 0.3:
        # A washer flange under the head.
        fl = height * rng.uniform(0.12, 0.2)
        parts.append(_cylinder(fl, big_r * rng.uniform(1.1, 1.3), center=(0, 0, fl / 2)))
    if bolt:
        shaft_r = flats * rng.uniform(0.4, 0.6)
        length = rng.uniform(1.5, 3.5)
        tip = shaft_r * 0.15
        shaft = _revolve(
            [
                (0.0, 0.0),
                (shaft_r, 0.0),
                (shaft_r, length - tip),
                (shaft_r - tip, length),
                (0, length),
            ]
        ).mirror((0.0, 0.0, 1.0))
        parts.append(shaft.translate((0.0, 0.0, 0.01)))
    body = _union(parts)
    if not bolt:
        bore = flats * rng.uniform(0.4, 0.6)
        cuts = [_cylinder(4.0, bore)]
        if rng.random() < 0.4:
            c = bore * rng.uniform(0.15, 0.3)
            cuts.append(
                _revolve(
                    [
                        (0, height - c),
                        (bore, height - c),
                        (bore + c, height + 0.01),
                        (0, height + 0.01),
                    ]
                )
            )
        body = body - _union(cuts)
    return _arrays(_one_piece(body))


def _build_flange(rng: np.random.Generator):
    """Revolved stepped parts (flanges, shafts, pulleys) with chamfers and bolt circles."""
    n_steps = int(rng.integers(2, 5))
    bore = rng.uniform(0.08, 0.25) if rng.random() < 0.8 else 0.0
    # Neighbouring steps differ by a clear shoulder: a sliver of a shoulder would be two
    # creases closer than an edge length.
    for _ in range(100):
        radii = rng.uniform(bore + 0.15, 1.0, n_steps)
        radii[rng.integers(n_steps)] = 1.0
        if np.all(np.abs(np.diff(radii)) >= 0.1):
            break
    else:
        raise _Reject("no step radii with clear shoulders")
    heights = rng.uniform(0.1, 0.5, n_steps)
    z = np.concatenate([[0.0], np.cumsum(heights)])
    cham = rng.uniform(0.03, 0.07) if rng.random() < 0.6 else 0.0
    pts = [(bore, z[0])]
    for k in range(n_steps):
        r = radii[k]
        c = min(cham, heights[k] / 3, (r - bore) / 3)
        pts += [(r - c, z[k]), (r, z[k] + c), (r, z[k + 1] - c), (r - c, z[k + 1])]
    pts.append((bore, z[-1]))
    # Consecutive steps share their corners' heights; dedupe coincident points.
    pts = np.array(pts)
    keep = np.ones(len(pts), bool)
    keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9
    body = _revolve(pts[keep])
    cuts = []
    big = int(np.argmax(radii))
    inner = max(
        bore, radii[big - 1] if big > 0 else 0.0, radii[big + 1] if big + 1 < n_steps else 0.0
    )
    if rng.random() < 0.7 and radii[big] - inner > 0.2:
        n_holes = int(rng.choice([3, 4, 5, 6, 8]))
        ring = (radii[big] + inner) / 2
        r_hole = min((radii[big] - inner) * 0.3, ring * np.sin(np.pi / n_holes) * 0.6)
        for k in range(n_holes):
            a = 2 * np.pi * k / n_holes
            cuts.append(_cylinder(4.0, r_hole, center=(ring * np.cos(a), ring * np.sin(a), 0)))
    if cuts:
        body = body - _union(cuts)
    return _arrays(_one_piece(body))


def _smooth_profile(
    rng: np.random.Generator, heights: np.ndarray, lo: float, hi: float
) -> np.ndarray:
    """A smooth positive radius profile through random control radii (PCHIP: no overshoot)."""
    from scipy.interpolate import PchipInterpolator

    k = int(rng.integers(4, 8))
    knots = np.linspace(heights[0], heights[-1], k)
    return PchipInterpolator(knots, rng.uniform(lo, hi, k))(heights)


def _flute(man, rng: np.random.Generator):
    """Radial fluting r -> r (1 + a sin(k θ)) on a solid of revolution."""
    k = int(rng.integers(6, 17))
    a = rng.uniform(0.02, 0.06)

    def warp(p):
        theta = np.arctan2(p[:, 1], p[:, 0])
        s = 1.0 + a * np.sin(k * theta)
        out = np.array(p, dtype=np.float64, copy=True)
        out[:, 0] *= s
        out[:, 1] *= s
        return out

    return man.warp_batch(warp)


def _build_vase(rng: np.random.Generator):
    """Solid or hollow vases of a smooth random profile, optionally fluted."""
    height = rng.uniform(1.2, 2.5)
    z = np.linspace(0.0, height, 96)
    r = _smooth_profile(rng, z, 0.25, 0.75)
    if rng.random() < 0.4:
        pts = [(0.0, 0.0)] + list(zip(r, z, strict=True)) + [(0.0, height)]
    else:
        wall = rng.uniform(0.05, 0.1)
        floor = rng.uniform(0.05, 0.15)
        inner = r - wall
        zi = z >= floor
        if inner[zi].min() < 0.05:
            raise _Reject("vase too narrow for its wall")
        outer = list(zip(r, z, strict=True))
        rim = []
        if rng.random() < 0.5:
            # Rounded lip: a half circle from the outer to the inner wall.
            phi = np.linspace(0.0, np.pi, 12)[1:-1]
            cx = r[-1] - wall / 2
            rim = list(
                zip(cx + wall / 2 * np.cos(phi), height + wall / 2 * np.sin(phi), strict=True)
            )
        inside = list(zip(inner[zi][::-1], z[zi][::-1], strict=True))
        pts = [(0.0, 0.0)] + outer + rim + inside + [(0.0, z[zi][0])]
    body = _revolve(pts)
    if rng.random() < 0.3:
        body = _flute(body, rng)
    return _arrays(_one_piece(body))


def _build_cup(rng: np.random.Generator):
    """Thick-walled cups and mugs, rounded bottom edge, with or without a handle."""
    m = _manifold()
    handle = rng.random() < 0.7
    r_bot = rng.uniform(0.5, 0.8)
    wall = rng.uniform(0.04, 0.09)
    # A handle needs a wall that stays thick along its span, so handled cups taper less.
    r_top = r_bot + (rng.uniform(0.0, 0.8) * wall if handle else r_bot * rng.uniform(0.0, 0.35))
    height = rng.uniform(0.7, 1.6)
    floor = rng.uniform(0.05, 0.12)
    fillet = rng.uniform(0.05, 0.15)
    phi = np.linspace(-np.pi / 2, 0.0, 10)
    corner = list(
        zip(r_bot - fillet + fillet * np.cos(phi), fillet + fillet * np.sin(phi), strict=True)
    )
    z = np.linspace(fillet, height, 40)[1:]
    outer_r = r_bot + (r_top - r_bot) * z / height
    pts = [(0.0, 0.0)] + corner + list(zip(outer_r, z, strict=True))
    pts += [
        (r_top - wall, height),
        (r_bot + (r_top - r_bot) * floor / height - wall, floor),
        (0.0, floor),
    ]
    body = _revolve(pts)
    if handle:
        z0, z1 = height * rng.uniform(0.15, 0.3), height * rng.uniform(0.7, 0.85)
        hr = (z1 - z0) / 2
        thick = rng.uniform(0.06, 0.1)
        ring = m.Manifold.revolve(
            m.CrossSection.circle(thick, 32)
            .scale((1.0, rng.uniform(1.0, 1.6)))
            .translate((hr, 0.0)),
            64,
        )
        # Torus in the xz plane, centred where the handle meets the wall.
        zc = (z0 + z1) / 2
        rc = r_bot + (r_top - r_bot) * zc / height
        ring = ring.rotate((90.0, 0.0, 0.0)).translate((rc, 0.0, zc))
        r_in_max = r_bot + (r_top - r_bot) * z1 / height - wall
        r_out_min = r_bot + (r_top - r_bot) * z0 / height
        cut = r_in_max + 0.3 * wall
        if cut >= r_out_min:
            raise _Reject("cup too tapered for a handle")
        handle = ring ^ _box((4.0, 4.0, 4.0), (cut + 2.0, 0.0, 0.0))
        body = body + handle
        return (*_arrays(_one_piece(body)), 1)
    return (*_arrays(_one_piece(body)), 0)


def _build_bottle(rng: np.random.Generator):
    """Closed bottles: rounded base, waisted body, smooth shoulder, neck and lip."""
    r_body = 1.0
    h_body = rng.uniform(1.5, 3.5)
    r_neck = rng.uniform(0.22, 0.45)
    h_shoulder = rng.uniform(0.3, 1.0)
    h_neck = rng.uniform(0.3, 1.0)
    fillet = rng.uniform(0.05, 0.25)
    waist = rng.uniform(0.0, 0.12) if rng.random() < 0.5 else 0.0
    wz, ww = rng.uniform(0.3, 0.7) * h_body, rng.uniform(0.1, 0.3) * h_body
    phi = np.linspace(-np.pi / 2, 0.0, 10)
    pts = [(0.0, 0.0)] + list(
        zip(r_body - fillet + fillet * np.cos(phi), fillet + fillet * np.sin(phi), strict=True)
    )
    z = np.linspace(fillet, h_body, 48)[1:]
    pts += list(zip(r_body * (1 - waist * np.exp(-(((z - wz) / ww) ** 2))), z, strict=True))
    s = np.linspace(0.0, 1.0, 24)[1:]
    pts += list(
        zip(
            r_neck + (r_body - r_neck) * 0.5 * (1 + np.cos(np.pi * s)),
            h_body + h_shoulder * s,
            strict=True,
        )
    )
    top = h_body + h_shoulder + h_neck
    lip_h = rng.uniform(0.05, 0.15)
    lip_r = r_neck + rng.uniform(0.03, 0.1)
    pts += [
        (r_neck, top - 2 * lip_h),
        (lip_r, top - 1.6 * lip_h),
        (lip_r, top - 0.4 * lip_h),
        (r_neck, top),
        (0.0, top),
    ]
    return _arrays(_one_piece(_revolve(pts)))


def _build_blob(rng: np.random.Generator):
    """Star-shaped smooth blobs: an icosphere displaced by random Fourier features."""
    d, f = _unit_icosphere(5)
    k = int(rng.integers(4, 12))
    omega = rng.normal(size=(k, 3)) * rng.uniform(0.8, 2.5, (k, 1))
    phase = rng.uniform(0, 2 * np.pi, k)
    amp = rng.normal(size=k) / np.linalg.norm(omega, axis=1) * rng.uniform(0.2, 0.6)
    log_r = np.sin(d @ omega.T + phase) @ amp
    v = d * np.exp(log_r)[:, None] * rng.uniform(0.6, 1.0, 3)
    return v, f


def _build_metaballs(rng: np.random.Generator):
    """Smooth unions of anisotropic Gaussian kernels chained into one body."""
    n = int(rng.integers(3, 8))
    centres, inv_cov, weights = [np.zeros(3)], [], []
    for i in range(n):
        rot = _random_rotation(rng)
        scales = rng.uniform(0.18, 0.45, 3)
        inv_cov.append(rot @ np.diag(1.0 / scales**2) @ rot.T)
        weights.append(rng.uniform(0.8, 1.2))
        if i + 1 < n:
            parent = centres[rng.integers(len(centres))]
            step = rng.normal(size=3)
            centres.append(parent + step / np.linalg.norm(step) * rng.uniform(0.45, 0.8))
    centres = np.array(centres)
    iso = rng.uniform(0.25, 0.45)

    def field(p):
        total = np.zeros(p.shape[:-1])
        for c, a, w in zip(centres, inv_cov, weights, strict=True):
            q = p - c
            total += w * np.exp(-0.5 * np.einsum("...i,ij,...j->...", q, a, q))
        return total - iso

    lo, hi = centres.min(0) - 1.3, centres.max(0) + 1.3
    v, f = _marching_cubes(field, lo, hi, float((hi - lo).max() / 80))
    return v, f


def _build_torus(rng: np.random.Generator):
    """Tori with elliptic, wavy or varying cross-sections, and torus knots."""
    if rng.random() < 0.3:
        p, q = [(2, 3), (3, 2), (2, 5)][rng.integers(3)]
        rho = rng.uniform(0.35, 0.5)
        u = 2 * np.pi * np.arange(512) / 512  # knots wind several times: twice the samples
        curve = np.stack(
            [
                (1 + rho * np.cos(q * u)) * np.cos(p * u),
                (1 + rho * np.cos(q * u)) * np.sin(p * u),
                rho * np.sin(q * u),
            ],
            1,
        )
        radius = np.full(u.size, rng.uniform(0.1, 0.17))
        aspect = 1.0
    else:
        u = 2 * np.pi * np.arange(256) / 256
        a, b = 1.0, rng.uniform(0.6, 1.0)
        wave = rng.uniform(0.0, 0.25) if rng.random() < 0.5 else 0.0
        kz = int(rng.integers(2, 5))
        curve = np.stack([a * np.cos(u), b * np.sin(u), wave * np.sin(kz * u)], 1)
        r0 = rng.uniform(0.15, 0.4) * b
        mod = rng.uniform(0.0, 0.4) if rng.random() < 0.5 else 0.0
        radius = r0 * (1 + mod * np.sin(int(rng.integers(1, 4)) * u + rng.uniform(0, 2 * np.pi)))
        aspect = rng.uniform(0.6, 1.4) if rng.random() < 0.5 else 1.0
    _check_tube_clearance(curve, radius * max(aspect, 1.0), closed=True)
    return _sweep_tube(curve, radius, closed=True, n_around=64, aspect=aspect)


def _build_genus(rng: np.random.Generator):
    """Smooth genus-n solids: chains or rings of blended tori, or slabs with n holes."""
    g = int(rng.integers(2, 6))
    kind = rng.integers(2)
    if kind == 0:
        big_r, small_r = 1.0, rng.uniform(0.25, 0.4)
        spacing = 2 * big_r * rng.uniform(0.8, 0.95)
        blend = rng.uniform(0.05, 0.2)
        ring = rng.random() < 0.4 and g >= 3
        if ring:
            rad = spacing / (2 * np.sin(np.pi / g))
            centres = np.array(
                [
                    (rad * np.cos(2 * np.pi * k / g), rad * np.sin(2 * np.pi * k / g), 0)
                    for k in range(g)
                ]
            )
        else:
            centres = np.array([(k * spacing, 0.0, 0.0) for k in range(g)])

        def sdf(p):
            d = _torus_sdf(p - centres[0], big_r, small_r)
            for c in centres[1:]:
                d = _smooth_min(d, _torus_sdf(p - c, big_r, small_r), blend)
            return d

        lo, hi = centres.min(0) - big_r - small_r - 0.2, centres.max(0) + big_r + small_r + 0.2
        res = 110
    else:
        half = np.array([rng.uniform(1.0, 2.0), rng.uniform(0.7, 1.2), rng.uniform(0.12, 0.3)])
        round_r = half[2] * rng.uniform(0.5, 0.95)
        holes = []
        for _ in range(200):
            if len(holes) == g:
                break
            r = rng.uniform(0.18, 0.4)
            c = rng.uniform(-1, 1, 2) * (half[:2] - r - 0.15)
            if all(np.linalg.norm(c - h[:2]) > r + h[2] + 0.12 for h in holes):
                holes.append((c[0], c[1], r))
        if len(holes) != g:
            raise _Reject("could not place the holes")
        holes = np.array(holes)
        blend = round_r * 0.5

        def sdf(p):
            q = np.abs(p) - (half - round_r)
            box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - round_r
            d = box
            for x, y, r in holes:
                cyl = np.sqrt((p[..., 0] - x) ** 2 + (p[..., 1] - y) ** 2) - r
                d = -_smooth_min(-d, cyl, blend)
            return d

        lo, hi = -half - 0.2, half + 0.2
        res = 120
    v, f = _marching_cubes(lambda p: -sdf(p), lo, hi, float((hi - lo).max() / res))
    return v, f, g


def _build_superquadric(rng: np.random.Generator):
    """Superellipsoids with random exponents, tapered or bent (Barr's deformations)."""
    d, f = _unit_icosphere(5)
    e1, e2 = rng.uniform(0.3, 2.0, 2)
    axes = rng.uniform(0.5, 1.0, 3)
    # Radial scale that puts direction d on the surface
    # (|x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1) + |z/c|^(2/e1) = 1.
    x, y, z = np.abs(d / axes).T
    with np.errstate(divide="ignore"):
        g = (x ** (2 / e2) + y ** (2 / e2)) ** (e2 / e1) + z ** (2 / e1)
    v = d * (g ** (-e1 / 2))[:, None]
    if rng.random() < 0.4:
        taper = rng.uniform(-0.6, 0.6, 2)
        zz = v[:, 2] / axes[2]
        v[:, 0] *= 1 + taper[0] * zz
        v[:, 1] *= 1 + taper[1] * zz
    if rng.random() < 0.3:
        k = rng.uniform(0.2, 0.6)  # curvature of the bend, in 1/length
        rb = 1.0 / k
        ang = v[:, 2] / rb
        v = np.stack([rb - (rb - v[:, 0]) * np.cos(ang), v[:, 1], (rb - v[:, 0]) * np.sin(ang)], 1)
    return v, f


def _height_field(rng: np.random.Generator, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bumps, ridges, smooth cliffs and low-frequency waves on `[-1, 1]^2`."""
    h = np.zeros_like(x)
    for _ in range(rng.integers(3, 12)):
        c = rng.uniform(-1, 1, 2)
        w = rng.uniform(0.08, 0.35)
        h += rng.uniform(-1, 1) * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / (2 * w**2))
    for _ in range(rng.integers(0, 3)):
        a = rng.uniform(0, np.pi)
        dist = np.cos(a) * x + np.sin(a) * y - rng.uniform(-0.6, 0.6)
        h += rng.uniform(-0.6, 0.6) * np.exp(-(dist**2) / (2 * rng.uniform(0.03, 0.1) ** 2))
    if rng.random() < 0.4:
        a = rng.uniform(0, 2 * np.pi)
        dist = np.cos(a) * x + np.sin(a) * y - rng.uniform(-0.5, 0.5)
        h += rng.uniform(0.3, 0.7) * np.tanh(dist / rng.uniform(0.03, 0.08))
    for _ in range(rng.integers(1, 4)):
        k = rng.normal(size=2) * 3
        h += (
            0.15
            * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 2 * np.pi))
            / (1 + np.linalg.norm(k) / 3)
        )
    span = h.max() - h.min()
    return (h - h.min()) / max(span, 1e-9)


def _square_to_disc(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smooth map of `[-1, 1]^2` onto the unit disc (elliptical grid mapping)."""
    return x * np.sqrt(1 - y**2 / 2), y * np.sqrt(1 - x**2 / 2)


def _build_relief(rng: np.random.Generator):
    """Closed slabs whose top is a random height field (bas-relief plates)."""
    n = 129
    s = np.linspace(-1.0, 1.0, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    aspect = rng.uniform(0.5, 1.0)
    amp = rng.uniform(0.08, 0.35)
    base = rng.uniform(0.08, 0.25)
    top_z = base + amp * _height_field(rng, x, y)
    xs, ys = x.ravel(), (y * aspect).ravel()
    top = np.stack([xs, ys, top_z.ravel()], 1)
    bottom = np.stack([xs, ys, np.zeros(n * n)], 1)
    v = np.concatenate([top, bottom])
    f_top = _grid_faces(n, n, wrap_rows=False, wrap_cols=False)
    f_bot = (f_top + n * n)[:, ::-1]
    # Boundary loop counter-clockwise seen from +z; walls (b_k, b_k+1, t_k+1), (b_k, t_k+1, t_k).
    i = np.arange(n - 1)
    loop = np.concatenate([i * n, (n - 1) * n + i, (n - 1 - i) * n + (n - 1), n - 1 - i])
    nxt = np.roll(loop, -1)
    bl, bn = loop + n * n, nxt + n * n
    walls = np.concatenate([np.stack([bl, bn, nxt], 1), np.stack([bl, nxt, loop], 1)])
    f = np.concatenate([f_top, f_bot, walls])
    return v, _orient_outward(v, f)


def _build_terrain(rng: np.random.Generator):
    """Open height-field patches (square or round): the one category with a boundary."""
    n = 129
    s = np.linspace(-1.0, 1.0, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    if rng.random() < 0.4:
        x, y = _square_to_disc(x, y)
    else:
        y = y * rng.uniform(0.5, 1.0)
    z = rng.uniform(0.1, 0.5) * _height_field(rng, x, y)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    return v, _grid_faces(n, n, wrap_rows=False, wrap_cols=False)


def _resample_outline(outline: np.ndarray, spacing: float) -> np.ndarray:
    """Inserts points along a closed polygon `[k, 2]` so no edge exceeds `spacing`,
    keeping every corner."""
    nxt = np.roll(outline, -1, axis=0)
    pieces = []
    for a, b in zip(outline, nxt, strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        t = np.arange(n)[:, None] / n
        pieces.append(a + t * (b - a))
    return np.concatenate(pieces)


def _build_twisted_bar(rng: np.random.Generator):
    """Polygonal bars extruded with a twist and bent along an arc.

    Built directly rather than with manifold3d's extrude: the outline is resampled so the
    side quads are close to square, otherwise the long thin quads of a twisted prism fold
    by tens of degrees along their diagonals and read as spurious creases.
    """
    kind = rng.integers(4)
    if kind == 0:
        w = rng.uniform(1.5, 4.0) * 0.1
        outline = np.array([[-w, -0.1], [w, -0.1], [w, 0.1], [-w, 0.1]])
    elif kind == 1:
        k = int(rng.integers(3, 7))
        a = 2 * np.pi * np.arange(k) / k
        outline = 0.15 * np.stack([np.cos(a), np.sin(a)], 1)
    elif kind == 2:
        a, b = rng.uniform(0.1, 0.175), rng.uniform(0.025, 0.05)
        outline = np.array(
            [
                [b, -b],
                [a, -b],
                [a, b],
                [b, b],
                [b, a],
                [-b, a],
                [-b, b],
                [-a, b],
                [-a, -b],
                [-b, -b],
                [-b, -a],
                [b, -a],
            ]
        )
    else:
        outline = _star_polygon(rng, int(rng.integers(4, 7))) * 0.18
    length = rng.uniform(1.5, 3.0)
    twist = np.radians(rng.uniform(0.0, 360.0)) if rng.random() < 0.8 else 0.0
    n_levels = 241
    ring = _resample_outline(outline, length / (n_levels - 1))
    z = np.linspace(-length / 2, length / 2, n_levels)
    ang = twist * (z / length + 0.5)
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    x = c * ring[None, :, 0] - s * ring[None, :, 1]
    y = s * ring[None, :, 0] + c * ring[None, :, 1]
    v = np.stack([x, y, np.broadcast_to(z[:, None], x.shape)], -1).reshape(-1, 3)
    n_ring = ring.shape[0]
    f = _grid_faces(n_levels, n_ring, wrap_rows=False, wrap_cols=True)
    # Outlines are star-shaped about the origin, so the caps are fans from the axis.
    i0, i1 = v.shape[0], v.shape[0] + 1
    v = np.concatenate([v, [[0.0, 0.0, z[0]], [0.0, 0.0, z[-1]]]])
    j = np.arange(n_ring)
    jn = (j + 1) % n_ring
    last = (n_levels - 1) * n_ring
    f = np.concatenate(
        [
            f,
            np.stack([np.full(n_ring, i0), j, jn], 1),
            np.stack([np.full(n_ring, i1), last + jn, last + j], 1),
        ]
    )
    if rng.random() < 0.7:
        bend = np.radians(rng.uniform(30.0, 180.0))
        rb = length / bend
        a = v[:, 2] / rb
        v = np.stack([rb - (rb - v[:, 0]) * np.cos(a), v[:, 1], (rb - v[:, 0]) * np.sin(a)], 1)
    return v, _orient_outward(v, f)


def _build_tube(rng: np.random.Generator):
    """Tubes swept along random smooth space curves, with round or flat ends."""
    from scipy.interpolate import CubicSpline

    k = int(rng.integers(4, 8))
    steps = rng.normal(size=(k - 1, 3))
    steps /= np.linalg.norm(steps, axis=1, keepdims=True)
    # Limit turning so the curve wanders instead of folding back.
    for i in range(1, k - 1):
        if np.dot(steps[i], steps[i - 1]) < -0.2:
            steps[i] = -steps[i]
    ctrl = np.concatenate([[np.zeros(3)], np.cumsum(steps * rng.uniform(0.6, 1.0, (k - 1, 1)), 0)])
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ctrl, axis=0), axis=1))])
    spline = CubicSpline(chord, ctrl, bc_type="natural")
    s = np.linspace(0.0, chord[-1], 400)
    curve = spline(s)
    # Thin the tube where the curve bends hard instead of rejecting it.
    curvature = np.linalg.norm(np.cross(spline(s, 1), spline(s, 2)), axis=1) / np.maximum(
        np.linalg.norm(spline(s, 1), axis=1) ** 3, 1e-12
    )
    r0 = min(rng.uniform(0.08, 0.2), 0.5 / curvature.max())
    radius = np.full(s.size, r0)
    if rng.random() < 0.4:
        wave = rng.uniform(0.1, 0.3) * np.sin(2 * np.pi * s / chord[-1] * rng.uniform(1, 3))
        radius = r0 * (1 + wave)
    _check_tube_clearance(curve, radius, closed=False)
    caps = "round" if rng.random() < 0.6 else "flat"
    return _sweep_tube(curve, radius, closed=False, n_around=48, caps=caps)


class _Spec(NamedTuple):
    build: Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]
    info: CategoryInfo


def _spec(name, build, closed, feature_angle, genus, description) -> tuple[str, _Spec]:
    return name, _Spec(build, CategoryInfo(name, closed, feature_angle, genus, description))


_SPECS: dict[str, _Spec] = dict(
    [
        _spec("blocks", _build_blocks, True, 30.0, None, "unions of boxes with pockets and holes"),
        _spec("bracket", _build_bracket, True, 30.0, None, "L-brackets with gussets, holes, slots"),
        _spec("extrusion", _build_extrusion, True, 30.0, None, "prisms of random outlines"),
        _spec("gear", _build_gear, True, 30.0, None, "spur gears with bore, hub, keyway"),
        _spec("csg", _build_csg, True, 30.0, None, "box/sphere/cylinder CSG solids"),
        _spec("fastener", _build_fastener, True, 30.0, None, "chamfered nuts and bolts"),
        _spec("flange", _build_flange, True, 30.0, None, "revolved stepped parts, bolt circles"),
        _spec("vase", _build_vase, True, 30.0, 0, "solid or hollow vases, smooth profiles"),
        _spec("cup", _build_cup, True, 30.0, None, "thick-walled cups, with or without handle"),
        _spec("bottle", _build_bottle, True, 30.0, 0, "closed bottles with shoulder and neck"),
        _spec("blob", _build_blob, True, 90.0, 0, "star-shaped noise-displaced spheres"),
        _spec("metaballs", _build_metaballs, True, 90.0, None, "blended anisotropic Gaussians"),
        _spec("torus", _build_torus, True, 90.0, 1, "tori with varying sections, torus knots"),
        _spec("genus", _build_genus, True, 90.0, None, "smooth genus 2-5 solids"),
        _spec("superquadric", _build_superquadric, True, 90.0, 0, "tapered/bent superellipsoids"),
        _spec("relief", _build_relief, True, 30.0, 0, "closed slabs with a height-field top"),
        _spec("terrain", _build_terrain, False, 90.0, 0, "open height-field patches (boundary)"),
        _spec("twisted_bar", _build_twisted_bar, True, 30.0, 0, "twisted and bent polygonal bars"),
        _spec("tube", _build_tube, True, 30.0, 0, "tubes swept along space curves"),
    ]
)

CATEGORIES: tuple[str, ...] = tuple(_SPECS)


def category_info(category: str) -> CategoryInfo:
    """What `category` promises (closed or open, feature angle, genus)."""
    _check_category(category)
    return _SPECS[category].info


def _check_category(category: str) -> None:
    if category not in _SPECS:
        raise ValueError(f"unknown shape category {category!r}; known: {', '.join(CATEGORIES)}")


def category_key(category: str) -> int:
    """A stable integer for a category name (CRC-32), used to seed its random streams."""
    return zlib.crc32(category.encode("utf-8"))


# --------------------------------------------------------------------------------------
# Remeshing, cleaning, checking
# --------------------------------------------------------------------------------------


def _meshset(vertices: np.ndarray, faces: np.ndarray):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(
            vertex_matrix=np.ascontiguousarray(vertices, dtype=np.float64),
            face_matrix=np.ascontiguousarray(faces, dtype=np.int32),
        )
    )
    return ms


def _clean_meshset(ms) -> None:
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()


def _current(ms) -> tuple[np.ndarray, np.ndarray]:
    mesh = ms.current_mesh()
    return (
        np.asarray(mesh.vertex_matrix(), dtype=np.float64).copy(),
        np.asarray(mesh.face_matrix(), dtype=np.int64).copy(),
    )


def clean_mesh(vertices, faces, *, orient: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Removes duplicate vertices and faces, zero-area faces and unreferenced vertices.

    Args:
      vertices: `[n, 3]` coordinates.
      faces: `[f, 3]` vertex indices.
      orient: also make the winding consistent where the surface allows it (edge-manifold
        and orientable; otherwise the winding is left as it is), and turn a closed
        surface outward.

    Returns:
      `(vertices float64 [n', 3], faces int32 [f', 3])`.
    """
    import pymeshlab

    v, f = validate_mesh(vertices, faces)
    ms = _meshset(v, f)
    _clean_meshset(ms)
    if orient:
        try:
            ms.meshing_re_orient_faces_coherently()
        except pymeshlab.PyMeshLabException:
            pass  # non-manifold or non-orientable: no consistent winding exists
    v, f = _current(ms)
    if orient:
        d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        n = v.shape[0]
        directed = np.unique(d[:, 0] * n + d[:, 1]).size == d.shape[0]
        undirected = np.unique(np.sort(d, axis=1), axis=0, return_counts=True)[1]
        if directed and np.all(undirected == 2):
            f = _orient_outward(v, f)
    return validate_mesh(v, f)


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total surface area."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return float(
        0.5
        * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    )


def decimate(
    vertices: np.ndarray, faces: np.ndarray, n_faces: int
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh decimated to about `n_faces` faces (pymeshlab's quadric edge collapse,
    topology and boundary kept, normals not flipped), cleaned; as it is if it has at most
    `n_faces` faces.

    Returns:
      `(vertices [m, 3] float64, faces [k, 3] int32)`.
    """
    f = np.asarray(faces)
    if f.shape[0] <= n_faces:
        return np.asarray(vertices, np.float64), f.astype(np.int32)
    ms = _meshset(np.asarray(vertices, np.float64), f)
    _clean_meshset(ms)
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(n_faces),
        preserveboundary=True,
        preservenormal=True,
        preservetopology=True,
        planarquadric=True,
    )
    _clean_meshset(ms)
    v, f = _current(ms)
    return v, f.astype(np.int32)


def remesh(
    vertices,
    faces,
    *,
    min_vertices: int,
    max_vertices: int,
    target_vertices: int | None = None,
    feature_angle: float = 30.0,
    iterations: int = 8,
    max_rounds: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing to a vertex count in `[min_vertices, max_vertices]`.

    The target edge length `L` comes from the area `A` and the target count `T`: a
    closed mesh of equilateral triangles has about `2T` faces, so `A ≈ 2T·(√3/4)L²`.
    Input edges longer than `4L` are first split at their midpoints. When
    the result misses the range, `L` is rescaled by `sqrt(n / T)` and the original surface
    remeshed again, at most `max_rounds` times.

    Args:
      vertices: `[n, 3]` coordinates of the surface to resample.
      faces: `[f, 3]` vertex indices.
      min_vertices, max_vertices: the accepted vertex range.
      target_vertices: the count aimed at (default: geometric mean of the range).
      feature_angle: dihedral angle (degrees) above which an edge is kept as a crease.
      iterations: remeshing iterations per round.
      max_rounds: remeshing rounds before giving up.

    Returns:
      `(vertices float64 [n', 3], faces int32 [f', 3])`, cleaned.

    Raises:
      ValueError: bad range, or no round landed in range (the message gives the counts).
    """
    import pymeshlab

    if not 4 <= min_vertices <= max_vertices:
        raise ValueError(
            f"need 4 <= min_vertices <= max_vertices, got {min_vertices}, {max_vertices}"
        )
    if target_vertices is None:
        target_vertices = int(round(np.sqrt(min_vertices * max_vertices)))
    v0, f0 = validate_mesh(vertices, faces)
    area = mesh_area(v0, f0)
    if not area > 0:
        raise ValueError("cannot remesh a surface of zero area")
    length = np.sqrt(2.0 * area / (np.sqrt(3.0) * target_vertices))
    counts = []
    for _ in range(max_rounds):
        ms = _meshset(v0, f0)
        _clean_meshset(ms)
        try:
            # Long input edges are halved first (exactly, at their midpoints): otherwise
            # isotropic remeshing can leave long slivers untouched, e.g. the annular caps
            # that manifold3d's revolve triangulates as fans of needles.
            ms.meshing_surface_subdivision_midpoint(
                iterations=10, threshold=pymeshlab.PureValue(float(4.0 * length))
            )
        except pymeshlab.PyMeshLabException:
            pass  # non-manifold input (scanned or CAD-exported files): remesh it as it is
        try:
            ms.meshing_isotropic_explicit_remeshing(
                iterations=iterations,
                adaptive=False,
                targetlen=pymeshlab.PureValue(float(length)),
                featuredeg=float(feature_angle),
                # Reprojection already keeps vertices on the input surface; the extra
                # distance check costs 3x the time and changed the measured deviation by
                # < 0.05 edge lengths.
                checksurfdist=False,
            )
        except pymeshlab.PyMeshLabException as exc:
            raise ValueError(f"pymeshlab could not remesh the surface: {exc}") from exc
        _clean_meshset(ms)
        n = ms.current_mesh().vertex_number()
        counts.append(n)
        if min_vertices <= n <= max_vertices:
            v, f = _current(ms)
            return validate_mesh(v, f)
        length *= np.sqrt(n / target_vertices)
    raise ValueError(
        f"remeshing missed the vertex range [{min_vertices}, {max_vertices}] "
        f"(target {target_vertices}) in {max_rounds} rounds: got {counts}"
    )


def mesh_problems(vertices, faces, *, closed: bool, genus: int | None = None) -> list[str]:
    """What is wrong with a mesh as training data (an empty list when nothing is).

    Checks: no duplicate or unreferenced vertices, no duplicate faces, no degenerate faces
    (area below 1e-6 of the mean, an angle below 1°, or more than 1% of faces with an
    angle below 10°), one connected component, every
    edge in at most two faces, consistent winding, manifold vertices; for `closed`
    meshes also no boundary and positive enclosed volume; and the genus if given.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    problems = []
    if np.unique(v, axis=0).shape[0] != v.shape[0]:
        problems.append("duplicate vertices")
    if np.bincount(f.ravel(), minlength=v.shape[0]).min() == 0:
        problems.append("unreferenced vertices")
    if np.unique(np.sort(f, axis=1), axis=0).shape[0] != f.shape[0]:
        problems.append("duplicate faces")
    e1, e2, e3 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 1]], v[f[:, 0]] - v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(e1, -e3), axis=1)
    if area.min() < 1e-6 * area.mean():
        problems.append(f"degenerate faces (min area {area.min():.3g}, mean {area.mean():.3g})")
    lengths = np.stack([np.linalg.norm(e, axis=1) for e in (e1, e2, e3)], 1)
    # sin(smallest angle) = 2·area / (product of the two longer sides)
    srt = np.sort(lengths, axis=1)
    sin_min = 2 * area / np.maximum(srt[:, 1] * srt[:, 2], 1e-300)
    if sin_min.min() < np.sin(np.radians(1.0)):
        problems.append(f"sliver faces (min angle {np.degrees(np.arcsin(sin_min.min())):.3g}°)")
    if np.mean(sin_min < np.sin(np.radians(10.0))) > 0.01:
        problems.append("more than 1% of faces have an angle below 10°")
    # Directed edges: each must appear at most once (consistent winding, ≤ 2 faces per edge).
    n = v.shape[0]
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    dkey = d[:, 0] * n + d[:, 1]
    if np.unique(dkey).size != dkey.size:
        problems.append("inconsistent winding or non-manifold edges")
    u = np.sort(d, axis=1)
    _, ucount = np.unique(u[:, 0] * n + u[:, 1], return_counts=True)
    if ucount.max() > 2:
        problems.append("edges shared by more than two faces")
    boundary = int((ucount == 1).sum())
    if closed and boundary:
        problems.append(f"{boundary} boundary edges on a closed surface")
    ms = _meshset(v, f)
    topo = ms.get_topological_measures()
    if topo["non_two_manifold_vertices"]:
        problems.append(f"{topo['non_two_manifold_vertices']} non-manifold vertices")
    if topo["connected_components_number"] != 1:
        problems.append(f"{topo['connected_components_number']} connected components")
    if closed and not boundary and _signed_volume(v, f) <= 0:
        problems.append("closed surface is oriented inwards")
    if genus is not None and topo["genus"] != genus:
        problems.append(f"genus {topo['genus']}, expected {genus}")
    return problems


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------

MAX_ATTEMPTS = 12


def _target_vertices(rng: np.random.Generator, min_vertices: int, max_vertices: int) -> int:
    """A target count drawn log-uniformly from the inner part of the range."""
    lo, hi = min_vertices * 1.1, max_vertices / 1.1
    if lo >= hi:
        return int(round(np.sqrt(min_vertices * max_vertices)))
    return int(round(np.exp(rng.uniform(np.log(lo), np.log(hi)))))


def generate_shape(
    category: str,
    seed: int,
    instance: int,
    *,
    min_vertices: int = 1000,
    max_vertices: int = 6000,
) -> tuple[np.ndarray, np.ndarray]:
    """One procedural shape, remeshed, cleaned and in the canonical frame.

    Args:
      category: an entry of `CATEGORIES`.
      seed: dataset seed (non-negative integer).
      instance: instance number within the category (non-negative integer).
      min_vertices, max_vertices: the vertex count lands in this range.

    Returns:
      `(vertices float64 [n, 3], faces int32 [f, 3])`, centred on the bounding box with
      longest side 1; closed and outward-oriented unless `category_info(category).closed`
      is `False`.

    Raises:
      ValueError: unknown category, negative seed or instance, bad vertex range.
      RuntimeError: no valid mesh after `MAX_ATTEMPTS` draws (the message says why).
    """
    _check_category(category)
    if int(seed) != seed or seed < 0 or int(instance) != instance or instance < 0:
        raise ValueError(f"seed and instance must be non-negative integers, got {seed}, {instance}")
    if not 4 <= min_vertices <= max_vertices:
        raise ValueError(
            f"need 4 <= min_vertices <= max_vertices, got {min_vertices}, {max_vertices}"
        )
    spec = _SPECS[category]
    key = category_key(category)
    last = ""
    for attempt in range(MAX_ATTEMPTS):
        shape_rng = np.random.default_rng([int(seed), key, int(instance), attempt, 0])
        mesh_rng = np.random.default_rng([int(seed), key, int(instance), attempt, 1])
        try:
            built = spec.build(shape_rng)
            v, f = built[:2]
            genus = built[2] if len(built) > 2 else spec.info.genus
            target = _target_vertices(mesh_rng, min_vertices, max_vertices)
            v, f = remesh(
                v,
                f,
                min_vertices=min_vertices,
                max_vertices=max_vertices,
                target_vertices=target,
                feature_angle=spec.info.feature_angle,
            )
        except (_Reject, ValueError) as exc:
            last = str(exc)
            continue
        problems = mesh_problems(v, f, closed=spec.info.closed, genus=genus)
        if problems:
            last = "; ".join(problems)
            continue
        frame = canonical_frame(v)
        return frame.apply(v), f.astype(np.int32)
    raise RuntimeError(
        f"no valid {category!r} mesh for seed {seed}, instance {instance} after "
        f"{MAX_ATTEMPTS} attempts; last problem: {last}"
    )
