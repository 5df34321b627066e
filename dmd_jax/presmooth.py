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
(`ModelConfig.presmooth_start`, `ModelConfig.presmooth_per_step`), fitted on the
validation split of `shared/meshes/train` by `benchmarks/presmooth_fit.py`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from dmd_jax.baselines._common import umbrella_weights
from dmd_jax.graph import face_adjacency

# The most Laplacian steps `denoise` runs before the network (the roughness saturates
# beyond about two mean edges of noise, so more noise cannot ask for more).
MAX_STEPS = 20
# The step size of each uniform Laplacian step, as `baselines.laplacian`'s default.
LAMBDA = 0.5


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals `[n_face, 3]`; zero rows for degenerate faces."""
    v = vertices[faces]
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.where(norm > 0, cross / np.where(norm > 0, norm, 1.0), 0.0)


def roughness(vertices, faces, *, adjacency=None) -> float:
    """The median angle, in degrees, between the normals of faces sharing an edge.

    Args:
      vertices: `[n_vertex, 3]` positions in any frame.
      faces: `[n_face, 3]` vertex indices.
      adjacency: `graph.face_adjacency(faces, n_vertex)`, if already known.

    Returns:
      The median over edge-adjacent face pairs whose faces both have an area; 0 for a
      mesh without such a pair (a single triangle, or only degenerate faces).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    a, b = face_adjacency(f, v.shape[0]) if adjacency is None else adjacency
    n = _face_normals(v, f)
    ok = (np.abs(n[a]).sum(axis=1) > 0) & (np.abs(n[b]).sum(axis=1) > 0)
    if not ok.any():
        return 0.0
    cos = np.clip(np.einsum("ij,ij->i", n[a[ok]], n[b[ok]]), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def steps_for(rough: float, start: float, per_step: float, most: int = MAX_STEPS) -> int:
    """Laplacian steps for a mesh of roughness `rough` (degrees) under the rule
    `round((rough − start) / per_step)` clipped to `[0, most]`; 0 when `start` is 0
    (no pre-smoothing)."""
    if start <= 0:
        return 0
    return int(np.clip(np.round((rough - start) / per_step), 0, most))


def laplacian_steps(vertices, faces, steps: int, lam: float = LAMBDA) -> np.ndarray:
    """`steps` uniform Laplacian steps `x ← x + λ (umbrella average − x)`.

    The operator of `baselines.laplacian` (its `umbrella_weights`: MeshLab's, where a
    vertex on an open boundary averages itself with its boundary neighbours only; tested
    equal), as one sparse matrix on the host: no compilation, memory linear in the mesh.

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
    n = x.shape[0]
    senders, receivers, weight, self_weight = umbrella_weights(np.asarray(faces), n)
    total = np.bincount(receivers, weights=weight, minlength=n) + self_weight
    scale = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
    average = sp.csr_matrix((weight * scale[receivers], (receivers, senders)), shape=(n, n))
    average = average + sp.diags(self_weight * scale)
    keep = (total > 0)[:, None]
    for _ in range(int(steps)):
        x = np.where(keep, x + lam * (average @ x - x), x)
    return x
