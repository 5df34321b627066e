"""Files: mesh readers and writers, and the atomic write every output goes through.

A reader keeps vertex order and count (no merging or cleaning, except STL's triangle
soup) and names the file, and the line where it can, in every error. Writers never leave
a half-written file: `atomic_write` writes a temporary file next to the target and
renames it into place.
"""

from __future__ import annotations

import os
import re
import stat
import tempfile
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dmd_jax.mesh import validate_mesh

SUPPORTED_EXTENSIONS = (".obj", ".off", ".ply", ".stl")
_BOM = b"\xef\xbb\xbf"  # the UTF-8 byte-order mark


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
    # Windows editors start UTF-8 files with a byte-order mark: glued to the first
    # keyword it would hide that statement (an OBJ's first `v` line, say).
    return data.removeprefix(_BOM).decode("utf-8", errors="replace")


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
    extra = next(rows, None)
    if extra is not None:
        # Data past the declared faces: the header or the file is wrong, and either
        # way cutting the mesh to the header's count would be a silent guess.
        raise ValueError(
            f"{name}: line {extra[0]}: data after the {n_face} faces the header declares "
            "(more faces than declared, or a wrong header)"
        )
    return _MeshText(
        np.array(coords, np.float64).reshape(-1, 3),
        np.array(flat, np.int64).reshape(-1, 3),
        n_poly,
    )


# --------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------

# PLY's scalar types and their NumPy codes (without byte order).
_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
# The header may carry long comments, but not without bound: past this it is not PLY.
_PLY_MAX_HEADER = 1 << 20


class _PlyProperty(NamedTuple):
    name: str
    dtype: str  # NumPy code of the value (of each item, for a list)
    count_dtype: str | None  # NumPy code of a list's length; None for a scalar


class _PlyElement(NamedTuple):
    name: str
    count: int
    properties: list[_PlyProperty]


class PlyHeader(NamedTuple):
    """A parsed PLY header: `format` is `ascii` or a binary one; `body` where data starts."""

    format: str
    elements: list[_PlyElement]
    body: int

    def counts(self) -> dict[str, int]:
        """`{element name: declared count}`."""
        return {e.name: e.count for e in self.elements}


def read_ply_header(data: bytes, name: str) -> PlyHeader:
    """Parses and checks a PLY header; any line it does not understand is an error.

    A corrupt header must not be skipped over: one mangled `property` line shifts every
    later column, which would read as a valid but wrong mesh.

    Raises:
      ValueError: not PLY, no `end_header`, an unknown keyword, type or format, a count
        that is not a non-negative integer.
    """
    data = data.removeprefix(_BOM)
    if not re.match(rb"ply[ \t]*\r?\n", data):
        raise ValueError(f"{name}: not a PLY file (it does not start with 'ply')")
    end = re.search(rb"(?:^|\n)end_header[ \t]*\r?\n", data[:_PLY_MAX_HEADER])
    if end is None:
        raise ValueError(
            f"{name}: no 'end_header' line in the first {_PLY_MAX_HEADER >> 20} MiB "
            "(a truncated or corrupt PLY header)"
        )
    lines = data[: end.start()].decode("ascii", errors="replace").splitlines()[1:]
    fmt = None
    elements: list[_PlyElement] = []
    for lineno, line in enumerate(lines, 2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        bad = f"{name}: header line {lineno}: "
        if parts[0] == "format":
            if len(parts) != 3 or parts[1] not in _PLY_FORMATS:
                raise ValueError(bad + f"unknown format {line.strip()[:60]!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(r"[0-9]+", parts[2]):
                raise ValueError(
                    bad + f"an element needs a name and a count >= 0, got {line.strip()[:60]!r}"
                )
            elements.append(_PlyElement(parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(bad + "a property before any element")
            if len(parts) == 5 and parts[1] == "list":
                count_t, item_t = _PLY_TYPES.get(parts[2]), _PLY_TYPES.get(parts[3])
                if count_t is None or item_t is None or count_t[0] == "f":
                    raise ValueError(bad + f"unknown list types in {line.strip()[:60]!r}")
                elements[-1].properties.append(_PlyProperty(parts[4], item_t, count_t))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1].properties.append(_PlyProperty(parts[2], _PLY_TYPES[parts[1]], None))
            else:
                raise ValueError(bad + f"unreadable property {line.strip()[:60]!r}")
        else:
            raise ValueError(bad + f"unknown keyword {parts[0][:30]!r}")
    if fmt is None:
        raise ValueError(f"{name}: the PLY header has no 'format' line")
    return PlyHeader(fmt, elements, end.end())


def _gather(buf: np.ndarray, offsets: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Values of `dtype` starting at the byte `offsets` of `buf` (uint8)."""
    idx = offsets[:, None] + np.arange(dtype.itemsize)
    return buf[idx].reshape(-1).view(dtype)


def _ply_binary_element(data: bytes, pos: int, el: _PlyElement, order: str, name: str):
    """`({property: values or (counts, items)}, end)` of one binary element at `pos`."""
    props = el.properties
    if el.count == 0 or not props:
        return {p.name: np.zeros(0) for p in props}, pos
    types = [np.dtype(order + p.dtype) for p in props]
    counts_t = [None if p.count_dtype is None else np.dtype(order + p.count_dtype) for p in props]
    truncated = ValueError(
        f"{name}: truncated PLY: the file ends inside the {el.count} '{el.name}' elements "
        "the header declares"
    )
    # Fast path: every list as long as in the first record (all triangles, say).
    lengths, p = [], pos
    for t, ct in zip(types, counts_t, strict=True):
        if ct is None:
            p += t.itemsize
            continue
        if p + ct.itemsize > len(data):
            raise truncated
        k = int(np.frombuffer(data, ct, 1, p)[0])
        lengths.append(k)
        p += ct.itemsize + max(k, 0) * t.itemsize
    if all(k >= 0 for k in lengths):
        fields, it = [], iter(lengths)
        for i, (t, ct) in enumerate(zip(types, counts_t, strict=True)):
            if ct is None:
                fields.append((f"p{i}", t))
            else:
                fields += [(f"n{i}", ct), (f"p{i}", t, (next(it),))]
        record = np.dtype(fields)
        if pos + record.itemsize * el.count <= len(data):
            arr = np.frombuffer(data, record, el.count, pos)
            uniform = all(
                (arr[f"n{i}"] == arr[f"n{i}"][0]).all()
                for i, ct in enumerate(counts_t)
                if ct is not None
            )
            if uniform:
                out = {}
                for i, (prop, ct) in enumerate(zip(props, counts_t, strict=True)):
                    values = arr[f"p{i}"]
                    if ct is None:
                        out[prop.name] = values
                    else:
                        out[prop.name] = (arr[f"n{i}"].astype(np.int64), values.reshape(-1))
                return out, pos + record.itemsize * el.count
    # Lists of mixed lengths (triangles and quads): walk the records one by one. The size
    # guard in `_read_ply` bounds the walk by the file's size.
    import struct

    codes = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}
    count_fmt = [None if p.count_dtype is None else order + codes[p.count_dtype] for p in props]
    sizes = [t.itemsize for t in types]
    starts = [np.empty(el.count, np.int64) for _ in props]
    lens = [None if c is None else np.empty(el.count, np.int64) for c in count_fmt]
    p, n = pos, len(data)
    for r in range(el.count):
        for i, cf in enumerate(count_fmt):
            if cf is None:
                starts[i][r] = p
                p += sizes[i]
                continue
            if p + counts_t[i].itemsize > n:
                raise truncated
            (k,) = struct.unpack_from(cf, data, p)
            if k < 0:
                raise ValueError(f"{name}: element '{el.name}' {r}: negative list length {k}")
            p += counts_t[i].itemsize
            starts[i][r], lens[i][r] = p, k
            p += k * sizes[i]
        if p > n:
            raise truncated
    buf = np.frombuffer(data, np.uint8)
    out = {}
    for i, prop in enumerate(props):
        if lens[i] is None:
            out[prop.name] = _gather(buf, starts[i], types[i])
        else:
            total = int(lens[i].sum())
            first = np.repeat(starts[i], lens[i])
            rank = np.arange(total) - np.repeat(np.cumsum(lens[i]) - lens[i], lens[i])
            out[prop.name] = (lens[i], _gather(buf, first + rank * sizes[i], types[i]))
    return out, p


def _numbers(tokens: list[bytes], name: str, what: str) -> np.ndarray:
    """Tokens of an ASCII PLY as float64 (exact for every integer a mesh can index)."""
    try:
        # float() one token at a time: a NumPy bytes array would be as wide as the
        # longest token, which a hostile file can make enormous.
        return np.fromiter(map(float, tokens), np.float64, len(tokens))
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise ValueError(f"{name}: {what}: {bad[:30]!r} is not a number") from None


def _is_float(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _list_length(x: float) -> int:
    """A list length read from ASCII as an int; -1 for anything that is not a count
    (negative, fractional, infinite or NaN)."""
    return int(x) if np.isfinite(x) and x >= 0 and x == int(x) else -1


def _ply_ascii_element(tokens: list[bytes], t: int, el: _PlyElement, name: str):
    """`({property: values or (counts, items)}, next token)` of one ASCII element."""
    props = el.properties
    what = f"element '{el.name}'"
    truncated = ValueError(
        f"{name}: truncated PLY: the file ends inside the {el.count} '{el.name}' elements "
        "the header declares"
    )
    if el.count == 0 or not props:
        return {p.name: np.zeros(0) for p in props}, t
    # Fast path: every list as long as in the first record.
    lengths, q = [], t
    for prop in props:
        if q >= len(tokens):
            raise truncated
        if prop.count_dtype is None:
            q += 1
            continue
        k = _list_length(_numbers([tokens[q]], name, what)[0])
        lengths.append(k)
        q += 1 + max(k, 0)
    width = q - t
    if all(k >= 0 for k in lengths) and t + width * el.count <= len(tokens):
        block = _numbers(tokens[t : t + width * el.count], name, what).reshape(el.count, width)
        out, col, ok = {}, 0, True
        for prop in props:
            if prop.count_dtype is None:
                out[prop.name] = block[:, col]
                col += 1
                continue
            k = int(block[0, col])
            if not (block[:, col] == k).all():
                ok = False
                break
            items = block[:, col + 1 : col + 1 + k].ravel()
            out[prop.name] = (np.full(el.count, k, np.int64), items)
            col += 1 + k
        if ok:
            return out, t + width * el.count
    # Lists of mixed lengths: one record at a time (bounded by the number of tokens).
    picks: list[list[int]] = [[] for _ in props]
    lens: list[list[int]] = [[] for _ in props]
    for r in range(el.count):
        for i, prop in enumerate(props):
            if t >= len(tokens):
                raise truncated
            if prop.count_dtype is None:
                picks[i].append(t)
                t += 1
                continue
            k = _list_length(_numbers([tokens[t]], name, what)[0])
            if k < 0:
                raise ValueError(
                    f"{name}: {what} {r}: list length {tokens[t][:30]!r} is not a count"
                )
            if t + 1 + k > len(tokens):
                raise truncated
            picks[i].extend(range(t + 1, t + 1 + k))
            lens[i].append(k)
            t += 1 + k
    out = {}
    for i, prop in enumerate(props):
        values = _numbers([tokens[j] for j in picks[i]], name, what)
        if prop.count_dtype is not None:
            values = (np.array(lens[i], np.int64), values)
        out[prop.name] = values
    return out, t


def _read_ply(data: bytes, name: str) -> _MeshText:
    """Reads an ASCII or binary PLY: its `vertex` x, y, z and its `face` index lists.

    Our own reader, not trimesh's: it reads faces of mixed corner counts in binary files
    and faces carrying further lists (texture coordinates) in ASCII ones, both of which
    trimesh refuses or misreads, and it refuses a file that contradicts its header
    (too short, or data left over after the declared elements).
    """
    header = read_ply_header(data, name)
    data = data.removeprefix(_BOM)
    body = header.body
    order = _PLY_FORMATS[header.format]
    # Every element with a property takes at least a byte (binary) or a token of two
    # (ASCII): a header promising more than the file holds is refused before any
    # allocation of its size.
    least = 0
    for el in header.elements:
        if el.properties:
            per = (
                2 * len(el.properties)
                if order is None
                else sum(np.dtype(p.count_dtype or p.dtype).itemsize for p in el.properties)
            )
            least += el.count * per
    if least > len(data) - body + (1 if order is None else 0):
        declared = ", ".join(f"{e.count} {e.name}" for e in header.elements)
        raise ValueError(
            f"{name}: the header declares {declared} elements, more than the file's "
            f"{len(data)} bytes can hold (truncated or corrupt)"
        )
    found: dict[str, dict] = {}
    if order is None:
        tokens = data[body:].split()
        t = 0
        for el in header.elements:
            found[el.name], t = _ply_ascii_element(tokens, t, el, name)
        if t < len(tokens):
            raise ValueError(
                f"{name}: {len(tokens) - t} values after the last element the header "
                "declares (more elements than declared, or a wrong header)"
            )
    else:
        pos = body
        for el in header.elements:
            found[el.name], pos = _ply_binary_element(data, pos, el, order, name)
        if data[pos:].strip(b" \t\r\n\0"):
            raise ValueError(
                f"{name}: {len(data) - pos} bytes after the last element the header "
                "declares (more elements than declared, or a wrong header)"
            )
    vertex = found.get("vertex")
    if vertex is None or not all(isinstance(vertex.get(c), np.ndarray) for c in ("x", "y", "z")):
        raise ValueError(f"{name}: the PLY has no 'vertex' element with x, y, z properties")
    vertices = np.stack([vertex[c].astype(np.float64) for c in ("x", "y", "z")], axis=1)
    face = found.get("face", {})
    lists = {k: v for k, v in face.items() if isinstance(v, tuple)}
    key = next((k for k in ("vertex_indices", "vertex_index") if k in lists), None)
    if key is None and len(lists) == 1:
        key = next(iter(lists))
    if key is None:
        if lists:
            raise ValueError(
                f"{name}: the 'face' element has no 'vertex_indices' list (it has "
                f"{', '.join(sorted(lists))})"
            )
        return _MeshText(vertices, np.zeros((0, 3), np.int64), 0)
    lens, items = lists[key]
    if len(lens) and lens.min() < 3:
        i = int(np.argmin(lens))
        raise ValueError(f"{name}: face {i} has {lens[i]} corners (a face needs at least 3)")
    items = np.asarray(items)
    if items.size:
        bad = (items < 0) | (items >= len(vertices)) | (items != np.floor(items))
        if bad.any():
            x = items[np.flatnonzero(bad)[0]]
            shown = f"{int(x)}" if np.isfinite(x) and x == np.floor(x) else f"{x!r}"
            problem = "is not an integer" if shown == f"{x!r}" else "is out of range"
            raise ValueError(f"{name}: face index {shown} {problem} for {len(vertices)} vertices")
    items = items.astype(np.int64)
    # Fan triangulation of every face at once: face i gives lens[i] - 2 triangles.
    start = np.cumsum(lens) - lens
    n_tri = lens - 2
    owner = np.repeat(np.arange(len(lens)), n_tri)
    j = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    base = start[owner]
    faces = np.stack([items[base], items[base + j + 1], items[base + j + 2]], axis=1)
    return _MeshText(vertices, faces, int(np.count_nonzero(lens > 3)))


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


def _read_stl(data: bytes, name: str) -> _MeshText:
    """STL (ASCII or binary) through trimesh, with the size checks trimesh skips."""
    from io import BytesIO  # the standard library's, not this module

    import trimesh

    if data.startswith(_BOM) and data[3:].lstrip()[:5].lower() == b"solid":
        # A BOM before an ASCII STL's `solid`; a binary STL's free 80-byte header may
        # start with any bytes, so only strip it when what follows is ASCII STL.
        data = data[3:]
    suffix = ".stl"
    _check_stl_size(data, name)
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
    return _MeshText(vertices, faces, 0)


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


def check_readable_file(path, what: str = "mesh file") -> None:
    """Refuses, with the reason, a path that is not a regular file one can read.

    Says which of the look-alikes of "no such file" it is: a directory, a FIFO or
    device (reading one could block for ever), a symlink loop or a dangling symlink.
    `what` names the expected file in the messages.

    Raises:
      FileNotFoundError: nothing there, or a symlink to nothing.
      ValueError: a directory, or not a regular file.
      OSError: the path cannot be examined (a symlink loop, no permission).
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        if path.is_symlink():
            raise FileNotFoundError(
                f"{path}: a symbolic link to {os.readlink(path)}, which does not exist"
            ) from None
        raise FileNotFoundError(f"{path}: no such {what}") from None
    except OSError as exc:  # ELOOP (a symlink loop), EACCES on a folder, ENAMETOOLONG
        raise OSError(exc.errno, f"{path}: cannot open it ({exc.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise ValueError(f"{path}: is a directory, not a {what}")
    if not stat.S_ISREG(info.st_mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(info.st_mode) else "not a regular file"
        raise ValueError(f"{path}: is {kind}; save the {what} to a regular file first")


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
    if suffix == ".obj":
        read = _read_obj(data, name)
    elif suffix == ".off":
        read = _read_off(data, name)
    elif suffix == ".ply":
        read = _read_ply(data, name)
    else:
        read = _read_stl(data, name)
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


# Rows per formatting call of the text writers: big enough that the per-call overhead
# vanishes, small enough that the text of one block stays a few tens of MB.
_WRITE_BLOCK = 1 << 18


def _write_rows(fh, row: str, rows: np.ndarray) -> None:
    """Writes `row % tuple(r)` for every row, a block at a time.

    `%r` of a Python float is its shortest repr, which reads back as the same float64
    (every finite value, 1e-300 and 1e300 alike); one `%` over a whole block keeps the
    formatting in C.
    """
    for s in range(0, len(rows), _WRITE_BLOCK):
        block = rows[s : s + _WRITE_BLOCK]
        fh.write((row * len(block)) % tuple(block.ravel().tolist()))


def _write_obj(tmp, v: np.ndarray, f: np.ndarray) -> None:
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write(f"# dmd_jax: {len(v)} vertices, {len(f)} faces\n")
        _write_rows(fh, "v %r %r %r\n", v)
        _write_rows(fh, "f %d %d %d\n", f.astype(np.int64) + 1)


def _write_off(tmp, v: np.ndarray, f: np.ndarray) -> None:
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write(f"OFF\n{len(v)} {len(f)} 0\n")
        _write_rows(fh, "%r %r %r\n", v)
        _write_rows(fh, "3 %d %d %d\n", f)


def _write_ply(tmp, v: np.ndarray, f: np.ndarray) -> None:
    """Binary little-endian PLY with float64 coordinates (exact) and int32 indices."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by dmd_jax\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    faces = np.empty(len(f), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    faces["n"] = 3
    faces["i"] = f
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(np.ascontiguousarray(v, "<f8").tobytes())
        fh.write(faces.tobytes())


def save_mesh(path, vertices, faces, *, overwrite: bool = False, protect=()) -> Path:
    """Writes a triangle mesh atomically (OBJ, OFF, PLY or STL).

    OBJ, OFF and PLY keep vertex order, unused vertices and float64 coordinates
    exactly: OBJ and OFF write each coordinate's shortest round-trip decimal (`repr`),
    PLY is binary with `double` coordinates, so `load_mesh` reads back the very same
    float64 values, at any scale. STL stores a float32 triangle soup (the format
    allows nothing else): coordinates are rounded to float32, and vertex order, unused
    vertices and the sharing of vertices are lost (`load_mesh` merges identical points
    again, see there).

    Raises:
      FileExistsError: `path` exists and `overwrite` is False.
      ValueError: unknown extension, `path` in `protect`, or an invalid mesh.
    """
    path = Path(path)
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise ValueError(
            f"{path}: unknown mesh format {path.suffix!r}; use one of "
            + ", ".join(SUPPORTED_EXTENSIONS)
        )
    v, f = validate_mesh(vertices, faces, name=str(path))
    file_type = path.suffix.lower()[1:]
    writers = {"obj": _write_obj, "off": _write_off, "ply": _write_ply}

    def write(tmp):
        if file_type in writers:
            writers[file_type](tmp, v, f)
            return
        import trimesh

        data = trimesh.Trimesh(vertices=v, faces=f, process=False).export(file_type=file_type)
        with open(tmp, "wb") as fh:
            fh.write(data if isinstance(data, bytes) else data.encode())

    return atomic_write(path, write, overwrite=overwrite, protect=protect)
