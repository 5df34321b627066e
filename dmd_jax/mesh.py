"""Meshes as index arrays: validation, the `MeshGraph`, batching, canonical frame and I/O.

Everything here runs on the host in NumPy, once per mesh. The model only ever sees the
index arrays of a `MeshGraph`, so no dense adjacency matrix is built anywhere.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:  # ops imports this module (and JAX); the layouts are only annotated here
    from dmd_jax.ops import EllLayout

SUPPORTED_EXTENSIONS = (".obj", ".off", ".ply", ".stl")


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def validate_mesh(vertices, faces, *, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Checks a triangle mesh and returns it as `(float64 [n, 3], int32 [f, 3])` copies.

    Args:
      vertices: array-like `[n_vertex, 3]` of real numbers (any float or int dtype).
      faces: array-like `[n_face, 3]` of integer vertex indices.
      name: how the mesh is called in error messages (a file name, say).

    Raises:
      ValueError: naming the problem, for empty meshes, wrong shapes or dtypes, NaN or
        infinite coordinates, polygons, negative or out-of-range indices, and faces that
        repeat a vertex.
    """
    try:
        v = np.asarray(vertices)
        f = np.asarray(faces)
    except ValueError:  # NumPy refuses ragged nested lists
        raise ValueError(
            f"{name}: vertices and faces must be numeric arrays, not ragged lists"
        ) from None
    if v.dtype == object or f.dtype == object:
        raise ValueError(f"{name}: vertices and faces must be numeric arrays, not ragged lists")
    if v.ndim != 2 or v.shape[-1] != 3:
        raise ValueError(f"{name}: vertices must have shape [n_vertex, 3], got {v.shape}")
    if v.shape[0] == 0:
        raise ValueError(f"{name}: the mesh has no vertices")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise ValueError(f"{name}: vertices must be real numbers, got dtype {v.dtype}")
    if f.ndim != 2:
        raise ValueError(f"{name}: faces must have shape [n_face, 3], got {f.shape}")
    if f.shape[0] == 0:
        raise ValueError(f"{name}: the mesh has no faces")
    if f.shape[1] != 3:
        raise ValueError(
            f"{name}: faces must be triangles ([n_face, 3]), got polygons with {f.shape[1]} "
            "corners; triangulate them first (load_mesh(..., polygons='triangulate'))"
        )
    if np.issubdtype(f.dtype, np.floating):
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise ValueError(f"{name}: face indices must be integers, got non-integral floats")
    elif not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name}: face indices must be integers, got dtype {f.dtype}")
    v = v.astype(np.float64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"{name}: {idx.size} vertices have NaN or infinite coordinates (first: vertex {idx[0]})"
        )
    f = f.astype(np.int64)
    if f.min() < 0:
        raise ValueError(f"{name}: negative face index {f.min()} (indices start at 0)")
    if f.max() >= v.shape[0]:
        raise ValueError(f"{name}: face index {f.max()} is out of range for {v.shape[0]} vertices")
    if v.shape[0] >= np.iinfo(np.int32).max or f.shape[0] >= np.iinfo(np.int32).max:
        raise ValueError(f"{name}: mesh too large for int32 indices")
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if repeated.any():
        idx = np.flatnonzero(repeated)
        raise ValueError(
            f"{name}: {idx.size} faces repeat a vertex index (first: face {idx[0]} = "
            f"{f[idx[0]].tolist()}); remove them, e.g. with trimesh's "
            "remove_degenerate_faces"
        )
    return v, f.astype(np.int32)


# --------------------------------------------------------------------------------------
# MeshGraph
# --------------------------------------------------------------------------------------


class MeshGraph(NamedTuple):
    """The index arrays of one mesh, or of a padded disjoint union of meshes.

    Sizes are static shapes: `n_vertex = vertex_graph.shape[0]`,
    `n_face = faces.shape[0]`, `n_graph = n_vertex_per_graph.shape[0]`. In a padded batch
    the padding vertices and faces belong to an extra last graph and are `False` in the
    masks; their edges carry weight 0.

    The two ELL fields are optional, precomputed padded-neighbour tables of the same GCN
    operators (see `with_ell_layout`); the model aggregates through them when they are
    set. They are `None` (an empty pytree: jit, `jax.tree.map` and sharding skip it)
    unless `with_ell_layout` added them, and `batch_mesh_graphs` and `pad_mesh_graph`
    drop them, because renumbering or adding nodes invalidates the tables.

    Attributes:
      faces: `[n_face, 3]` int32 vertex indices.
      vertex_senders: `[n_vertex_edge]` int32; primal edges in both directions plus one
        self loop per vertex, sorted by receiver.
      vertex_receivers: `[n_vertex_edge]` int32, sorted ascending.
      vertex_edge_weight: `[n_vertex_edge]` float32, `1/sqrt(d_s d_r)` with the degrees of
        `A + I` (the symmetric GCN normalisation).
      face_senders: `[n_face_edge]` int32; dual edges (faces sharing an edge; on a
        non-manifold edge every pair of its faces) both ways plus self loops.
      face_receivers: `[n_face_edge]` int32, sorted ascending.
      face_edge_weight: `[n_face_edge]` float32, symmetric normalisation of the dual graph.
      vertex_face_degree: `[n_vertex]` float32, number of faces incident to each vertex.
      vertex_graph: `[n_vertex]` int32 graph id of every vertex.
      face_graph: `[n_face]` int32 graph id of every face.
      vertex_mask: `[n_vertex]` bool, `False` on padding.
      face_mask: `[n_face]` bool, `False` on padding.
      n_vertex_per_graph: `[n_graph]` int32, real (unpadded) vertex count of every graph.
      n_face_per_graph: `[n_graph]` int32, real face count of every graph.
      vertex_ell: `None`, or the `ops.EllLayout` of the vertex edges, three
        `[n_vertex, width]` tables.
      face_ell: `None`, or the `ops.EllLayout` of the face edges, three
        `[n_face, width]` tables.
    """

    faces: np.ndarray
    vertex_senders: np.ndarray
    vertex_receivers: np.ndarray
    vertex_edge_weight: np.ndarray
    face_senders: np.ndarray
    face_receivers: np.ndarray
    face_edge_weight: np.ndarray
    vertex_face_degree: np.ndarray
    vertex_graph: np.ndarray
    face_graph: np.ndarray
    vertex_mask: np.ndarray
    face_mask: np.ndarray
    n_vertex_per_graph: np.ndarray
    n_face_per_graph: np.ndarray
    vertex_ell: EllLayout | None = None
    face_ell: EllLayout | None = None

    @property
    def n_vertex(self) -> int:
        return self.vertex_graph.shape[0]

    @property
    def n_face(self) -> int:
        return self.faces.shape[0]

    @property
    def n_graph(self) -> int:
        return self.n_vertex_per_graph.shape[0]


def _sorted_unique(keys: np.ndarray) -> np.ndarray:
    """`np.unique(keys)` for a 1-D integer array, by a sort and a mask of first entries.

    NumPy 2.4's `np.unique` hashes: 3 s for 1M int64 keys here against 0.07 s for
    `np.sort`, which made `build_mesh_graph` take a minute at 1M vertices.
    """
    k = np.sort(keys)
    if k.size == 0:
        return k
    return k[np.concatenate([[True], k[1:] != k[:-1]])]


def _symmetric_with_self_loops(
    senders: np.ndarray, receivers: np.ndarray, n_node: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique directed edges of `A + I`, sorted by receiver, and their GCN weights."""
    loops = np.arange(n_node, dtype=np.int64)
    s = np.concatenate([senders, receivers, loops])
    r = np.concatenate([receivers, senders, loops])
    key = _sorted_unique(r * n_node + s)
    r, s = np.divmod(key, n_node)
    degree = np.bincount(r, minlength=n_node).astype(np.float64)
    weight = 1.0 / np.sqrt(degree[s] * degree[r])
    return s.astype(np.int32), r.astype(np.int32), weight.astype(np.float32)


def vertex_edges(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected primal edges `[n_edge, 2]` (sorted pairs) of a triangle mesh."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.sort(e, axis=1)
    key = _sorted_unique(e[:, 0] * n_vertex + e[:, 1])
    a, b = np.divmod(key, n_vertex)
    return a, b


def face_adjacency(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces that share an edge, each unordered pair once (`a < b`).

    On a non-manifold edge with k faces all k(k-1)/2 pairs are adjacent.
    """
    f = np.asarray(faces, dtype=np.int64)
    n_face = f.shape[0]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = e[:, 0] * n_vertex + e[:, 1]
    face_of = np.tile(np.arange(n_face, dtype=np.int64), 3)
    order = np.argsort(key, kind="stable")
    key, face_of = key[order], face_of[order]
    # Groups of equal keys in the sorted array: where each starts and how long it is.
    start = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if key.size else key
    size = np.diff(np.append(start, key.size))
    # Each face-edge entry pairs with every entry of its edge group (vectorised).
    group = np.repeat(np.arange(start.size), size)
    reps = size[group]
    first = np.repeat(np.arange(key.size), reps)
    offset = np.arange(first.size) - np.repeat(np.cumsum(reps) - reps, reps)
    second = start[group[first]] + offset
    a, b = face_of[first], face_of[second]
    keep = a < b
    pair = _sorted_unique(a[keep] * n_face + b[keep])
    return np.divmod(pair, n_face)


def build_mesh_graph(faces, n_vertex: int) -> MeshGraph:
    """Builds the `MeshGraph` of one triangle mesh on the host.

    Works on open boundaries, non-manifold edges, isolated vertices (self loop only, no
    incident face) and several components.

    Args:
      faces: `[n_face, 3]` integer vertex indices (validated with `validate_mesh` first).
      n_vertex: number of vertices, isolated ones included.
    """
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape [n_face, 3], got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= n_vertex):
        raise ValueError(f"face indices must lie in [0, {n_vertex}), got [{f.min()}, {f.max()}]")
    n_face = f.shape[0]
    a, b = vertex_edges(f, n_vertex)
    vs, vr, vw = _symmetric_with_self_loops(a, b, n_vertex)
    fa, fb = face_adjacency(f, n_vertex)
    fs, fr, fw = _symmetric_with_self_loops(fa, fb, n_face)
    degree = np.bincount(f.ravel(), minlength=n_vertex).astype(np.float32)
    return MeshGraph(
        faces=f.astype(np.int32),
        vertex_senders=vs,
        vertex_receivers=vr,
        vertex_edge_weight=vw,
        face_senders=fs,
        face_receivers=fr,
        face_edge_weight=fw,
        vertex_face_degree=degree,
        vertex_graph=np.zeros(n_vertex, np.int32),
        face_graph=np.zeros(n_face, np.int32),
        vertex_mask=np.ones(n_vertex, bool),
        face_mask=np.ones(n_face, bool),
        n_vertex_per_graph=np.array([n_vertex], np.int32),
        n_face_per_graph=np.array([n_face], np.int32),
    )


def batch_mesh_graphs(graphs: Sequence[MeshGraph]) -> MeshGraph:
    """Disjoint union of several graphs (indices offset, graph ids renumbered).

    ELL layouts of the inputs are dropped (the result has `vertex_ell = face_ell =
    None`): build them on the final padded graph with `with_ell_layout`.
    """
    if not graphs:
        raise ValueError("batch_mesh_graphs needs at least one graph")
    v_off = np.cumsum([0] + [g.n_vertex for g in graphs[:-1]])
    f_off = np.cumsum([0] + [g.n_face for g in graphs[:-1]])
    g_off = np.cumsum([0] + [g.n_graph for g in graphs[:-1]])

    def cat(field, offsets=None):
        parts = [getattr(g, field) for g in graphs]
        if offsets is not None:
            parts = [p + o for p, o in zip(parts, offsets, strict=True)]
        return np.concatenate(parts)

    return MeshGraph(
        faces=cat("faces", v_off).astype(np.int32),
        vertex_senders=cat("vertex_senders", v_off).astype(np.int32),
        vertex_receivers=cat("vertex_receivers", v_off).astype(np.int32),
        vertex_edge_weight=cat("vertex_edge_weight"),
        face_senders=cat("face_senders", f_off).astype(np.int32),
        face_receivers=cat("face_receivers", f_off).astype(np.int32),
        face_edge_weight=cat("face_edge_weight"),
        vertex_face_degree=cat("vertex_face_degree"),
        vertex_graph=cat("vertex_graph", g_off).astype(np.int32),
        face_graph=cat("face_graph", g_off).astype(np.int32),
        vertex_mask=cat("vertex_mask"),
        face_mask=cat("face_mask"),
        n_vertex_per_graph=cat("n_vertex_per_graph"),
        n_face_per_graph=cat("n_face_per_graph"),
    )


class PaddedSizes(NamedTuple):
    """Static sizes a batch is padded to (one compiled program per distinct value)."""

    n_vertex: int
    n_face: int
    n_vertex_edge: int
    n_face_edge: int
    n_graph: int


def bucket_size(n: int, *, minimum: int = 64) -> int:
    """Rounds `n` up to the next of 2^k · {1, 1.25, 1.5, 1.75}: few shapes, ≤ 25 % waste."""
    n = max(int(n), minimum)
    k = int(np.floor(np.log2(n)))
    for m in (1.0, 1.25, 1.5, 1.75, 2.0):
        size = int(np.ceil(m * 2**k))
        if size >= n:
            return size
    return 2 ** (k + 1)


def padded_sizes_for(graph: MeshGraph, *, n_graph: int | None = None) -> PaddedSizes:
    """Bucketed sizes that hold `graph` plus at least one padding vertex, face and graph."""
    return PaddedSizes(
        n_vertex=bucket_size(graph.n_vertex + 1),
        n_face=bucket_size(graph.n_face + 1),
        n_vertex_edge=bucket_size(graph.vertex_senders.shape[0] + 1),
        n_face_edge=bucket_size(graph.face_senders.shape[0] + 1),
        n_graph=(graph.n_graph + 1) if n_graph is None else n_graph,
    )


def pad_mesh_graph(graph: MeshGraph, sizes: PaddedSizes) -> MeshGraph:
    """Pads a (batched) graph to static sizes with one extra padding graph, as jraph does.

    Padding faces are the degenerate triangle `(p, p, p)` on the first padding vertex
    `p`; padding edges are weight-0 self loops there. The masks are `False` on padding.
    ELL layouts of the input are dropped (their tables have the unpadded row count);
    call `with_ell_layout` on the result.
    """
    nv, nf = graph.n_vertex, graph.n_face
    ne, nfe = graph.vertex_senders.shape[0], graph.face_senders.shape[0]
    if (
        sizes.n_vertex <= nv
        or sizes.n_face < nf
        or sizes.n_vertex_edge < ne
        or sizes.n_face_edge < nfe
        or sizes.n_graph <= graph.n_graph
    ):
        raise ValueError(
            f"cannot pad a graph of {nv} vertices, {nf} faces, {ne}/{nfe} edges, "
            f"{graph.n_graph} graphs to {sizes} (need room for one padding vertex and graph)"
        )
    pv, pf, pad_graph = nv, nf, sizes.n_graph - 1
    extra_nodes_v = sizes.n_vertex - nv
    extra_nodes_f = sizes.n_face - nf
    extra_graphs = sizes.n_graph - graph.n_graph

    def pad(x, n, value):
        return np.concatenate([x, np.full((n,) + x.shape[1:], value, dtype=x.dtype)])

    # Padding face edges need a padding face to sit on; with no padding face they go to
    # face 0 with weight 0, which changes nothing.
    face_pad_node = pf if extra_nodes_f > 0 else 0
    return MeshGraph(
        faces=pad(graph.faces, extra_nodes_f, pv),
        vertex_senders=pad(graph.vertex_senders, sizes.n_vertex_edge - ne, pv),
        vertex_receivers=pad(graph.vertex_receivers, sizes.n_vertex_edge - ne, pv),
        vertex_edge_weight=pad(graph.vertex_edge_weight, sizes.n_vertex_edge - ne, 0.0),
        face_senders=pad(graph.face_senders, sizes.n_face_edge - nfe, face_pad_node),
        face_receivers=pad(graph.face_receivers, sizes.n_face_edge - nfe, face_pad_node),
        face_edge_weight=pad(graph.face_edge_weight, sizes.n_face_edge - nfe, 0.0),
        vertex_face_degree=pad(graph.vertex_face_degree, extra_nodes_v, 0.0),
        vertex_graph=pad(graph.vertex_graph, extra_nodes_v, pad_graph),
        face_graph=pad(graph.face_graph, extra_nodes_f, pad_graph),
        vertex_mask=pad(graph.vertex_mask, extra_nodes_v, False),
        face_mask=pad(graph.face_mask, extra_nodes_f, False),
        n_vertex_per_graph=pad(graph.n_vertex_per_graph, extra_graphs, 0),
        n_face_per_graph=pad(graph.n_face_per_graph, extra_graphs, 0),
    )


def with_ell_layout(
    graph: MeshGraph, *, slot_multiple: int = 4, max_fill: float | None = None
) -> MeshGraph:
    """`graph` with `vertex_ell` and `face_ell` built from its edge lists (host, NumPy).

    Call it on the final graph, after `batch_mesh_graphs` and `pad_mesh_graph` (both
    drop the layouts). The model then aggregates with `ops.gcn_aggregate_ell`, the same
    operator as the sorted segment sum over the edge lists and several times faster on
    CPU. The table width, the largest valence plus one (self loop), is rounded up to a
    multiple of `slot_multiple`, so meshes whose maximum valences differ by a little
    share one compiled program; the extra slots point at their own row with weight 0
    (and are their own reverse slot), which changes nothing.

    The table costs `n_node × width` work and memory however few rows reach the
    width, so one high-valence vertex (the pole of a UV sphere, a fan of a scanner's
    hole filling) can make it many times the edge list. `max_fill` bounds that: a
    graph whose table would hold more than `max_fill` slots per edge keeps no table
    (`None`) and the model aggregates it over its edge lists, as in training.

    Args:
      graph: a `MeshGraph` of NumPy arrays (symmetric edge lists, as built here).
      slot_multiple: the table width is a multiple of this (≥ 1).
      max_fill: leave out a table with more than this many slots per edge (None: keep
        every table).

    Returns:
      `graph` with `vertex_ell` (`[n_vertex, width_v]` tables) and `face_ell`
      (`[n_face, width_f]` tables) set, or `None` where `max_fill` left one out; every
      other field is unchanged.

    Raises:
      ValueError: `slot_multiple < 1`, `max_fill < 1`, or an edge list that is not
        structurally symmetric (see `ops.ell_layout`).
    """
    # Imported here: ops imports this module, and mesh stays usable without JAX loaded.
    from dmd_jax.ops import ell_layout

    if int(slot_multiple) < 1:
        raise ValueError(f"slot_multiple must be at least 1, got {slot_multiple}")
    if max_fill is not None and not max_fill >= 1:
        raise ValueError(f"max_fill must be at least 1 (slots per edge), got {max_fill}")

    def layout(senders, receivers, weight, n_node):
        # The fill is judged before rounding: the rounding slots add at most
        # slot_multiple - 1 per row, the same for every mesh.
        ell = ell_layout(senders, receivers, weight, n_node, max_fill=max_fill)
        if ell is None:
            return None
        width = ell.neighbours.shape[1]
        extra = -width % int(slot_multiple)
        if extra == 0:
            return ell
        rows = np.arange(n_node, dtype=np.int32)[:, None]
        slots = np.arange(width, width + extra, dtype=np.int32)[None, :]
        return type(ell)(
            np.concatenate([ell.neighbours, np.broadcast_to(rows, (n_node, extra))], 1),
            np.concatenate([ell.weights, np.zeros((n_node, extra), ell.weights.dtype)], 1),
            np.concatenate([ell.reverse_slot, np.broadcast_to(slots, (n_node, extra))], 1),
        )

    return graph._replace(
        vertex_ell=layout(
            graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight, graph.n_vertex
        ),
        face_ell=layout(
            graph.face_senders, graph.face_receivers, graph.face_edge_weight, graph.n_face
        ),
    )


def pad_vertex_array(x: np.ndarray, n_vertex: int, value: float = 0.0) -> np.ndarray:
    """Pads a per-vertex array `[n, ...]` to `[n_vertex, ...]` with `value`."""
    x = np.asarray(x)
    if x.shape[0] > n_vertex:
        raise ValueError(f"cannot pad {x.shape[0]} rows down to {n_vertex}")
    fill = np.full((n_vertex - x.shape[0],) + x.shape[1:], value, dtype=x.dtype)
    return np.concatenate([x, fill])


# --------------------------------------------------------------------------------------
# Canonical frame
# --------------------------------------------------------------------------------------


class CanonicalFrame(NamedTuple):
    """Centre and scale mapping a mesh so its bounding box is centred, longest side 1."""

    centre: np.ndarray  # [3]
    scale: float

    def apply(self, vertices):
        """World → canonical: `(v - centre) / scale`."""
        return (vertices - self.centre) / self.scale

    def invert(self, vertices):
        """Canonical → world: `v * scale + centre` (the exact inverse of `apply`)."""
        return vertices * self.scale + self.centre


def canonical_frame(vertices) -> CanonicalFrame:
    """The canonical frame of a vertex set: bounding-box centre, longest side as scale."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    with np.errstate(over="ignore"):
        scale = float((hi - lo).max())
    if not np.all(np.isfinite(v)):
        raise ValueError("the mesh has NaN or infinite coordinates: no canonical frame exists")
    if not np.isfinite(scale):
        raise ValueError(
            f"the mesh's extent overflows float64 (coordinates up to {np.abs(v).max():.3g}); "
            "rescale it first"
        )
    if scale <= 0.0:
        raise ValueError(
            "the mesh has zero extent (all vertices coincide): no canonical frame exists"
        )
    return CanonicalFrame(centre=(lo + hi) / 2.0, scale=scale)


def mean_edge_length(vertices, faces) -> float:
    """Mean length of the unique undirected edges of a mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b = vertex_edges(faces, v.shape[0])
    return float(np.linalg.norm(v[a] - v[b], axis=1).mean())


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
    import io

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
                io.BytesIO(data),
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
