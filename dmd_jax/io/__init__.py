"""Files: mesh readers and writers, and the atomic write every output goes through.

One module per format (`obj`, `off`, `ply`, `stl`) behind one `load_mesh` and one
`save_mesh`; `_files` holds what they share. A reader keeps vertex order and count (no
merging or cleaning, except STL's triangle soup) and names the file, and the line where
it can, in every error. Writers never leave a half-written file: `atomic_write` writes a
temporary file next to the target and renames it into place.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from dmd_jax.io._files import (
    atomic_write,
    check_not_compressed,
    check_readable_file,
    is_temp_name,
    name_max,
    same_file,
    write_text_atomic,
)
from dmd_jax.io.obj import _read_obj, _write_obj
from dmd_jax.io.off import _read_off, _write_off
from dmd_jax.io.ply import PlyHeader, _read_ply, _write_ply, read_ply_header
from dmd_jax.io.stl import (
    _merge_identical_vertices,
    _read_stl,
    _write_stl,
    binary_stl_size_ok,
    check_float32,
)
from dmd_jax.mesh import validate_mesh

__all__ = [
    "SUPPORTED_EXTENSIONS",
    "PlyHeader",
    "atomic_write",
    "check_readable_file",
    "is_temp_name",
    "load_mesh",
    "name_max",
    "read_ply_header",
    "same_file",
    "save_mesh",
    "write_text_atomic",
]

SUPPORTED_EXTENSIONS = (".obj", ".off", ".ply", ".stl")
# Each format's reader and writer, by suffix.
_READERS = {".obj": _read_obj, ".off": _read_off, ".ply": _read_ply, ".stl": _read_stl}
_WRITERS = {".obj": _write_obj, ".off": _write_off, ".ply": _write_ply, ".stl": _write_stl}


def load_mesh(path, *, polygons: str = "triangulate") -> tuple[np.ndarray, np.ndarray]:
    """Reads a triangle mesh, keeping vertex order and count (no merging, no cleaning).

    OBJ, OFF and PLY keep the file's vertices exactly, unused ones included. STL has no
    shared vertices (it stores a float32 triangle soup), so there bit-identical points
    are merged and numbered in order of first appearance in the faces: the order and
    count of the mesh that was saved come back only if it had no unused vertices and its
    vertices were already numbered in order of first appearance.

    OBJ, ASCII OFF and PLY (ASCII and binary) are read here (trimesh drops the unused
    vertices of an OBJ whose faces carry texture indices, silently skips truncated OFF
    faces, and refuses or misreads valid PLY files with mixed polygon sizes or extra
    face lists); STL goes through trimesh, then its size is checked. A leading UTF-8
    byte-order mark is ignored. Any malformed file, a truncated one or one holding more
    than its header declares included, raises `ValueError` naming the file (and the
    line for OBJ/OFF), never a smaller or shifted mesh.

    Args:
      path: an `.obj`, `.off`, `.ply` or `.stl` file.
      polygons: `"triangulate"` (fan-triangulate quads and n-gons, with a warning saying
        how many) or `"reject"` (raise `ValueError`).

    Returns:
      `(vertices float64 [n, 3], faces int32 [f, 3])`, validated by `validate_mesh`.

    Raises:
      ValueError: unknown extension, unreadable or empty file, a directory or FIFO,
        polygons with `polygons="reject"`, or any problem `validate_mesh` names.
      FileNotFoundError: the file does not exist.
      OSError: the file cannot be opened (permissions, a symlink loop).
    """
    path = Path(path)
    if polygons not in ("triangulate", "reject"):
        raise ValueError(f"polygons must be 'triangulate' or 'reject', got {polygons!r}")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_EXTENSIONS:
        raise ValueError(
            f"{path}: unknown mesh format {path.suffix!r}; use one of "
            + ", ".join(SUPPORTED_EXTENSIONS)
        )
    check_readable_file(path)
    data = path.read_bytes()
    if not data.strip():
        raise ValueError(f"{path}: the file is empty")
    name = str(path)
    if not (suffix == ".stl" and binary_stl_size_ok(data)):  # STL's header is free text
        check_not_compressed(data, name)
    vertices, faces, n_poly = _READERS[suffix](data, name)
    if len(faces) == 0:
        raise ValueError(f"{path}: the file holds no faces (a point cloud is not a mesh)")
    if len(vertices) == 0:
        raise ValueError(f"{path}: the file holds no vertices (empty or corrupt)")
    if n_poly and polygons == "reject":
        raise ValueError(f"{path}: {n_poly} faces are polygons (more than 3 corners)")
    if suffix == ".stl":
        vertices, faces = _merge_identical_vertices(vertices, faces)
    if n_poly:
        warnings.warn(
            f"{path}: triangulated {n_poly} polygon faces (fan triangulation)", stacklevel=2
        )
    return validate_mesh(vertices, faces, name=name)


def save_mesh(path, vertices, faces, *, overwrite: bool = False, protect=()) -> Path:
    """Writes a triangle mesh atomically (OBJ, OFF, PLY or STL).

    OBJ, OFF and PLY keep vertex order, unused vertices and float64 coordinates
    exactly: OBJ and OFF write each coordinate's shortest round-trip decimal (`repr`),
    PLY is binary with `double` coordinates, so `load_mesh` reads back the very same
    float64 values, at any scale. STL stores a float32 triangle soup (the format
    allows nothing else): coordinates are rounded to float32, and vertex order, unused
    vertices and the sharing of vertices are lost (`load_mesh` merges identical points
    again, see there). An STL is refused, not rounded silently, when float32 cannot hold
    the mesh: coordinates beyond its range, or rounding that would move vertices by more
    than `stl.STL_ROUNDING_TOLERANCE` of the median edge length (a small part at survey
    coordinates, ~1e6).

    Raises:
      FileExistsError: `path` exists and `overwrite` is False.
      ValueError: unknown extension, `path` in `protect`, an invalid mesh, or an STL that
        float32 cannot hold.
    """
    path = Path(path)
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise ValueError(
            f"{path}: unknown mesh format {path.suffix!r}; use one of "
            + ", ".join(SUPPORTED_EXTENSIONS)
        )
    v, f = validate_mesh(vertices, faces, name=str(path))
    if path.suffix.lower() == ".stl":
        check_float32(str(path), v, f)
    writer = _WRITERS[path.suffix.lower()]

    def write(tmp):
        writer(tmp, v, f)

    return atomic_write(path, write, overwrite=overwrite, protect=protect)
