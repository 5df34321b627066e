"""STL, ASCII and binary, through trimesh: a float32 triangle soup, size-checked on
reading and merged back into shared vertices."""

from __future__ import annotations

import warnings

import numpy as np

import dmd_jax.io._syntax as _syntax
from dmd_jax.io._files import _BOM, _MeshText, _text_of


def binary_stl_size_ok(data: bytes) -> bool:
    """Whether `data` is exactly as long as a binary STL of its header's triangle count."""
    return len(data) >= 84 and len(data) == 84 + 50 * int(np.frombuffer(data[80:84], "<u4")[0])


def _is_ascii_stl(data: bytes) -> bool:
    """ASCII STL starts with `solid` (a binary one may too: its size decides first)."""
    return not binary_stl_size_ok(data) and data.lstrip()[:5].lower() == b"solid"


# The tokens of one facet of an ASCII STL, in order; None stands for a number.
_FACET = ("facet", "normal", None, None, None, "outer", "loop") + ("vertex", None, None, None) * 3
_FACET_END = ("endloop", "endfacet")
_FACET_WIDTH = len(_FACET) + len(_FACET_END)
_NUMBER_COLUMNS = [i for i, word in enumerate(_FACET) if word is None]
_VERTEX_COLUMNS = [c for c in _NUMBER_COLUMNS if c > 6]


def _ascii_stl_body(text: str, name: str) -> list[tuple[int, str]]:
    """`(line, token)` of every token of the facets, the `solid NAME` and `endsolid
    NAME` lines left out (a name is free text); refuses a file without `endsolid`."""
    out: list[tuple[int, str]] = []
    ended = False
    for lineno, line in enumerate(_syntax.lines(text), 1):
        parts = _syntax.tokens(line)
        if not parts:
            continue
        word = parts[0].lower()
        if word in ("solid", "endsolid"):
            ended = word == "endsolid"
            continue
        out.extend((lineno, t) for t in parts)
        ended = False
    if not ended:
        raise ValueError(f"{name}: truncated ASCII STL (no closing 'endsolid')")
    return out


def _read_ascii_stl(data: bytes, name: str) -> _MeshText:
    """An ASCII STL's facets (`facet normal n n n / outer loop / vertex x y z` x 3 /
    `endloop / endfacet`), read with the lines, tokens and numbers of `_syntax`."""
    body = _ascii_stl_body(_text_of(data, name), name)
    words = [t.lower() for _, t in body]
    n = len(words) // _FACET_WIDTH
    expected = _FACET + _FACET_END
    if len(words) == n * _FACET_WIDTH:
        # The common layout, checked and read in bulk.
        table = np.array(words, dtype=object).reshape(n, _FACET_WIDTH) if n else None
        keywords = [i for i, w in enumerate(expected) if w is not None]
        if n == 0 or all((table[:, i] == expected[i]).all() for i in keywords):
            columns = [body[r * _FACET_WIDTH + c] for r in range(n) for c in _VERTEX_COLUMNS]
            numbers = [body[r * _FACET_WIDTH + c] for r in range(n) for c in _NUMBER_COLUMNS]
            try:
                _syntax.floats([t for _, t in numbers])
            except ValueError:
                pass  # named with its line below
            else:
                v = _syntax.floats([t for _, t in columns]).reshape(-1, 3)
                return _MeshText(v, np.arange(len(v), dtype=np.int64).reshape(-1, 3), 0)
    # Token by token, naming the line of the first thing out of place.
    coords: list[float] = []
    i = 0
    while i < len(body):
        for want in expected:
            if i >= len(body):
                raise ValueError(f"{name}: truncated ASCII STL (the last facet is cut short)")
            lineno, token = body[i]
            if want is None:
                try:
                    value = _syntax.float_of(token)
                except ValueError as exc:
                    raise ValueError(f"{name}: line {lineno}: {exc}") from None
                coords.append(value)
            elif token.lower() != want:
                raise ValueError(
                    f"{name}: line {lineno}: expected {want!r} in an ASCII STL facet, got "
                    f"{token[:30]!r}"
                )
            i += 1
    # Each facet gave 3 normal and 9 vertex numbers: keep the vertices.
    v = np.array(coords, np.float64).reshape(-1, 12)[:, 3:].reshape(-1, 3)
    return _MeshText(v, np.arange(len(v), dtype=np.int64).reshape(-1, 3), 0)


def _check_binary_stl(data: bytes, name: str) -> None:
    """A binary STL's size is fixed by its triangle count."""
    if binary_stl_size_ok(data):
        return
    promised = (
        f"its header promises {int(np.frombuffer(data[80:84], '<u4')[0])} triangles "
        f"({84 + 50 * int(np.frombuffer(data[80:84], '<u4')[0])} bytes), the file has "
        f"{len(data)}"
        if len(data) >= 84
        else f"the file has only {len(data)} bytes"
    )
    raise ValueError(f"{name}: truncated or corrupt binary STL: {promised}")


def _read_stl(data: bytes, name: str) -> _MeshText:
    """STL: ASCII by our reader (`_syntax`'s numbers), binary through trimesh, with the
    size check trimesh skips."""
    from io import BytesIO  # the standard library's, not this module

    import trimesh

    if data.startswith(_BOM) and data[3:].lstrip()[:5].lower() == b"solid":
        # A BOM before an ASCII STL's `solid`; a binary STL's free 80-byte header may
        # start with any bytes, so only strip it when what follows is ASCII STL.
        data = data[3:]
    if _is_ascii_stl(data):
        return _read_ascii_stl(data, name)
    _check_binary_stl(data, name)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = trimesh.load(
                BytesIO(data),
                file_type="stl",
                process=False,
                maintain_order=True,
                force="mesh",
                skip_materials=True,
            )
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


# The most float32's rounding may move a vertex, as a fraction of the mesh's median edge
# length, before an STL output is refused: a thousandth keeps every feature the mesh
# resolves (rounding at the unit scale moves ~1e-7 of it; at a 1e6 offset, ~0.03 units).
STL_ROUNDING_TOLERANCE = 1e-3


def check_float32(name: str, v: np.ndarray, f: np.ndarray) -> None:
    """Refuses a mesh STL's float32 cannot store: beyond float32's range, or so far from
    the origin for its size that rounding to float32 would move its vertices by more
    than `STL_ROUNDING_TOLERANCE` of its median edge length (survey coordinates).

    Args:
      name: the output, named in the error.
      v: `[n_vertex, 3]` float64 positions.
      f: `[n_face, 3]` vertex indices.

    Raises:
      ValueError: saying which, and that PLY, OBJ and OFF keep float64.
    """
    largest = float(np.abs(v).max()) if v.size else 0.0
    limit = float(np.finfo(np.float32).max)
    keep = "save it as .ply, .obj or .off instead (float64, exact)"
    if largest > limit:
        raise ValueError(
            f"{name}: STL stores float32, whose largest value is {limit:.4g}; this mesh "
            f"has coordinates up to {largest:.4g}: {keep}"
        )
    moved = float(np.abs(v.astype(np.float32).astype(np.float64) - v).max()) if v.size else 0.0
    if moved == 0.0:
        return
    corners = v[f]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).ravel()
    edges = edges[edges > 0]
    median = float(np.median(edges)) if edges.size else 0.0
    if moved > STL_ROUNDING_TOLERANCE * median:
        raise ValueError(
            f"{name}: STL stores float32, which would move vertices by up to {moved:.3g} at "
            f"these coordinates (up to {largest:.4g}), more than "
            f"{STL_ROUNDING_TOLERANCE:g} of the median edge length {median:.3g}: {keep}, "
            "or move the mesh near the origin first"
        )


def _write_stl(tmp, v: np.ndarray, f: np.ndarray) -> None:
    """Binary STL through trimesh (float32 coordinates, a triangle soup)."""
    import trimesh

    data = trimesh.Trimesh(vertices=v, faces=f, process=False).export(file_type="stl")
    with open(tmp, "wb") as fh:
        fh.write(data if isinstance(data, bytes) else data.encode())
