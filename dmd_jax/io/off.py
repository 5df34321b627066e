"""OFF (ASCII; COFF, NOFF and STOFF read too): read and written."""

from __future__ import annotations

import numpy as np

import dmd_jax.io._syntax as _syntax
from dmd_jax.io._files import _fan, _MeshText, _text_of, _write_rows, not_this_format


def _read_off(data: bytes, name: str) -> _MeshText:
    """Reads an ASCII OFF file (also COFF, NOFF, STOFF: extra columns are ignored).

    The counts in the header are checked against the file: a truncated file, or a face
    with fewer than 3 corners, is an error rather than a smaller mesh.
    """
    rows = (
        (lineno, tokens)
        for lineno, line in enumerate(_syntax.lines(_text_of(data, name)), 1)
        if (tokens := _syntax.tokens(line.split("#", 1)[0]))
    )
    first = next(rows, None)
    if first is None:
        raise ValueError(f"{name}: the file holds no data (only comments or blank lines)")
    lineno, head = first
    keyword = head[0]
    if not keyword.upper().endswith("OFF"):
        not_this_format(
            data, name, "OFF", f"line {lineno} starts with {keyword[:20]!r}, not an OFF keyword"
        )
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
        n_vertex, n_face = (int(c) for c in _syntax.ints(counts[:3])[:2])
    except ValueError:
        raise ValueError(
            f"{name}: line {lineno}: expected the counts 'n_vertex n_face n_edge' (integers), "
            f"got {' '.join(counts)[:60]!r}"
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
        if len(tokens) < 3:
            raise ValueError(
                f"{name}: line {lineno}: a vertex needs 3 numbers, got {' '.join(tokens)[:60]!r}"
            )
        try:
            # Every column is a number: x y z, then a colour, normal or texture.
            values = _syntax.floats(tokens)
        except ValueError as exc:
            raise ValueError(f"{name}: line {lineno}: vertex coordinate {exc}") from None
        coords.append((values[0], values[1], values[2]))
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
            k = _syntax.int_of(tokens[0])
            corners = [_syntax.int_of(t) for t in tokens[1 : 1 + max(k, 0)]]
            _syntax.floats(tokens[1 + max(k, 0) :])  # a colour, if any
        except ValueError as exc:
            raise ValueError(
                f"{name}: line {lineno}: a face is 'k i_1 ... i_k' with integers, but {exc}"
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


def _write_off(tmp, v: np.ndarray, f: np.ndarray) -> None:
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write(f"OFF\n{len(v)} {len(f)} 0\n")
        _write_rows(fh, "%r %r %r\n", v)
        _write_rows(fh, "3 %d %d %d\n", f)
