"""Network-free routes the denoising policy may take instead of the network.

A route here is one of the network's own candidate normal fields taken alone: the
bilateral pre-filter of the `"local"` encoding (`encoding.bilateral_face_normals`: faces
sharing an edge and the face itself, spatial σ one mean edge, range σ `sigma_r`, after
`passes` passes), then the vertex update of the normal-first head
(`geometry.fit_vertices_to_normals`, `VERTEX_ITERATIONS` iterations). The network mixes
twelve such candidates per face; where noise is light on a mesh of large flats and sharp
creases the bundled network's mix ends two to three times above its own sharpest field
(validation split, 0.1 edges: `cgal_boeing` 6.17° against 3.06° for σ 0.2 after 60
passes), and the learned choice of `dmd_jax.presmooth` may then run the field alone
(`policy.DenoisePolicy.route_fields`).

Host side (NumPy: no JAX import, no compilation): each pass is a gather over the padded
table of each face's edge neighbours that the encoding's ELL path reads, in chunks of
faces, so memory stays linear in the mesh.
`tests/test_routes.py` checks the result against the encoding's JAX field and the JAX
vertex update.
"""

from __future__ import annotations

import numpy as np

from dmd_jax.constants import FILTER_SPATIAL_SIGMA
from dmd_jax.graph import ell_layout
from dmd_jax.mesh import edge_unit_frame
from dmd_jax.topology import face_adjacency

# The normal-first head's vertex update count of the bundled configuration.
VERTEX_ITERATIONS = 10
# Faces per chunk of a pass: bounds the temporaries (about 200 bytes a face).
_CHUNK = 1 << 20


def _neighbour_table(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """`(neighbours, real)` `[n_face, slots]`: the padded table of the faces sharing an
    edge with each face and the face itself, as the encoding's `MeshGraph.face_ell`
    (`topology.face_adjacency` plus self loops, through `graph.ell_layout`); `real` is
    False on the unused slots, which point at the face itself."""
    n_face = faces.shape[0]
    a, b = face_adjacency(faces, n_vertex)
    loops = np.arange(n_face)
    layout = ell_layout(
        np.concatenate([a, b, loops]),
        np.concatenate([b, a, loops]),
        np.ones(2 * a.size + n_face, np.float32),
        n_face,
    )
    return layout.neighbours, layout.weights > 0


def field_normals(x, faces, sigma_r: float, passes: int) -> np.ndarray:
    """The encoding's bilateral face-normal field after `passes` passes, on the host.

    Args:
      x: `[n_vertex, 3]` positions in mean-edge units (the `"local"` frame).
      faces: `[n_face, 3]` vertex indices.
      sigma_r: range σ.
      passes: passes, >= 0.

    Returns:
      `[n_face, 3]` unit normals (0 for a degenerate face with no neighbour normal).
    """
    f = np.asarray(faces, np.int64)
    p = x[f]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = _unit(cross)
    c = p.mean(axis=1)
    table, real = _neighbour_table(f, x.shape[0])
    spatial = np.empty(table.shape)
    for lo in range(0, f.shape[0], _CHUNK):
        t = table[lo : lo + _CHUNK]
        d2 = np.sum((c[t] - c[lo : lo + _CHUNK, None, :]) ** 2, axis=-1)
        spatial[lo : lo + _CHUNK] = (
            real[lo : lo + _CHUNK] * area[t] * np.exp(-d2 * (0.5 / FILTER_SPATIAL_SIGMA**2))
        )
    del real
    inv_sr2 = 1.0 / (sigma_r * sigma_r)
    for _ in range(int(passes)):
        out = np.empty_like(n)
        for lo in range(0, f.shape[0], _CHUNK):
            t = table[lo : lo + _CHUNK]
            nk = n[t]  # [chunk, slots, 3]
            agree = np.einsum("fkc,fc->fk", nk, n[lo : lo + _CHUNK])
            w = spatial[lo : lo + _CHUNK] * np.exp((agree - 1.0) * inv_sr2)
            out[lo : lo + _CHUNK] = np.einsum("fk,fkc->fc", w, nk)
        n = _unit(out)
    return n


def fit_vertices(x, faces, normals, iterations: int = VERTEX_ITERATIONS) -> np.ndarray:
    """Sun et al.'s vertex update toward fixed face normals, as
    `geometry.fit_vertices_to_normals` with every vertex free, on the host."""
    import scipy.sparse as sp

    f = np.asarray(faces, np.int64)
    x = np.array(x, np.float64)
    n = np.asarray(normals, np.float64)
    corner_vertex = f.ravel()  # corner 3 i + j is vertex f[i, j]
    degree = np.maximum(np.bincount(corner_vertex, minlength=x.shape[0]), 1)
    # `[n_vertex, 3 n_face]`: each vertex's mean over its corners. One sparse product
    # per iteration is three times faster than a bincount per coordinate at 100k faces.
    mean_over_corners = sp.csr_matrix(
        (1.0 / degree[corner_vertex], (corner_vertex, np.arange(corner_vertex.size))),
        shape=(x.shape[0], corner_vertex.size),
    )
    for _ in range(int(iterations)):
        p = x[f]  # [n_face, 3 corners, 3]
        d = p.mean(axis=1, keepdims=True) - p
        move = n[:, None, :] * np.einsum("fkc,fc->fk", d, n)[..., None]
        x = x + mean_over_corners @ move.reshape(-1, 3)
    return x


def field_route(x, faces, sigma_r: float, passes: int) -> np.ndarray:
    """One candidate field alone: `field_normals`, then `fit_vertices`.

    Args:
      x: `[n_vertex, 3]` noisy positions in mean-edge units.
      faces: `[n_face, 3]` vertex indices.
      sigma_r, passes: the field (`field_normals`).

    Returns:
      `[n_vertex, 3]` float64 positions in the same frame.
    """
    x = np.asarray(x, np.float64)
    return fit_vertices(x, faces, field_normals(x, faces, sigma_r, passes))


def run_route(vertices, faces, sigma_r: float, passes: int) -> np.ndarray:
    """`field_route` in the `"local"` frame of the noisy mesh (`encoding.mesh_frame`:
    bounding-box centre, mean edge length as unit), the frame `denoise` runs the network
    in; `[n_vertex, 3]` float64 positions in the input frame."""
    v = np.asarray(vertices, np.float64)
    frame = edge_unit_frame(v, faces)
    return frame.invert(field_route(frame.apply(v), faces, sigma_r, passes))


def _unit(n: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)
