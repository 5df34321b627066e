"""Wavefront OBJ: its `v` and `f` statements, read and written."""

from __future__ import annotations

import numpy as np

import dmd_jax.io._syntax as _syntax
from dmd_jax.io._files import _fan, _MeshText, _text_of, _write_rows, not_this_format, sniff_format


def _read_obj(data: bytes, name: str) -> _MeshText:
    """Reads the `v` and `f` statements of a Wavefront OBJ file; everything else is ignored.

    Keeps every vertex in file order (unused ones too, which trimesh drops when faces
    carry texture or normal indices), resolves negative (relative) indices, and names
    the line of any malformed statement.
    """
    text = _text_of(data, name)
    plain = _read_plain_obj(text)
    return plain if plain is not None else _read_obj_lines(text, name)


def _read_obj_lines(text: str, name: str) -> _MeshText:
    """`_read_obj`, one line at a time (lines, tokens and numbers as in `_syntax`)."""
    if "\\" in text:
        text = text.replace("\\\r\n", " ").replace("\\\n", " ").replace("\\\r", " ")
    coords: list[tuple[float, float, float]] = []
    flat: list[int] = []
    n_poly = 0
    max_index, max_line = 0, 0
    for lineno, line in enumerate(_syntax.lines(text), 1):
        parts = _syntax.tokens(line.split("#", 1)[0])
        if not parts or parts[0] not in ("v", "f"):
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise ValueError(
                    f"{name}: line {lineno}: a vertex needs 3 coordinates, got {len(parts) - 1}"
                )
            try:
                # Every number of the statement (x y z, and w or a colour) is checked.
                values = _syntax.floats(parts[1:])
            except ValueError as exc:
                raise ValueError(f"{name}: line {lineno}: vertex coordinate {exc}") from None
            coords.append((values[0], values[1], values[2]))
            continue
        tokens = parts[1:]
        if len(tokens) < 3:
            raise ValueError(
                f"{name}: line {lineno}: a face needs at least 3 vertices, got {len(tokens)}"
            )
        corners = []
        for token in tokens:
            # `v`, `v/vt`, `v//vn` or `v/vt/vn`: every part present is an integer.
            fields = token.split("/")
            try:
                if len(fields) > 3 or (len(fields) == 3 and fields[2] == ""):
                    raise ValueError(f"{token[:30]!r} is not an integer")
                i = _syntax.int_of(fields[0])
                for extra in fields[1:]:
                    if extra:
                        _syntax.int_of(extra)
            except ValueError as exc:
                raise ValueError(f"{name}: line {lineno}: face index {exc}") from None
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
    if not coords and not flat:
        # No `v` or `f` statement: another format under an .obj name (OFF text, say) is
        # named as such; an OBJ of comments only holds no faces (`load_mesh` says so).
        data = text.encode("utf-8", "replace")
        if sniff_format(data) not in (None, "OBJ"):
            not_this_format(data, name, "OBJ", "no 'v' or 'f' statement")
    return _MeshText(
        np.array(coords, np.float64).reshape(-1, 3),
        np.array(flat, np.int64).reshape(-1, 3),
        n_poly,
    )


# Characters that send a file to the line-by-line reader: comments past the header,
# texture or normal indices, continuation lines, and the line breaks and blanks other
# than "\n", " " and "\t" (`str.split` would treat the rest otherwise than `_syntax`).
_NOT_PLAIN = ("#", "/", "\\", "\r", "\x0b", "\x0c", "\x1c", "\x1d", "\x1e", "\x1f", "\n\n")


def _read_plain_obj(text: str) -> _MeshText | None:
    """The common OBJ of one `v x y z` or `f i j k` statement (positive indices) per
    line after a header of `#` comments, parsed in bulk (80k faces: 0.05 s against
    0.35 s line by line); None for any other file, which `_read_obj` reads line by line
    with the same result and names the line of an error."""
    text = text.replace("\r\n", "\n")
    if "\r" in text:  # a lone CR ends a line (a comment too): the line reader
        return None
    start = 0
    while text.startswith("#", start):  # the header comments
        start = text.find("\n", start) + 1
        if start == 0:
            return None
    body = text[start:]
    if not body.isascii() or any(c in body for c in _NOT_PLAIN):
        return None
    tokens = body.split()
    lines = body.count("\n") + (not body.endswith("\n"))
    if not tokens or len(tokens) != 4 * lines or body.startswith("\n"):
        return None
    rows = np.array(tokens, dtype=object).reshape(-1, 4)
    is_v, is_f = rows[:, 0] == "v", rows[:, 0] == "f"
    if not (is_v | is_f).all():
        return None
    try:
        v = _syntax.floats(rows[is_v, 1:].ravel().tolist()).reshape(-1, 3)
        f = _syntax.ints(rows[is_f, 1:].ravel().tolist()).reshape(-1, 3)
    except ValueError:
        return None  # the line reader names the line
    if f.size and (f.min() < 1 or f.max() > len(v)):
        return None
    return _MeshText(v.reshape(-1, 3), (f - 1).reshape(-1, 3), 0)


def _write_obj(tmp, v: np.ndarray, f: np.ndarray) -> None:
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write(f"# dmd_jax: {len(v)} vertices, {len(f)} faces\n")
        _write_rows(fh, "v %r %r %r\n", v)
        _write_rows(fh, "f %d %d %d\n", f.astype(np.int64) + 1)
