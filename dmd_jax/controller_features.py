"""Scale-free statistics of a noisy mesh: what the smoothing controller decides from.

How much to smooth depends on how strong the noise is relative to the mesh's sampling,
how far it is correlated along the surface, whether it moves vertices along one
direction (a depth camera's view) or along the normals, and how much of the mesh is
boundary. Each statistic here is invariant to translation, rotation and uniform scale
(lengths are in local mean edges, angles in degrees), so the controller trained on
generated meshes reads the same numbers on a user's scan at any size and pose.

They must also not read an irregular triangulation as noise. A vertex of a clean but
irregular mesh sits far from its neighbours' mean (the umbrella vector), but on their
plane: the noise statistics are the distances to the plane fitted through each vertex's
neighbours, in that vertex's own mean edge, weighted by area; the umbrella vector's
tangential part, which irregular sampling and isotropic noise both give, is one
statistic of its own beside the triangulation's own irregularity (edge-length spread,
smallest angles) so the controller can tell them apart.

`features(vertices, faces)` returns `[N_FEATURES]` float64, named by `FEATURE_NAMES`.
Cost: a few sparse sweeps over a crop (`crops`; `benchmarks/controller_cost.py`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dmd_jax import presmooth

# Which statistics these are: stored with every generated example (data.smoothing_set),
# which refuses to mix examples of another version.
FEATURES_VERSION = 2
# Laplacian steps after which the roughness is measured again: noise correlated over a
# few edges survives more steps than white noise (the ratios read the correlation length).
SMOOTH_PROBES = (1, 4, 16)
QUANTILES = (0.25, 0.5, 0.75, 0.9)
# A large mesh is read in this many crops of this many vertices (`crops`).
CROPS = 4
CROP_VERTICES = 400

FEATURE_NAMES = (
    *(f"rough_q{int(q * 100)}" for q in QUANTILES),
    *(f"rough_ratio_{k}" for k in SMOOTH_PROBES),
    "bend_share",
    "plane_rms",
    *(f"plane_ratio_{k}" for k in SMOOTH_PROBES[1:]),
    "tangent_rms",
    "disp_anisotropy",
    "edge_spread",
    "angle_q10",
    "boundary_share",
)
N_FEATURES = len(FEATURE_NAMES)


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def _dihedral_deg(v: np.ndarray, f: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = _face_normals(v, f)
    return np.degrees(np.arccos(np.clip(np.sum(n[a] * n[b], axis=1), -1.0, 1.0)))


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    area_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    corners = f.ravel()
    out = np.stack(
        [np.bincount(corners, np.repeat(area_n[:, d], 3), minlength=len(v)) for d in range(3)],
        axis=1,
    )
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(length > 0, length, 1.0)


def crops(vertices, faces, *, n_crops: int = CROPS, crop_vertices: int = CROP_VERTICES):
    """Up to `n_crops` local pieces of a mesh, each the faces among the `crop_vertices`
    vertices nearest a seed vertex (seeds spread over the mesh, fixed for a mesh), each
    re-indexed: `[(vertices [m, 3], faces [k, 3])]`. The whole mesh when it is small.

    The controller was trained on crops of 400-1200 faces (`data.smoothing_set`); its
    statistics are per-area, and reading a few crops of a large mesh costs a few
    milliseconds where the whole mesh would cost a second (82k faces).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(v) <= 2 * crop_vertices:
        return [(v, f)]
    seeds = np.random.default_rng(0).choice(len(v), size=n_crops, replace=False)
    out = []
    for seed in seeds:
        d = np.sum((v - v[seed]) ** 2, axis=1)
        keep = np.zeros(len(v), bool)
        keep[np.argpartition(d, crop_vertices)[:crop_vertices]] = True
        inside = f[keep[f].all(axis=1)]
        if len(inside) < crop_vertices // 2:
            continue  # a sliver of a thin part: too few faces to read
        used = np.unique(inside)
        index = np.full(len(v), -1, np.int64)
        index[used] = np.arange(len(used))
        out.append((v[used], index[inside]))
    return out or [(v, f)]


def _weighted_quantile(x: np.ndarray, w: np.ndarray, q) -> np.ndarray:
    """Quantiles `q` of `x [n]` under weights `w [n]` (the lower value at each step)."""
    if len(x) == 0:
        return np.zeros(len(np.atleast_1d(q)))
    order = np.argsort(x)
    cum = np.cumsum(w[order])
    at = np.searchsorted(cum, np.asarray(q) * cum[-1])
    return x[order][np.minimum(at, len(x) - 1)]


class _Rings(NamedTuple):
    """A mesh's 1-rings as index arrays: vertex `i[k]` neighbours `j[k]`; `count [n]`."""

    i: np.ndarray
    j: np.ndarray
    count: np.ndarray


def _rings(edges: np.ndarray, n: int) -> _Rings:
    i = np.concatenate([edges[:, 0], edges[:, 1]])
    j = np.concatenate([edges[:, 1], edges[:, 0]])
    return _Rings(i, j, np.bincount(i, minlength=n))


def _plane_residuals(x: np.ndarray, rings: _Rings, local_edge: np.ndarray):
    """Each vertex's distance to the least-squares plane of its neighbours (not itself:
    the plane is not pulled toward its own noise) and the umbrella vector's part in that
    plane, both in the vertex's own mean edge.

    Args:
      x: `[n, 3]` positions.
      rings: the 1-rings.
      local_edge: `[n]` each vertex's mean incident edge length.

    Returns:
      `(normal [n], tangent [n], ok [n] bool)`: ok where the plane is defined (3 or
      more neighbours).
    """
    n = len(x)
    cnt = np.maximum(rings.count, 1)[:, None]
    centre = np.stack([np.bincount(rings.i, x[rings.j, d], n) for d in range(3)], 1) / cnt
    d = x[rings.j] - centre[rings.i]
    cov = np.stack(
        [np.bincount(rings.i, d[:, a] * d[:, b], n) for a in range(3) for b in range(3)], 1
    ).reshape(n, 3, 3)
    normal = np.linalg.eigh(cov)[1][:, :, 0]  # the smallest spread's direction
    u = centre - x  # the umbrella vector
    along = np.sum(u * normal, axis=1)
    tangent = np.linalg.norm(u - along[:, None] * normal, axis=1)
    scale = np.where(local_edge > 0, local_edge, 1.0)
    return np.abs(along) / scale, tangent / scale, rings.count >= 3


def _weighted_rms(x: np.ndarray, w: np.ndarray) -> float:
    total = float(np.sum(w))
    return float(np.sqrt(np.sum(w * x**2) / total)) if total > 0 else 0.0


def features(vertices, faces) -> np.ndarray:
    """The controller's statistics of one mesh (`FEATURE_NAMES`).

    Args:
      vertices: `[n_vertex, 3]` noisy positions, any frame.
      faces: `[n_face, 3]` vertex indices, every vertex referenced.

    Returns:
      `[N_FEATURES]` float64: roughness quantiles (angles between edge-adjacent face
      normals, degrees, weighted by the two faces' area) and the median's ratios after
      1/4/16 Laplacian steps; the bend share (`presmooth.bend_share`); the area-weighted
      rms distance of the vertices to their neighbours' plane in local mean edges, and its
      ratios after 4/16 steps; the rms tangential part of the umbrella vector in local
      mean edges; the umbrella vector's anisotropy (largest eigenvalue share of its
      second moment: 1/3 for isotropic noise, 1 for noise along one view direction); the
      spread of the edge lengths (standard deviation over the mean of each edge's length
      over its ends' local mean edge); the 10th percentile of the triangles' smallest
      angles (degrees); the share of boundary edges. No size: the controller trained on
      crops reads whole scans.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    length = np.linalg.norm(v[unique[:, 0]] - v[unique[:, 1]], axis=1)
    mean_edge = float(length.mean())
    if not mean_edge > 0:
        raise ValueError("the mesh's edges all have zero length")
    v = (v - v.mean(axis=0)) / mean_edge
    length = length / mean_edge
    n = len(v)
    rings = _rings(unique, n)
    # Each vertex's own mean edge: the unit of its displacements where sizes vary.
    local_edge = np.bincount(rings.i, np.concatenate([length, length]), n) / np.maximum(
        rings.count, 1
    )
    spread_ratio = length / np.maximum(
        0.5 * (local_edge[unique[:, 0]] + local_edge[unique[:, 1]]), 1e-12
    )
    edge_spread = float(np.std(spread_ratio) / max(np.mean(spread_ratio), 1e-12))

    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    face_area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    vertex_area = np.bincount(f.ravel(), np.repeat(face_area / 3.0, 3), n)
    a, b = presmooth._edge_pairs(f, n)
    pair_area = face_area[a] + face_area[b]
    rough = _dihedral_deg(v, f, a, b)
    q = _weighted_quantile(rough, pair_area, QUANTILES)

    # One operator for every probe (building it is most of a step's cost on a crop);
    # the same steps as `presmooth.laplacian_steps`.
    step = presmooth._laplacian_operator(f, n)

    def plane_rms(x):
        normal, _, ok = _plane_residuals(x, rings, local_edge)
        return _weighted_rms(normal, vertex_area * ok)

    normal0, tangent, ok = _plane_residuals(v, rings, local_edge)
    plane0 = _weighted_rms(normal0, vertex_area * ok)
    tangent_rms = _weighted_rms(tangent, vertex_area * ok)
    ratios, plane_ratios = [], []
    x, done = v, 0
    for k in SMOOTH_PROBES:
        for _ in range(k - done):
            x = step(x, presmooth.LAMBDA)
        done = k
        med = float(_weighted_quantile(_dihedral_deg(x, f, a, b), pair_area, [0.5])[0])
        ratios.append(med / max(q[1], 1e-9))
        if k != SMOOTH_PROBES[0]:
            plane_ratios.append(plane_rms(x) / max(plane0, 1e-12))
    # Noise's own direction: the energy-weighted second moment of the displacement one
    # umbrella step removes (a sphere's own curvature adds an isotropic part that the
    # weighting keeps small: measured 0.92-0.97 for scanner noise, 0.34 for isotropic).
    disp0 = step(v, 1.0) - v
    energy = max(float(np.sum(disp0**2)), 1e-24)
    aniso = float(np.linalg.eigvalsh(disp0.T @ disp0 / energy)[-1])
    angle_q10 = float(np.quantile(_smallest_angles_deg(v, f), 0.1)) if len(f) else 60.0
    return np.array(
        [
            *q,
            *ratios,
            presmooth.bend_share(v, f),
            plane0,
            *plane_ratios,
            tangent_rms,
            aniso,
            edge_spread,
            angle_q10,
            float(np.count_nonzero(counts == 1)) / max(len(unique), 1),
        ],
        np.float64,
    )


def _smallest_angles_deg(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """`[n_face]` each triangle's smallest interior angle (degrees; 0 for a degenerate one)."""
    p = v[f]  # [n_face, 3, 3]
    out = np.full(len(f), 180.0)
    for k in range(3):
        u = p[:, (k + 1) % 3] - p[:, k]
        w = p[:, (k + 2) % 3] - p[:, k]
        nu, nw = np.linalg.norm(u, axis=1), np.linalg.norm(w, axis=1)
        cos = np.sum(u * w, axis=1) / np.maximum(nu * nw, 1e-300)
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        out = np.minimum(out, np.where((nu > 0) & (nw > 0), angle, 0.0))
    return out
