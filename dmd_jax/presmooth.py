"""Heavy-noise pre-smoothing: uniform Laplacian steps before the network, as many as the
noisy mesh's roughness asks for.

The bundled DMD-Net was trained on noise up to one mean edge length. Heavier noise (the
paper's Table II levels reach 2.7 mean edges per coordinate) crumples the mesh so much
that no candidate normal of the network is close to the surface, and more network passes
recover little (`experiments/results/sota/sota.md`, the "DMD-Net, network only"
columns). Per-coordinate noise of a third of an edge already hurts: its tangential part
leaves folded triangles the network does not unfold. `denoise` therefore first runs
`steps_for(roughness(...))` uniform Laplacian steps (the classic `baselines.laplacian`
step, λ = `LAMBDA`) and gives the network the result.

The roughness is the median angle between the normals of faces that share an edge: scale
free, blind to the few sharp creases of a CAD part (the median edge of a clean mesh is a
smooth one: at most 23° over the validation split and 27° over `shared/meshes`), and it
grows with the noise until, beyond about two edges of noise, it saturates near 115°.
The number of steps is a straight line in it, `round((roughness − start) / per_step)`
clipped to `[0, MAX_STEPS]`, whose two numbers are a property of trained weights
stored in the weights' policy (`policy.DenoisePolicy.presmooth_start`,
`presmooth_per_step`; the bundled 27° and 4.5° were fitted on the validation split of
`shared/meshes/train` in 2026-12, docs/bundled-model.md).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from dmd_jax.mesh import face_normals_np
from dmd_jax.topology import edge_keys, umbrella_weights

# The most Laplacian steps `denoise` runs before the network (the roughness saturates
# beyond about two mean edges of noise, so more noise cannot ask for more).
MAX_STEPS = 20
# The step size of each uniform Laplacian step, as `baselines.laplacian`'s default.
LAMBDA = 0.5


# Up to this many faces the roughness reads every edge; a larger mesh reads a fixed
# hash-chosen sample of about `SAMPLED_HALF_EDGES / 2` edges, so time and memory stay
# bounded (a 5M-face grid: 0.2 s and 75 MB sampled, 6 s and 1.9 GB with every edge).
# The median of ~150k angles is within a few tenths of a degree of the whole mesh's
# (four hash constants on that noisy grid: 30.12–30.41° against 30.11°), under a tenth of
# a step of the bundled rule.
EXACT_MAX_FACES = 100_000
SAMPLED_HALF_EDGES = 300_000
_CHUNK_FACES = 1_000_000
_HASH = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: spreads nearby keys
# The rule runs no step where fewer than this share of the bent edges bend the less
# common way (`bend_share`): the roughness is then the shape of a coarse convex solid,
# not noise. Noisy meshes the rule pre-smooths measure 0.33 or more (every mesh of
# `shared/meshes` and 40 of `train/` at Gaussian 0.15–1.0, impulse 0.6, scanner 0.8).
MIN_BEND_SHARE = 0.1
# Faces within 1° of each other bend neither way (`bend_share`).
_FLAT_COS = float(np.cos(np.radians(1.0)))


def _edge_pairs(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces sharing an edge: all of them for a mesh of at most
    `EXACT_MAX_FACES` faces, else the pairs of a hash-chosen subset of the edges (both
    half-edges of an edge have the same key, so a kept edge keeps its pair). Around a
    non-manifold edge, consecutive faces in sorted order are paired."""
    m = faces.shape[0]
    stride = 1 if m <= EXACT_MAX_FACES else -(-3 * m // SAMPLED_HALF_EDGES)
    keys, owners = [], []
    for lo_face in range(0, m, _CHUNK_FACES):
        f = faces[lo_face : lo_face + _CHUNK_FACES]
        # `edge_keys` lists a chunk's edges slot by slot: entry k is the chunk's face
        # k % len(f). The hash is mixed in place to keep the temporaries to two arrays.
        key = edge_keys(f, n_vertex)
        if stride > 1:
            mixed = key.astype(np.uint64)
            with np.errstate(over="ignore"):
                mixed *= _HASH
            mixed >>= np.uint64(32)
            mixed %= np.uint64(stride)
            keep = np.flatnonzero(mixed == 0)
            del mixed
            key, face = key[keep], lo_face + keep % f.shape[0]
        else:
            face = np.tile(np.arange(lo_face, lo_face + f.shape[0], dtype=np.int64), 3)
        keys.append(key)
        owners.append(face)
    key, owner = np.concatenate(keys), np.concatenate(owners)
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    return owner[same], owner[same + 1]


def roughness(vertices, faces, free=None, *, normals=None) -> float:
    """The median angle, in degrees, between the normals of faces sharing an edge.

    Args:
      vertices: `[n_vertex, 3]` positions in any frame.
      faces: `[n_face, 3]` vertex indices.
      free: `[n_vertex]` bool, or None for all: only pairs of faces whose every vertex
        is free count. `denoise` leaves out the exact vertices of a clean part's flats,
        creases and corners (`consistency.exact_vertices`): the dihedral angles of faces
        anchored on them (90° all over a coarse box, 60° at a cone's rim) are the
        part's shape, not noise.
      normals: `[n_face, 3]` `mesh.face_normals_np` of `vertices` (as float64) and
        `faces`, if already known (`denoise` computes them once for its checks).

    Returns:
      The median over edge-adjacent face pairs whose faces both have an area (over a
      fixed sample of the edges above `EXACT_MAX_FACES` faces); 0 for a mesh without
      such a pair (a single triangle, or only degenerate faces).
    """
    v, f, a, b, na, nb = _counted_pairs(vertices, faces, free, normals)
    if not a.size:
        return 0.0
    cos = np.clip(np.einsum("ij,ij->i", na, nb), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def bend_share(vertices, faces, free=None, *, normals=None) -> float:
    """The share of the edges `roughness` reads that bend the less common way.

    An edge is convex when the far vertex of one face lies below the other face's
    plane. Noise bends neighbouring faces both ways (a noisy mesh rough enough to be
    pre-smoothed: 0.3–0.5 of its edges bend the less common way); the shape of a coarse
    convex solid bends them all one way (0 for a tetrahedron, an octahedron or an
    icosahedron, whose 70–140° dihedrals the roughness would read as noise beyond two
    edges, and whose shape the Laplacian steps would shrink to a point).

    Args:
      vertices: `[n_vertex, 3]` positions in any frame.
      faces: `[n_face, 3]` consistently wound faces.
      free: `[n_vertex]` bool, or None for all: as `roughness`.
      normals: as `roughness`.

    Returns:
      In `[0, 0.5]`; 0.5 for a mesh without such a pair.
    """
    v, f, a, b, na, nb = _counted_pairs(vertices, faces, free, normals)
    bent = np.einsum("ij,ij->i", na, nb) < _FLAT_COS  # a flat pair bends neither way
    a, b, na = a[bent], b[bent], na[bent]
    if not a.size:
        return 0.5
    fa, fb = f[a], f[b]
    far = fb[np.arange(len(b)), np.argmax((fb[:, :, None] != fa[:, None, :]).all(2), axis=1)]
    side = np.einsum("ij,ij->i", na, v[far] - v[fa[:, 0]])
    convex = float(np.mean(side < 0))
    return min(convex, 1.0 - convex)


def _counted_pairs(vertices, faces, free, normals=None):
    """`(v, f, a, b, na, nb)`: the positions and faces as arrays, and the pairs of
    faces `roughness` reads (`a`, `b` `[n_pair]`) with their unit normals `[n_pair, 3]`
    (rows of `normals`, the faces' `face_normals_np`, when given: the same numbers)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    a, b = _edge_pairs(f, v.shape[0])
    if free is not None:
        loose = np.asarray(free, bool)[f].all(axis=1)
        keep = loose[a] & loose[b]
        a, b = a[keep], b[keep]
    if normals is None:
        na, nb = face_normals_np(v, f[a]), face_normals_np(v, f[b])
    else:
        na, nb = normals[a], normals[b]
    ok = (np.abs(na).sum(axis=1) > 0) & (np.abs(nb).sum(axis=1) > 0)
    return v, f, a[ok], b[ok], na[ok], nb[ok]


def steps_for(rough: float, start: float, per_step: float, most: int = MAX_STEPS) -> int:
    """Laplacian steps for a mesh of roughness `rough` (degrees) under the rule
    `round((rough − start) / per_step)` clipped to `[0, most]`; 0 when `start` is 0
    (no pre-smoothing)."""
    if start <= 0:
        return 0
    return int(np.clip(np.round((rough - start) / per_step), 0, most))


def _laplacian_operator(faces: np.ndarray, n: int):
    """One uniform Laplacian step `x ↦ x + λ (umbrella average − x)` as a function."""
    senders, receivers, weight, self_weight = umbrella_weights(np.asarray(faces), n)
    total = np.bincount(receivers, weights=weight, minlength=n) + self_weight
    scale = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
    average = sp.csr_matrix((weight * scale[receivers], (receivers, senders)), shape=(n, n))
    average = average + sp.diags(self_weight * scale)
    keep = (total > 0)[:, None]

    def step(x, lam):
        return np.where(keep, x + lam * (average @ x - x), x)

    return step


def laplacian_steps(vertices, faces, steps: int, lam: float = LAMBDA) -> np.ndarray:
    """`steps` uniform Laplacian steps `x ← x + λ (umbrella average − x)`.

    The operator of `baselines.laplacian` (`topology.umbrella_weights`: MeshLab's, where a
    vertex on an open boundary averages itself with its boundary neighbours only; tested
    equal), as one sparse matrix on the host: no compilation, memory linear in the mesh
    (measured on a 5M-face grid: 1.2 GB at peak, 3.6 s for 5 steps on 2 cores).

    Args:
      vertices: `[n_vertex, 3]` positions (not modified).
      faces: `[n_face, 3]` vertex indices.
      steps: number of steps, >= 0.
      lam: the step size λ.

    Returns:
      `[n_vertex, 3]` float64 positions; isolated vertices stay where they are.
    """
    x = np.array(vertices, dtype=np.float64)
    if steps <= 0:
        return x
    step = _laplacian_operator(faces, x.shape[0])
    for _ in range(int(steps)):
        x = step(x, lam)
    return x
