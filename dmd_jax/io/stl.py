"""STL, ASCII and binary, through trimesh: a float32 triangle soup, size-checked on
reading and merged back into shared vertices."""

from __future__ import annotations

import warnings

import numpy as np

from dmd_jax.io._files import _BOM, _MeshText


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
