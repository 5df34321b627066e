"""Real training meshes: a fixed validation split and connected training patches.

`shared/meshes/train/` (or any folder of meshes) holds real CAD parts and scans of
1k-60k vertices. Whole 40k-vertex meshes make a CPU training step slow and a batch
lopsided, so training sees *connected patches* of a few thousand faces: a breadth-first
region grown over the face adjacency from a random seed face. Patches are cut once, on
the host, from a seeded generator (the set is a pure function of the files and the
seed); rotation and noise are drawn per step by the input pipeline as for any mesh.

The validation split is fixed by file name, not by a random draw: a file is held out
when the first 8 hex digits of the SHA-1 of its name, read as a fraction, fall below
`VALIDATION_FRACTION`. Adding or removing other files never moves a file between
splits, and anyone can recompute the list (`validation_names`).

Coarse copies (`coarse_copies`, `DataConfig.real_coarse_faces`): patches cut from a fine
mesh are finely tessellated, so their clean faces meet at small angles, and a network
learns that larger ones are noise and flattens a coarse mesh (a decimated scan, a low-poly
part). Each training mesh can also be decimated whole (quadric edge collapse) to a few
face counts. Measured (median angle between neighbouring clean faces, quartiles): the
real training patches 1.0 / 2.7 / 4.7°, the procedural training meshes 0 / 1.7 / 3.5°,
the 175 copies at 1,000 and 3,000 faces 3.5 / 7.8 / 13°; benchmark meshes reach 11°
(`cgal_knot2`), 13° (`camel_b`) and 27° (the decimated knight).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import breadth_first_order

from dmd_jax.data.repair import decimate
from dmd_jax.io import SUPPORTED_EXTENSIONS as MESH_SUFFIXES
from dmd_jax.io import is_temp_name, load_mesh
from dmd_jax.topology import face_adjacency_matrix

VALIDATION_FRACTION = 0.15


def is_validation(name: str, fraction: float = VALIDATION_FRACTION) -> bool:
    """Whether the file `name` (base name, e.g. `"cgal_bull.ply"`) is held out."""
    digest = hashlib.sha1(Path(name).name.encode()).hexdigest()
    return int(digest[:8], 16) / 16**8 < fraction


def mesh_files(folder, split: str) -> list[Path]:
    """The mesh files of `folder` in `split` (`"train"`, `"val"` or `"all"`), sorted."""
    if split not in ("train", "val", "all"):
        raise ValueError(f"unknown split {split!r}; use 'train', 'val' or 'all'")
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such mesh folder")
    # A writer's temporary file (an interrupted run's) is never a mesh of the set.
    files = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in MESH_SUFFIXES and p.is_file() and not is_temp_name(p.name)
    )
    if split == "all":
        return files
    return [p for p in files if is_validation(p.name) == (split == "val")]


def validation_names(folder) -> list[str]:
    """File names of the validation split of `folder`."""
    return [p.name for p in mesh_files(folder, "val")]


def connected_patch(
    faces: np.ndarray, n_vertex: int, seed_face: int, max_faces: int, adjacency=None
) -> tuple[np.ndarray, np.ndarray]:
    """A connected region of at most `max_faces` faces grown breadth-first from a face.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: number of vertices.
      seed_face: the face to grow from.
      max_faces: patch size limit.
      adjacency: optional precomputed sparse `[n_face, n_face]` face adjacency.

    Returns:
      `(face_ids [k], vertex_ids [m])`: the patch's faces (BFS order) and the sorted
      vertices they use.
    """
    if adjacency is None:
        adjacency = face_adjacency_matrix(faces, n_vertex)
    order = breadth_first_order(adjacency, seed_face, directed=False, return_predecessors=False)
    face_ids = np.asarray(order[:max_faces])
    vertex_ids = np.unique(faces[face_ids].ravel())
    return face_ids, vertex_ids


def mesh_patches(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    max_faces: int,
    n_patches: int,
    rng: np.random.Generator,
    min_faces: int = 200,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Up to `n_patches` connected patches of a mesh (the whole mesh if it is small).

    Seeds are drawn uniformly among faces; a patch smaller than `min_faces` (a seed in
    a tiny component) is dropped.

    Returns:
      `[(vertices [m, 3], faces [k, 3])]`, each re-indexed.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if f.shape[0] <= max_faces:
        return [(v, f.astype(np.int32))]
    adjacency = face_adjacency_matrix(f, v.shape[0])
    out = []
    for seed_face in rng.choice(f.shape[0], size=n_patches, replace=False):
        pv, pf = patch_mesh(v, f, int(seed_face), max_faces, adjacency)
        if pf.shape[0] >= min_faces:
            out.append((pv, pf))
    return out


def patch_mesh(
    vertices: np.ndarray, faces: np.ndarray, seed_face: int, max_faces: int, adjacency=None
) -> tuple[np.ndarray, np.ndarray]:
    """`connected_patch` as a mesh of its own: `(vertices [m, 3], faces [k, 3] int32)`,
    re-indexed so it holds only the vertices its faces use."""
    face_ids, vertex_ids = connected_patch(
        faces, vertices.shape[0], seed_face, max_faces, adjacency
    )
    remap = np.full(vertices.shape[0], -1, np.int64)
    remap[vertex_ids] = np.arange(vertex_ids.shape[0])
    return vertices[vertex_ids], remap[faces[face_ids]].astype(np.int32)


def load_real_patches(
    folder,
    split: str = "train",
    *,
    max_faces: int = 6000,
    faces_per_patch: int = 12000,
    max_patches: int = 8,
    seed: int = 0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Connected patches of every mesh of `split` in `folder`.

    A mesh of `F` faces gives `clip(F // faces_per_patch + 1, 1, max_patches)` patches
    of at most `max_faces` faces (a mesh under `max_faces` faces is kept whole).

    Args:
      folder: a folder of mesh files.
      split: `"train"`, `"val"` or `"all"` (see `is_validation`).
      max_faces: faces per patch.
      faces_per_patch: how many of a mesh's faces one patch stands for.
      max_patches: patches per mesh at most.
      seed: seed of the patch centres.

    Returns:
      `[(vertices, faces)]` in the files' own coordinates.
    """
    rng = np.random.default_rng(seed)
    out = []
    for path in mesh_files(folder, split):
        v, f = load_mesh(path)
        n = int(np.clip(f.shape[0] // faces_per_patch + 1, 1, max_patches))
        out.extend(mesh_patches(v, f, max_faces=max_faces, n_patches=n, rng=rng))
    return out


def coarse_copies(
    folder, split: str = "train", *, face_counts: Sequence[int], min_faces: int = 200
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every mesh of `split` in `folder` decimated whole to each of `face_counts` that it
    exceeds by at least half (a copy much like the mesh itself adds nothing).

    Args:
      folder: a folder of mesh files.
      split: `"train"`, `"val"` or `"all"` (see `is_validation`).
      face_counts: target face counts, e.g. `(1000, 3000)`.
      min_faces: a copy with fewer faces (a mesh of many tiny components) is dropped.

    Returns:
      `[(vertices, faces)]` in the files' own coordinates.
    """
    counts = sorted({int(c) for c in face_counts})
    out = []
    for path in mesh_files(folder, split):
        v, f = load_mesh(path)
        for n in counts:
            if f.shape[0] >= 1.5 * n:
                cv, cf = decimate(v, f, n)
                if cf.shape[0] >= min_faces:
                    out.append((cv, cf))
    return out


def load_meshes(paths: Sequence) -> list[tuple[np.ndarray, np.ndarray]]:
    """`(vertices, faces)` of every path."""
    return [load_mesh(p) for p in paths]
