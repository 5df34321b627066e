"""A depth-camera simulator: a clean mesh seen by one sensor, as a noisy range-image mesh.

`simulate_scan(seed, vertices, faces, view=..., resolution=...)` renders the mesh into a
depth map from a view, triangulates the depth map back into a mesh and adds the scanner
noise (`dmd_jax.noise.ScannerModel`) in depth. What comes out has the features of the
range-image meshes users bring (issue 53's measurements on public scans): grid
tessellation, open boundaries, holes at depth discontinuities and occlusions, long slivers
at grazing angles, a few spikes, quantised depth. It has exact ground truth: every scan
vertex's clean position is the true surface point its pixel's ray hits.

The camera is orthographic: every ray runs along `view`, so noise in depth is a
displacement along `view`, as the scanner noise kind draws it, and

    noisy == clean + scanner_displacement(host_rng(key), clean, faces, level, h, view=view)

with `h` the scan's mean edge length (tested). The image frames the mesh's projection,
square pixels, `resolution` on the longer side.

Rendering is a vectorised z-buffer rasteriser in NumPy (no Python loop over faces or
pixels, no ray-casting package): every face's candidate pixels (pixel centres inside its
projected bounding box) are enumerated at once, tested with barycentric coordinates, and
the nearest hit per pixel kept, in chunks of at most `_CHUNK_CANDIDATES` candidates so the
memory stays bounded. Deterministic: the same seed, mesh and arguments give the same
bits. `benchmarks/bench_scan.py` measures it (100k faces at 256², results in
`benchmarks/results/scan.md`).

Triangulation: each 2 x 2 block of hit pixels gives two triangles (one when a corner is
missing); a triangle is dropped when its depths differ by more than `max_depth_jump`
pixel sizes (a jump between surfaces: occlusion boundary) or a corner's surface is seen at
more than `max_grazing_deg` from the ray (sensors lose the return there). Pixels left
in no triangle are dropped, so every scan vertex is used.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from dmd_jax import noise as noise_lib
from dmd_jax.mesh import mean_edge_length, validate_mesh

# The simulator's defaults, each a named choice.
DEFAULT_RESOLUTION = 256
# Above this the depth map alone takes over 130 MB; no scan of this library needs more.
MAX_RESOLUTION = 4096
# The default scanner level: the middle of the depth-camera range measured on real scans
# (0.4-0.9 mean edge lengths of the scan).
DEFAULT_SCAN_LEVEL = 0.5
# Surfaces seen at more than this angle from the ray return nothing (structured-light and
# time-of-flight sensors lose most returns beyond ~75-80°); slivers below it stay.
MAX_GRAZING_DEG = 80.0
# A scan triangle whose depths differ by more than this many pixel sizes spans a depth
# jump (occlusion). A surface at the grazing limit rises tan(80°) = 5.7 pixel sizes per
# pixel step, so 8 keeps every surface triangle the grazing limit keeps (diagonals
# included: 5.7 x √2 = 8.0).
MAX_DEPTH_JUMP = 8.0
# The image frames the projection with this margin (fraction of the longer side).
FRAME_MARGIN = 0.02
# Candidate (face, pixel) pairs rasterised at once.
_CHUNK_CANDIDATES = 1 << 22
# `facing_view`: an open mesh whose area-weighted normals add up to more than this share
# of its area is roughly one-sided, and is scanned from its front.
OPEN_MESH_SHARE = 0.1


class Scan(NamedTuple):
    """A simulated scan: one range-image mesh with exact ground truth.

    Attributes:
      clean: `[n_vertex, 3]` the true surface point of each kept pixel.
      noisy: `[n_vertex, 3]` the same points with the scanner noise in depth.
      faces: `[n_face, 3]` int32 grid triangles, oriented towards the sensor.
      view: `[3]` the unit direction the sensor looks along.
    """

    clean: np.ndarray
    noisy: np.ndarray
    faces: np.ndarray
    view: np.ndarray


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as `validate_mesh` checks it for `denoise`, with int64 faces."""
    v, f = validate_mesh(vertices, faces)
    return v, f.astype(np.int64)


def _check_real(name: str, value) -> float:
    """A real-number argument as a float; `TypeError` naming it for anything else."""
    if isinstance(value, bool | np.bool_) or not isinstance(
        value, int | float | np.integer | np.floating
    ):
        raise TypeError(f"{name} must be a number, got {value!r}")
    return float(value)


def _check_resolution(resolution) -> int:
    if isinstance(resolution, bool) or not isinstance(resolution, int | np.integer):
        raise ValueError(f"resolution must be an integer, got {resolution!r}")
    if not 2 <= int(resolution) <= MAX_RESOLUTION:
        raise ValueError(f"resolution must lie in [2, {MAX_RESOLUTION}], got {resolution}")
    return int(resolution)


def facing_view(view, vertices, faces) -> np.ndarray:
    """`view` (unit), turned to look at the front of a roughly one-sided open mesh.

    A crop or patch seen from behind or edge-on leaves little to scan. When the
    area-weighted face normals add up to more than `OPEN_MESH_SHARE` of the area, the
    view is flipped if it looks along them; a closed mesh's normals add up to zero and
    any view stands.
    """
    d = noise_lib.check_view(view)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    total = cross.sum(axis=0)
    area = np.linalg.norm(cross, axis=1).sum()
    if np.linalg.norm(total) > OPEN_MESH_SHARE * area and d @ total > 0:
        d = -d
    return d


def view_basis(view) -> np.ndarray:
    """A right-handed orthonormal basis `[3, 3]`: rows `e1, e2, d` with `e1 × e2 = d`."""
    d = noise_lib.check_view(view)
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    e1 = np.cross(helper, d)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(d, e1), d])


class DepthMap(NamedTuple):
    """The nearest hit of each pixel (`render_depth`).

    Attributes:
      face: `[res_y, res_x]` int64 index of the hit face, -1 where the ray misses.
      bary: `[res_y, res_x, 3]` barycentric coordinates of the hit on that face.
      depth: `[res_y, res_x]` depth along the view (inf where missed).
      pixel: the pixel size, in the mesh's units.
    """

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    pixel: float


def render_depth(vertices, faces, basis: np.ndarray, resolution: int) -> DepthMap:
    """Rasterises a mesh into an orthographic depth map (vectorised z-buffer).

    Args:
      vertices: `[n_vertex, 3]` float64.
      faces: `[n_face, 3]` int.
      basis: `view_basis(view)`: image axes `e1` (x), `e2` (y) and the view `d`.
      resolution: pixels on the longer side of the projection's frame.

    Returns:
      A `DepthMap`.
    """
    p = vertices @ basis[:2].T  # [n, 2] image-plane coordinates
    z = vertices @ basis[2]
    lo, hi = p.min(axis=0), p.max(axis=0)
    extent = float(np.max(hi - lo))
    if extent <= 0:
        extent = 1.0
    pixel = extent * (1.0 + 2.0 * FRAME_MARGIN) / resolution
    shape = np.maximum(np.ceil((hi - lo) / pixel + 2.0 * FRAME_MARGIN * resolution), 1)
    nx, ny = (min(int(s), resolution) for s in shape)
    origin = (lo + hi) / 2.0 - pixel * np.array([nx, ny]) / 2.0
    q = (p - origin) / pixel - 0.5  # pixel centres at integer coordinates
    tri = q[faces]  # [m, 3, 2]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    x0 = np.clip(np.ceil(tri[:, :, 0].min(axis=1)), 0, nx).astype(np.int64)
    x1 = np.clip(np.floor(tri[:, :, 0].max(axis=1)), -1, nx - 1).astype(np.int64)
    y0 = np.clip(np.ceil(tri[:, :, 1].min(axis=1)), 0, ny).astype(np.int64)
    y1 = np.clip(np.floor(tri[:, :, 1].max(axis=1)), -1, ny - 1).astype(np.int64)
    width = np.maximum(x1 - x0 + 1, 0)
    counts = width * np.maximum(y1 - y0 + 1, 0)
    counts[np.abs(area2) < 1e-12] = 0  # edge-on faces cover no pixel centre
    depth = np.full(nx * ny, np.inf)
    face = np.full(nx * ny, -1, np.int64)
    bary = np.zeros((nx * ny, 3))
    zf = z[faces]
    ends = np.cumsum(counts)
    starts = ends - counts
    total = int(ends[-1]) if ends.size else 0
    # Candidates are numbered face by face; each chunk is a range of those numbers, so a
    # face larger than a chunk (a big triangle at a high resolution) is split too.
    for c0 in range(0, total, _CHUNK_CANDIDATES):
        cand = np.arange(c0, min(c0 + _CHUNK_CANDIDATES, total))
        fid = np.searchsorted(ends, cand, side="right")
        local = cand - starts[fid]
        px = x0[fid] + local % width[fid]
        py = y0[fid] + local // width[fid]
        ax, ay = a[fid, 0] - px, a[fid, 1] - py
        bx, by = b[fid, 0] - px, b[fid, 1] - py
        cx, cy = c[fid, 0] - px, c[fid, 1] - py
        inv = 1.0 / area2[fid]
        l0 = (bx * cy - by * cx) * inv
        l1 = (cx * ay - cy * ax) * inv
        l2 = 1.0 - l0 - l1
        # A small tolerance closes cracks between faces sharing an edge through a centre.
        inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        if not inside.any():
            continue
        fid, l0, l1, l2 = fid[inside], l0[inside], l1[inside], l2[inside]
        pix = (py * nx + px)[inside]
        zz = l0 * zf[fid, 0] + l1 * zf[fid, 1] + l2 * zf[fid, 2]
        # Nearest hit per pixel within the chunk: sort by depth, first of each pixel.
        order = np.lexsort((zz, pix))
        first = np.ones(order.size, bool)
        first[1:] = pix[order[1:]] != pix[order[:-1]]
        sel = order[first]
        better = zz[sel] < depth[pix[sel]]
        sel = sel[better]
        target = pix[sel]
        depth[target] = zz[sel]
        face[target] = fid[sel]
        bary[target] = np.stack([l0[sel], l1[sel], l2[sel]], axis=1)
    return DepthMap(face.reshape(ny, nx), bary.reshape(ny, nx, 3), depth.reshape(ny, nx), pixel)


def _grid_faces(valid: np.ndarray, depth: np.ndarray, jump: float) -> np.ndarray:
    """Triangles `[k, 3]` of pixel indices over a `[ny, nx]` mask, depth jumps dropped.

    Per 2 x 2 block `(a b / c e)` two triangles `(a, c, b)` and `(b, c, e)` when all four
    pixels are valid, else the one triangle of the three valid corners (`a, c, b`, `b, c,
    e`, `a, e, b` or `a, c, e`), all with the same winding.
    """
    ny, nx = valid.shape
    ids = np.arange(ny * nx).reshape(ny, nx)
    a, b = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel()
    c, e = ids[1:, :-1].ravel(), ids[1:, 1:].ravel()
    va, vb, vc, ve = (valid.ravel()[k] for k in (a, b, c, e))
    full = va & vb & vc & ve
    candidates = [
        (np.stack([a, c, b], 1), va & vb & vc),
        (np.stack([b, c, e], 1), vb & vc & ve),
        (np.stack([a, e, b], 1), ~full & va & vb & ve & ~vc),
        (np.stack([a, c, e], 1), ~full & va & vc & ve & ~vb),
    ]
    tri = np.concatenate([t[m] for t, m in candidates])
    if tri.size == 0:
        return tri.reshape(0, 3)
    z = depth.ravel()[tri]
    return tri[(z.max(axis=1) - z.min(axis=1)) <= jump]


def simulate_scan(
    seed,
    vertices,
    faces,
    *,
    view=None,
    resolution: int = DEFAULT_RESOLUTION,
    level: float = DEFAULT_SCAN_LEVEL,
    max_grazing_deg: float = MAX_GRAZING_DEG,
    max_depth_jump: float = MAX_DEPTH_JUMP,
    model: noise_lib.ScannerModel = noise_lib.SCANNER_MODEL,
) -> Scan:
    """Scans a clean mesh with a simulated depth camera (module docstring).

    Args:
      seed: an `int` or a `jax.random` key: the view (when not given) and the noise.
      vertices: `[n_vertex, 3]` clean positions, in any frame.
      faces: `[n_face, 3]` vertex indices.
      view: the direction the sensor looks along, `[3]`; None draws it from `seed`
        (uniform on the sphere).
      resolution: pixels on the longer side of the image, in `[2, MAX_RESOLUTION]`.
      level: rms of the depth noise in mean edge lengths of the scan (about the pixel
        size); 0 gives `noisy == clean`.
      max_grazing_deg: pixels whose surface is seen at more than this angle from the ray
        return nothing.
      max_depth_jump: triangles whose depths differ by more than this many pixel sizes
        are dropped (occlusion boundaries).
      model: the scanner noise's `ScannerModel`.

    Returns:
      A `Scan` `(clean, noisy, faces, view)`: clean and noisy `[n, 3]` float64 vertices of
      one range-image triangulation, its faces `[k, 3]` int32, the unit view `[3]`.

    Raises:
      ValueError: a bad mesh (shape, NaN, indices), `view` (zero, not a 3-vector),
        `resolution`, `level`, or no surface in view (nothing left to triangulate).
    """
    key = noise_lib.seed_key(seed)
    v, f = _check_mesh(vertices, faces)
    resolution = _check_resolution(resolution)
    level = noise_lib.check_level(level)
    if not 0.0 < _check_real("max_grazing_deg", max_grazing_deg) <= 90.0:
        raise ValueError(f"max_grazing_deg must lie in (0, 90], got {max_grazing_deg!r}")
    if not _check_real("max_depth_jump", max_depth_jump) > 0.0:
        raise ValueError(f"max_depth_jump must be > 0, got {max_depth_jump!r}")
    noise_lib.check_scanner_model(model)
    if view is not None:
        view = noise_lib.check_view(view)
    rng = noise_lib.host_rng(key)
    if view is None:
        view = noise_lib.random_view(rng)
    basis = view_basis(view)
    depth_map = render_depth(v, f, basis, resolution)
    hit = depth_map.face >= 0
    # Grazing: the angle between the hit face's normal and the ray.
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    cos = np.zeros(hit.shape)
    cos[hit] = np.abs(normals[depth_map.face[hit]] @ view)
    valid = hit & (cos >= math.cos(math.radians(float(max_grazing_deg))) - 1e-12)
    tri = _grid_faces(valid, depth_map.depth, float(max_depth_jump) * depth_map.pixel)
    if tri.shape[0] == 0:
        raise ValueError(
            f"no surface in view: the mesh leaves no scan triangle along view {view.tolist()} "
            f"at resolution {resolution} (seen edge-on, or smaller than a pixel)"
        )
    used, inverse = np.unique(tri, return_inverse=True)
    scan_faces = inverse.reshape(-1, 3).astype(np.int32)
    pix_face = depth_map.face.ravel()[used]
    pix_bary = depth_map.bary.reshape(-1, 3)[used]
    clean = np.einsum("nk,nkd->nd", pix_bary, v[f[pix_face]])
    h = mean_edge_length(clean, scan_faces)
    moved, _ = noise_lib.scanner_displacement(
        rng, clean, scan_faces, level, h, view=view, model=model
    )
    return Scan(clean, clean + moved, scan_faces, np.asarray(view, np.float64))
