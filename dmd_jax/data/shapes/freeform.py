"""Shape categories of smooth or swept surfaces: vessels (`vase`, `cup`, `bottle`),
`blob`, `metaballs`, `torus`, `genus`, `superquadric`, height fields (`relief`,
`terrain`), `twisted_bar` and `tube`. Each builder maps a random generator to a base
surface `(vertices, faces)` (and, for `genus`, the genus it built)."""

from __future__ import annotations

import numpy as np

from dmd_jax.data.repair import _orient_outward
from dmd_jax.data.shapes.kit import (
    _arrays,
    _box,
    _check_tube_clearance,
    _grid_faces,
    _manifold,
    _marching_cubes,
    _one_piece,
    _random_rotation,
    _Reject,
    _revolve,
    _smooth_min,
    _star_polygon,
    _sweep_tube,
    _torus_sdf,
    _unit_icosphere,
)


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
