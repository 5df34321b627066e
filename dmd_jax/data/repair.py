"""Mesh repair and checks: cleaning, decimation, isotropic remeshing and what is wrong with
a mesh as training data.

Used by the shape generator (`dmd_jax.data.shapes`: every drawn shape is remeshed and
checked here), by the datasets (`dmd_jax.data.dataset`: files converted into a dataset
are cleaned and remeshed) and by the real-mesh training data (`dmd_jax.data.real`:
coarse copies by decimation). The pymeshlab filters are wrapped so that every function
takes and returns plain arrays (`vertices float64 [n, 3]`, `faces int32 [f, 3]`).
"""

from __future__ import annotations

import numpy as np

from dmd_jax.mesh import validate_mesh


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _orient_outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Flips all faces of a consistently wound closed surface if it encloses negative volume."""
    return f[:, ::-1].copy() if _signed_volume(v, f) < 0 else f


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
