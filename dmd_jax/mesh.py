"""Triangle meshes as arrays: validation and the canonical frame.

`validate_mesh` is the one gate every mesh passes (file readers, `denoise`, the
baselines); `canonical_frame` is the frame the network sees a mesh in; `mean_edge_length`
and `face_normals_np` are the host-side measures the rest of the package shares. Graphs built from
meshes live in `dmd_jax.graph`, file formats in `dmd_jax.io`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dmd_jax.topology import face_adjacency, vertex_edges

# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def validate_mesh(vertices, faces, *, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Checks a triangle mesh and returns it as `(float64 [n, 3], int32 [f, 3])` copies.

    Args:
      vertices: array-like `[n_vertex, 3]` of real numbers (any float or int dtype).
      faces: array-like `[n_face, 3]` of integer vertex indices.
      name: how the mesh is called in error messages (a file name, say).

    Raises:
      ValueError: naming the problem, for empty meshes, wrong shapes or dtypes, NaN or
        infinite coordinates, polygons, negative or out-of-range indices, and faces that
        repeat a vertex.
    """
    v = validate_vertices(vertices, name=name)
    f = validate_faces(faces, v.shape[0], name=name)
    if v.shape[0] >= np.iinfo(np.int32).max or f.shape[0] >= np.iinfo(np.int32).max:
        raise ValueError(f"{name}: mesh too large for int32 indices")
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if repeated.any():
        idx = np.flatnonzero(repeated)
        raise ValueError(
            f"{name}: {idx.size} faces repeat a vertex index (first: face {idx[0]} = "
            f"{f[idx[0]].tolist()}); remove them, e.g. with trimesh's "
            "remove_degenerate_faces"
        )
    return v, f.astype(np.int32)


def validate_faces(
    faces, n_vertex: int, *, name: str = "mesh", allow_empty: bool = False
) -> np.ndarray:
    """Checks face indices alone (`validate_mesh`'s part, for `build_mesh_graph`) and
    returns them as an int64 `[n_face, 3]` copy.

    Raises:
      ValueError: ragged lists, a shape other than `[n_face >= 1, 3]`, indices that are
        not integers, negative, or not below `n_vertex` (checked in the input's own
        dtype: an unsigned or float index beyond int64 is not wrapped).
      TypeError: `n_vertex` is not an integer.

    `allow_empty` takes a mesh of no faces (a graph of isolated vertices).
    """
    if isinstance(n_vertex, bool | np.bool_) or not isinstance(n_vertex, int | np.integer):
        raise TypeError(f"n_vertex must be an integer, got {n_vertex!r}")
    try:
        f = np.asarray(faces)
    except ValueError:  # NumPy refuses ragged nested lists
        raise ValueError(
            f"{name}: vertices and faces must be numeric arrays, not ragged lists"
        ) from None
    if f.dtype == object:
        raise ValueError(f"{name}: vertices and faces must be numeric arrays, not ragged lists")
    if f.ndim != 2:
        raise ValueError(f"{name}: faces must have shape [n_face, 3], got {f.shape}")
    if f.shape[0] == 0 and not (allow_empty and f.shape[1:] in ((0,), (3,))):
        raise ValueError(f"{name}: the mesh has no faces")
    if f.shape[0] == 0:
        return np.zeros((0, 3), np.int64)
    if f.shape[1] != 3:
        raise ValueError(
            f"{name}: faces must be triangles ([n_face, 3]), got polygons with {f.shape[1]} "
            "corners; triangulate them first (load_mesh(..., polygons='triangulate'))"
        )
    if np.issubdtype(f.dtype, np.floating):
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise ValueError(f"{name}: face indices must be integers, got non-integral floats")
    elif not np.issubdtype(f.dtype, np.integer) or np.issubdtype(f.dtype, np.bool_):
        raise ValueError(f"{name}: face indices must be integers, got dtype {f.dtype}")
    # Compared before the cast to int64, which would wrap a uint64 index past 2**63.
    if f.min() < 0:
        raise ValueError(
            f"{name}: negative face index {f.min()} (faces index vertices from 0; negative "
            "indices are not taken from the end)"
        )
    if f.max() >= n_vertex:
        raise ValueError(
            f"{name}: face index {f.max()} is out of range for {n_vertex} vertices (faces "
            f"index vertices 0 to {n_vertex - 1})"
        )
    return f.astype(np.int64)


def validate_vertices(vertices, *, name: str = "mesh") -> np.ndarray:
    """Checks vertex positions alone (`validate_mesh`'s part, for functions whose faces
    are optional) and returns them as a float64 `[n, 3]` copy.

    Raises:
      ValueError: ragged lists, a shape other than `[n_vertex >= 1, 3]`, a dtype other
        than real numbers, NaN or infinite coordinates.
    """
    try:
        v = np.asarray(vertices)
    except ValueError:  # NumPy refuses ragged nested lists
        raise ValueError(
            f"{name}: vertices and faces must be numeric arrays, not ragged lists"
        ) from None
    if v.dtype == object:
        raise ValueError(f"{name}: vertices and faces must be numeric arrays, not ragged lists")
    if v.ndim != 2 or v.shape[-1] != 3:
        raise ValueError(f"{name}: vertices must have shape [n_vertex, 3], got {v.shape}")
    if v.shape[0] == 0:
        raise ValueError(f"{name}: the mesh has no vertices")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise ValueError(f"{name}: vertices must be real numbers, got dtype {v.dtype}")
    v = v.astype(np.float64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"{name}: {idx.size} vertices have NaN or infinite coordinates (first: vertex {idx[0]})"
        )
    return v


# --------------------------------------------------------------------------------------
# Canonical frame
# --------------------------------------------------------------------------------------


class CanonicalFrame(NamedTuple):
    """Centre and scale mapping a mesh so its bounding box is centred, longest side 1."""

    centre: np.ndarray  # [3]
    scale: float

    def apply(self, vertices):
        """World → canonical: `(v - centre) / scale`."""
        return (vertices - self.centre) / self.scale

    def invert(self, vertices):
        """Canonical → world: `v * scale + centre` (the exact inverse of `apply`)."""
        return vertices * self.scale + self.centre


def canonical_frame(vertices) -> CanonicalFrame:
    """The canonical frame of a vertex set: bounding-box centre, longest side as scale."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    with np.errstate(over="ignore"):
        scale = float((hi - lo).max())
    if not np.all(np.isfinite(v)):
        raise ValueError("the mesh has NaN or infinite coordinates: no canonical frame exists")
    if not np.isfinite(scale):
        raise ValueError(
            f"the mesh's extent overflows float64 (coordinates up to {np.abs(v).max():.3g}); "
            "rescale it first"
        )
    if scale <= 0.0:
        raise ValueError(
            "the mesh has zero extent (all vertices coincide): no canonical frame exists"
        )
    return CanonicalFrame(centre=(lo + hi) / 2.0, scale=scale)


def edge_unit_frame(vertices, faces, *, edges=None) -> CanonicalFrame:
    """The `"local"` encoding's frame: centred on the bounding box, the mean edge length
    as unit (`encoding.mesh_frame`).

    Raises:
      ValueError: non-finite coordinates, or a mesh whose edges all have zero length.
    """
    box = canonical_frame(vertices)  # validates finiteness and extent
    h = mean_edge_length(vertices, faces, edges=edges)
    if not (np.isfinite(h) and h > 0):
        raise ValueError("the mesh's mean edge length is zero: no edge-unit frame exists")
    return CanonicalFrame(centre=box.centre, scale=h)


def mean_edge_length(vertices, faces, *, edges=None) -> float:
    """Mean length of the unique undirected edges of a mesh.

    Args:
      vertices: `[n_vertex, 3]`.
      faces: `[n_face, 3]`.
      edges: the unique undirected edges `(a, b)` if already known (e.g.
        `graph.undirected_vertex_edges` of the mesh's graph), to skip their sort.
    """
    v = np.asarray(vertices, dtype=np.float64)
    a, b = vertex_edges(faces, v.shape[0]) if edges is None else edges
    return float(np.linalg.norm(v[a] - v[b], axis=1).mean())


def face_normals_np(vertices, faces) -> np.ndarray:
    """Unit face normals `[n_face, 3]` on the host (NumPy); zero rows for degenerate
    faces. `geometry.face_normals` is the differentiable JAX version."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def edge_dihedral_angles(vertices, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles between the normals of faces sharing an edge, in degrees.

    Args:
      vertices: `[n_vertex, 3]` positions.
      faces: `[n_face, 3]` vertex indices.

    Returns:
      `(a, b, angle)`: the face pairs (`topology.face_adjacency`) and `[n_pair]` angles
      in `[0, 180]`; a pair with a zero-area face gets 0 (no crease can be told there).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    a, b = face_adjacency(f, v.shape[0])
    n = face_normals_np(v, f)
    cos = np.clip(np.sum(n[a] * n[b], axis=1), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    ok = np.any(n[a] != 0, axis=1) & np.any(n[b] != 0, axis=1)  # zero rows: degenerate
    return a, b, np.where(ok, angle, 0.0)
