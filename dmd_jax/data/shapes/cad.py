"""Shape categories with creases (feature angle 30°): machined parts built as manifold3d
solids (`blocks`, `bracket`, `extrusion`, `gear`, `csg`, `fastener`, `flange`). Each
builder maps a random generator to a base surface `(vertices, faces)`."""

from __future__ import annotations

import numpy as np

from dmd_jax.data.shapes.kit import (
    _HOLE_SEGMENTS,
    _REVOLVE_SEGMENTS,
    _arrays,
    _box,
    _cross_section,
    _cylinder,
    _manifold,
    _one_piece,
    _Reject,
    _revolve,
    _star_polygon,
    _union,
)

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
