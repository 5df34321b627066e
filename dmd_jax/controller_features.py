"""Scale-free statistics of a noisy mesh: what the smoothing controller decides from.

How much to smooth depends on how strong the noise is relative to the mesh's sampling,
how far it is correlated along the surface, whether it moves vertices along one
direction (a depth camera's view) or along the normals, and how much of the mesh is
boundary. Each statistic here is invariant to translation, rotation and uniform scale
(lengths are in mean edges, angles in degrees), so the controller trained on generated
meshes reads the same numbers on a user's scan at any size and pose.

`features(vertices, faces)` returns `[N_FEATURES]` float64, named by `FEATURE_NAMES`.
Cost: a few sparse sweeps over the mesh (about 2 % of a default `denoise` call at
100k faces; `benchmarks/results/controller.md`).
"""

from __future__ import annotations

import numpy as np

from dmd_jax import presmooth

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
    "disp_rms",
    *(f"disp_ratio_{k}" for k in SMOOTH_PROBES[1:]),
    "disp_normal_share",
    "disp_anisotropy",
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


def features(vertices, faces) -> np.ndarray:
    """The controller's statistics of one mesh (`FEATURE_NAMES`).

    Args:
      vertices: `[n_vertex, 3]` noisy positions, any frame.
      faces: `[n_face, 3]` vertex indices, every vertex referenced.

    Returns:
      `[N_FEATURES]` float64: roughness quantiles (angles between edge-adjacent face
      normals, degrees) and their ratios after 1/4/16 Laplacian steps; the bend share
      (`presmooth.bend_share`); the rms Laplacian displacement in mean edges and its
      ratios after 4/16 steps; the share of the displacement along the vertex normals;
      its anisotropy (largest eigenvalue share of the displacement's second moment:
      1/3 for isotropic noise, 1 for noise along one view direction); the share
      of boundary edges. No size: the controller trained on crops reads whole scans.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    mean_edge = float(np.linalg.norm(v[unique[:, 0]] - v[unique[:, 1]], axis=1).mean())
    if not mean_edge > 0:
        raise ValueError("the mesh's edges all have zero length")
    v = (v - v.mean(axis=0)) / mean_edge
    a, b = presmooth._edge_pairs(f, len(v))
    rough = _dihedral_deg(v, f, a, b)
    q = np.quantile(rough, QUANTILES) if len(rough) else np.zeros(len(QUANTILES))
    step = presmooth._laplacian_operator(f, len(v))
    disp0 = step(v, 1.0) - v  # the umbrella Laplacian: toward the neighbours' mean
    rms0 = float(np.sqrt(np.mean(np.sum(disp0**2, axis=1))))
    ratios, disp_ratios = [], []
    x, done = v, 0
    for k in SMOOTH_PROBES:
        x = presmooth.laplacian_steps(x, f, k - done)
        done = k
        med = float(np.median(_dihedral_deg(x, f, a, b))) if len(a) else 0.0
        ratios.append(med / max(q[1], 1e-9))
        if k != SMOOTH_PROBES[0]:
            d = step(x, 1.0) - x
            disp_ratios.append(float(np.sqrt(np.mean(np.sum(d**2, axis=1)))) / max(rms0, 1e-12))
    # Noise's own direction: the energy-weighted second moment of the displacement one
    # umbrella step removes (a sphere's own curvature adds an isotropic part that the
    # weighting keeps small: measured 0.92-0.97 for scanner noise, 0.34 for isotropic).
    energy = max(float(np.sum(disp0**2)), 1e-24)
    aniso = float(np.linalg.eigvalsh(disp0.T @ disp0 / energy)[-1])
    normals = _vertex_normals(v, f)
    along = float(np.sum(np.sum(disp0 * normals, axis=1) ** 2)) / energy
    return np.array(
        [
            *q,
            *ratios,
            presmooth.bend_share(v, f),
            rms0,
            *disp_ratios,
            along,
            aniso,
            float(np.count_nonzero(counts == 1)) / max(len(unique), 1),
        ],
        np.float64,
    )
