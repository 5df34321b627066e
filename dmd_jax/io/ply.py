"""PLY, ASCII and binary: a checked header, its `vertex` and `face` elements, and the
binary little-endian writer."""

from __future__ import annotations

import re
from typing import NamedTuple

import numpy as np

import dmd_jax.io._syntax as _syntax
from dmd_jax.io._files import _BOM, _MeshText

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
        that is not a non-negative integer, an element or a property declared twice.
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
    lines = _syntax.lines(data[: end.start()].decode("ascii", errors="replace"))[1:]
    fmt = None
    elements: list[_PlyElement] = []
    for lineno, line in enumerate(lines, 2):
        parts = _syntax.tokens(line)
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
            if any(e.name == parts[1] for e in elements):
                # Two `vertex` elements: which one is the mesh would be a guess.
                raise ValueError(bad + f"element {parts[1][:30]!r} is declared twice")
            elements.append(_PlyElement(parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(bad + "a property before any element")
            prop = parts[-1]
            if any(p.name == prop for p in elements[-1].properties):
                # Read by name, a repeated property would silently be one of its columns.
                raise ValueError(
                    bad + f"property {prop[:30]!r} appears twice in element "
                    f"{elements[-1].name[:30]!r}"
                )
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


def _numbers(tokens: list[bytes], name: str, what: str, integer: bool = False) -> np.ndarray:
    """Tokens of an ASCII PLY as float64 (exact for every integer a mesh can index): real
    numbers as C `strtod` reads them, or, for `integer` (a property of an integer type,
    a list length), integers as `strtol` does (`_syntax`)."""
    try:
        if integer:
            return _syntax.ints(tokens).astype(np.float64)
        return _syntax.floats(tokens)
    except _syntax.TokenError as exc:
        kind = " of an integer type" if integer else ""
        raise _syntax.TokenError(f"{name}: {what}{kind}: {exc}", exc.token) from None


def _is_int(code: str | None) -> bool:
    return code is not None and code[0] in "iu"


def _list_length(token: bytes, name: str, what: str) -> int:
    """A list length read from ASCII; -1 for a negative one."""
    k = int(_numbers([token], name, what, integer=True)[0])
    return k if k >= 0 else -1


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
        k = _list_length(tokens[q], name, what)
        lengths.append(k)
        q += 1 + max(k, 0)
    width = q - t
    if all(k >= 0 for k in lengths) and t + width * el.count <= len(tokens):
        flat = tokens[t : t + width * el.count]
        block = _numbers(flat, name, what).reshape(el.count, width)
        out, col, ok = {}, 0, True
        for prop in props:
            if prop.count_dtype is None:
                if _is_int(prop.dtype):
                    _numbers(flat[col::width], name, what, integer=True)
                out[prop.name] = block[:, col]
                col += 1
                continue
            k = int(block[0, col])
            if not (block[:, col] == k).all():
                ok = False
                break
            _numbers(flat[col::width], name, what, integer=True)
            if _is_int(prop.dtype):
                for c in range(col + 1, col + 1 + k):
                    _numbers(flat[c::width], name, what, integer=True)
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
            k = _list_length(tokens[t], name, what)
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
        values = _numbers([tokens[j] for j in picks[i]], name, what, _is_int(prop.dtype))
        if prop.count_dtype is not None:
            values = (np.array(lens[i], np.int64), values)
        out[prop.name] = values
    return out, t


def _with_line(message: str, data: bytes, body: int, token: bytes, name: str) -> str:
    """`message` (`NAME: ...`) with the line of `token`'s first place in the body."""
    for m in re.finditer(rb"[^ \t\n\r\v\f]+", data[body:]):
        if m.group() == token:
            line = data[: body + m.start()].count(b"\n") + 1
            return message.replace(f"{name}: ", f"{name}: line {line}: ", 1)
    return message


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
        try:
            for el in header.elements:
                found[el.name], t = _ply_ascii_element(tokens, t, el, name)
        except _syntax.TokenError as exc:
            raise ValueError(_with_line(str(exc), data, body, exc.token, name)) from None
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
    if "face" not in found:
        others = [e.name for e in header.elements if e.name != "vertex"]
        if others:
            # Not a point cloud: its faces (if any) sit in an element PLY does not name so.
            raise ValueError(
                f"{name}: the PLY has no 'face' element (it declares "
                f"{', '.join(repr(e.name[:30]) for e in header.elements)}); PLY names the "
                "faces' element 'face'"
            )
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
