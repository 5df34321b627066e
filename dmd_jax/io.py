"""Files: mesh readers and writers, and the atomic write every output goes through.

A reader keeps vertex order and count (no merging or cleaning, except STL's triangle
soup) and names the file, and the line where it can, in every error. Writers never leave
a half-written file: `atomic_write` writes a temporary file next to the target and
renames it into place.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dmd_jax.mesh import validate_mesh

SUPPORTED_EXTENSIONS = (".obj", ".off", ".ply", ".stl")


# --------------------------------------------------------------------------------------
# I/O
# --------------------------------------------------------------------------------------


class _MeshText(NamedTuple):
    """What a reader found: vertices, triangulated faces and how many were polygons."""

    vertices: np.ndarray  # [n_vertex, 3] float64
    faces: np.ndarray  # [n_face, 3] int64
    n_polygons: int


def _fan(corners: list[int], out: list[int]) -> None:
    """Appends the fan triangulation `(c0, c_i, c_i+1)` of one face to a flat list."""
    c0 = corners[0]
    for i in range(1, len(corners) - 1):
        out += (c0, corners[i], corners[i + 1])


def _text_of(data: bytes, name: str) -> str:
    """The text of an OBJ or OFF file; NUL bytes mean it is not text at all."""
    if b"\0" in data:
        raise ValueError(f"{name}: binary data in a text mesh format (corrupt file?)")
    # Numbers are ASCII; anything else can only sit in comments and names, so bytes that
    # are not UTF-8 (a Latin-1 comment, say) must not stop the file from loading.
    return data.decode("utf-8", errors="replace")


def _read_obj(data: bytes, name: str) -> _MeshText:
    """Reads the `v` and `f` statements of a Wavefront OBJ file; everything else is ignored.

    Keeps every vertex in file order (unused ones too, which trimesh drops when faces
    carry texture or normal indices), resolves negative (relative) indices, and names
    the line of any malformed statement.
    """
    text = _text_of(data, name)
    if "\\" in text:
        text = text.replace("\\\r\n", " ").replace("\\\n", " ")  # continuation lines
    coords: list[tuple[float, float, float]] = []
    flat: list[int] = []
    n_poly = 0
    max_index, max_line = 0, 0
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.lstrip()
        if not s.startswith(("v ", "v\t", "f ", "f\t")):
            continue
        parts = s.split("#", 1)[0].split()
        if parts[0] == "v":
            if len(parts) < 4:
                raise ValueError(
                    f"{name}: line {lineno}: a vertex needs 3 coordinates, got {len(parts) - 1}"
                )
            try:
                coords.append((float(parts[1]), float(parts[2]), float(parts[3])))
            except ValueError:
                raise ValueError(
                    f"{name}: line {lineno}: vertex coordinates are not numbers: "
                    f"{' '.join(parts[1:4])[:60]!r}"
                ) from None
            continue
        tokens = parts[1:]
        if len(tokens) < 3:
            raise ValueError(
                f"{name}: line {lineno}: a face needs at least 3 vertices, got {len(tokens)}"
            )
        corners = []
        for token in tokens:
            try:
                i = int(token.split("/", 1)[0])
            except ValueError:
                raise ValueError(
                    f"{name}: line {lineno}: face index {token[:30]!r} is not an integer"
                ) from None
            if i > 0:
                if i > max_index:
                    max_index, max_line = i, lineno
                corners.append(i - 1)
            elif i < 0:
                if -i > len(coords):
                    raise ValueError(
                        f"{name}: line {lineno}: relative face index {i} points before the "
                        f"first vertex ({len(coords)} vertices so far)"
                    )
                corners.append(len(coords) + i)
            else:
                raise ValueError(
                    f"{name}: line {lineno}: face index 0 is invalid (OBJ indices start at 1)"
                )
        n_poly += len(corners) > 3
        _fan(corners, flat)
    if max_index > len(coords):
        raise ValueError(
            f"{name}: line {max_line}: face index {max_index} is out of range for the "
            f"file's {len(coords)} vertices (OBJ indices start at 1)"
        )
    return _MeshText(
        np.array(coords, np.float64).reshape(-1, 3),
        np.array(flat, np.int64).reshape(-1, 3),
        n_poly,
    )


def _read_off(data: bytes, name: str) -> _MeshText:
    """Reads an ASCII OFF file (also COFF, NOFF, STOFF: extra columns are ignored).

    The counts in the header are checked against the file: a truncated file, or a face
    with fewer than 3 corners, is an error rather than a smaller mesh.
    """
    rows = (
        (lineno, tokens)
        for lineno, line in enumerate(_text_of(data, name).splitlines(), 1)
        if (tokens := line.split("#", 1)[0].split())
    )
    first = next(rows, None)
    if first is None:
        raise ValueError(f"{name}: the file holds no data (only comments or blank lines)")
    lineno, head = first
    keyword = head[0]
    if not keyword.upper().endswith("OFF"):
        raise ValueError(f"{name}: not an OFF file (line {lineno} starts with {keyword[:20]!r})")
    if "BINARY" in (t.upper() for t in head[1:]):
        raise ValueError(f"{name}: binary OFF is not supported; save it as ASCII OFF")
    prefix = keyword[:-3]
    if "4" in prefix or prefix.endswith("n"):
        raise ValueError(f"{name}: OFF variant {keyword!r} (not 3-D points) is not supported")
    counts = head[1:]
    if not counts:
        nxt = next(rows, None)
        if nxt is None:
            raise ValueError(f"{name}: truncated after the OFF header (no counts line)")
        lineno, counts = nxt
    try:
        n_vertex, n_face = int(counts[0]), int(counts[1])
    except (ValueError, IndexError):
        raise ValueError(
            f"{name}: line {lineno}: expected the counts 'n_vertex n_face n_edge', got "
            f"{' '.join(counts)[:60]!r}"
        ) from None
    if n_vertex < 0 or n_face < 0:
        raise ValueError(f"{name}: line {lineno}: negative counts {n_vertex} {n_face}")
    coords: list[tuple[float, float, float]] = []
    for _ in range(n_vertex):
        row = next(rows, None)
        if row is None:
            raise ValueError(
                f"{name}: truncated: the header promises {n_vertex} vertices, the file "
                f"ends after {len(coords)}"
            )
        lineno, tokens = row
        try:
            coords.append((float(tokens[0]), float(tokens[1]), float(tokens[2])))
        except (ValueError, IndexError):
            raise ValueError(
                f"{name}: line {lineno}: a vertex needs 3 numbers, got {' '.join(tokens)[:60]!r}"
            ) from None
    flat: list[int] = []
    n_poly = 0
    for done in range(n_face):
        row = next(rows, None)
        if row is None:
            raise ValueError(
                f"{name}: truncated: the header promises {n_face} faces, the file ends after {done}"
            )
        lineno, tokens = row
        try:
            k = int(tokens[0])
            corners = [int(t) for t in tokens[1 : 1 + k]]
        except ValueError:
            raise ValueError(
                f"{name}: line {lineno}: a face is 'k i_1 ... i_k' with integers, got "
                f"{' '.join(tokens)[:60]!r}"
            ) from None
        if k < 3 or len(corners) < k:
            raise ValueError(
                f"{name}: line {lineno}: a face needs k >= 3 corners and k indices, got "
                f"{' '.join(tokens)[:60]!r}"
            )
        for c in corners:
            # Checked here, not in validate_mesh: an index beyond int64 cannot reach it.
            if c < 0:
                raise ValueError(
                    f"{name}: line {lineno}: negative face index {c} (indices start at 0)"
                )
            if c >= n_vertex:
                raise ValueError(
                    f"{name}: line {lineno}: face index {c} is out of range for {n_vertex} vertices"
                )
        n_poly += k > 3
        _fan(corners, flat)
    return _MeshText(
        np.array(coords, np.float64).reshape(-1, 3),
        np.array(flat, np.int64).reshape(-1, 3),
        n_poly,
    )


def _ply_header_counts(data: bytes) -> dict[str, int]:
    """`{element name: count}` from a PLY header (`{}` when there is no readable header)."""
    end = data.find(b"end_header", 0, 1 << 16)
    if end < 0:
        return {}
    counts = {}
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[2].isdigit():
            counts[parts[1]] = int(parts[2])
    return counts


def _check_stl_size(data: bytes, name: str) -> None:
    """A binary STL's size is fixed by its triangle count; ASCII STL ends with `endsolid`."""
    if len(data) >= 84:
        n = int(np.frombuffer(data[80:84], "<u4")[0])
        if len(data) == 84 + 50 * n:
            return
    if data.lstrip()[:5].lower() == b"solid":
        if b"endsolid" not in data[-1024:].lower():
            raise ValueError(f"{name}: truncated ASCII STL (no closing 'endsolid')")
        return
    promised = (
        f"its header promises {n} triangles ({84 + 50 * n} bytes), the file has {len(data)}"
        if len(data) >= 84
        else f"the file has only {len(data)} bytes"
    )
    raise ValueError(f"{name}: truncated or corrupt binary STL: {promised}")


def _read_with_trimesh(data: bytes, suffix: str, name: str) -> _MeshText:
    """PLY (ASCII or binary) and STL through trimesh, with the checks trimesh skips."""
    from io import BytesIO  # the standard library's, not this module

    import trimesh

    if suffix == ".stl":
        _check_stl_size(data, name)
    if suffix == ".ply":
        declared = sum(_ply_header_counts(data).values())
        # Every element takes at least one byte, in ASCII or binary: a header that
        # promises more would make trimesh allocate for counts the file cannot hold.
        if declared > len(data):
            raise ValueError(
                f"{name}: the header declares {declared} elements, more than the file's "
                f"{len(data)} bytes can hold (truncated or corrupt)"
            )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = trimesh.load(
                BytesIO(data),
                file_type=suffix[1:],
                process=False,
                maintain_order=True,
                force="mesh",
                skip_materials=True,
            )
    except ImportError:
        # trimesh guesses the encoding of undecodable text with an optional package.
        raise ValueError(f"{name}: corrupt file (neither valid binary nor UTF-8 text)") from None
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise ValueError(f"{name}: could not read the mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3), np.int64)), np.int64)
    n_poly = 0
    if suffix == ".ply":
        declared = _ply_header_counts(data)
        n_v, n_f = declared.get("vertex"), declared.get("face")
        if n_v is not None and len(vertices) != n_v:
            raise ValueError(
                f"{name}: the header declares {n_v} vertices, the file holds {len(vertices)}"
            )
        if n_f is not None and len(faces) < n_f:
            raise ValueError(
                f"{name}: the header declares {n_f} faces, only {len(faces)} triangles "
                "could be read (truncated, or faces with fewer than 3 corners)"
            )
        # trimesh fan-triangulates PLY polygons: every extra corner is an extra triangle.
        n_poly = 0 if n_f is None else len(faces) - n_f
    return _MeshText(vertices, faces, n_poly)


def _merge_identical_vertices(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Merges bit-identical vertices, numbered in order of first appearance in `faces`.

    STL stores a triangle soup (three vertices per face, no shared indices); without
    this every face would be its own component and no graph op could see a neighbour.
    """
    f = np.asarray(faces, dtype=np.int64)
    # Adding 0.0 turns -0.0 into 0.0, so the two zeros merge.
    v = np.asarray(vertices, dtype=np.float64)[f.ravel()] + 0.0
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return v[first[order]], rank[inverse.reshape(-1)].reshape(f.shape)


def load_mesh(path, *, polygons: str = "triangulate") -> tuple[np.ndarray, np.ndarray]:
    """Reads a triangle mesh, keeping vertex order and count (no merging, no cleaning).

    OBJ, OFF and PLY keep the file's vertices exactly, unused ones included. STL has no
    shared vertices (it stores a float32 triangle soup), so there bit-identical points
    are merged and numbered in order of first appearance in the faces: the order and
    count of the mesh that was saved come back only if it had no unused vertices and its
    vertices were already numbered in order of first appearance.

    OBJ and ASCII OFF are read here (trimesh drops the unused vertices of an OBJ whose
    faces carry texture indices, and silently skips truncated OFF faces); PLY and STL go
    through trimesh, then their header counts and sizes are checked. Any malformed
    file, truncated one included, raises `ValueError` naming the file (and the line for
    OBJ/OFF), never a smaller mesh.

    Args:
      path: an `.obj`, `.off`, `.ply` or `.stl` file.
      polygons: `"triangulate"` (fan-triangulate quads and n-gons, with a warning saying
        how many; for PLY the count is the number of extra triangles) or `"reject"`
        (raise `ValueError`).

    Returns:
      `(vertices float64 [n, 3], faces int32 [f, 3])`, validated by `validate_mesh`.

    Raises:
      ValueError: unknown extension, unreadable or empty file, polygons with
        `polygons="reject"`, or any problem `validate_mesh` names.
      FileNotFoundError: the file does not exist.
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
    if path.is_dir():
        raise ValueError(f"{path}: is a directory, not a mesh file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    data = path.read_bytes()
    if not data.strip():
        raise ValueError(f"{path}: the file is empty")
    name = str(path)
    if suffix == ".obj":
        read = _read_obj(data, name)
    elif suffix == ".off":
        read = _read_off(data, name)
    else:
        read = _read_with_trimesh(data, suffix, name)
    vertices, faces, n_poly = read
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


def atomic_write(path, write_fn, *, overwrite: bool = False, protect=()) -> Path:
    """Writes a file by `write_fn(tmp_path)` then renames it into place.

    Args:
      path: destination.
      write_fn: callable that writes the whole file to the temporary path it is given.
      overwrite: replace an existing file; without it an existing file is an error.
      protect: paths that must never be written (the user's inputs).
    """
    path = Path(path)
    for p in protect:
        if Path(p).exists() and path.exists() and os.path.samefile(p, path):
            raise ValueError(f"{path}: refusing to overwrite the input file")
        if Path(p).resolve() == path.resolve():
            raise ValueError(f"{path}: refusing to overwrite the input file")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass overwrite=True / --overwrite)")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path.parent}: output directory does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write_fn(tmp)
        # mkstemp creates 0600 files; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_text_atomic(path, text: str) -> Path:
    """Replaces `path` with `text` atomically (a report, a log summary, a JSON file).

    Args:
      path: destination; its folder must exist. An existing file is replaced.
      text: the whole content.
    """
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text), overwrite=True)


def save_mesh(path, vertices, faces, *, overwrite: bool = False, protect=()) -> Path:
    """Writes a triangle mesh atomically (OBJ, OFF, PLY or STL).

    OBJ and OFF keep vertex order and float64 coordinates: 17 decimals read back the
    same float64 where `|x| >= 0.1` and within 1e-17 below. PLY keeps the order but trimesh
    writes float32 coordinates. STL stores a float32 triangle soup: vertex order,
    unused vertices and the sharing of vertices are lost (`load_mesh` merges identical
    points again, see there).

    Raises:
      FileExistsError: `path` exists and `overwrite` is False.
      ValueError: unknown extension, `path` in `protect`, or an invalid mesh.
    """
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise ValueError(
            f"{path}: unknown mesh format {path.suffix!r}; use one of "
            + ", ".join(SUPPORTED_EXTENSIONS)
        )
    v, f = validate_mesh(vertices, faces, name=str(path))
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
    file_type = path.suffix.lower()[1:]

    def write(tmp):
        # trimesh's default of 8 decimals would lose precision on small-scale meshes.
        options = {"digits": 17} if file_type in ("obj", "off") else {}
        data = mesh.export(file_type=file_type, **options)
        mode = "wb" if isinstance(data, bytes) else "w"
        with open(tmp, mode) as fh:
            fh.write(data)

    return atomic_write(path, write, overwrite=overwrite, protect=protect)
