"""Meshes as graphs: the `MeshGraph` index arrays, batching, padding and ELL tables.

Everything here runs on the host in NumPy, once per mesh (or batch). The model only ever
sees the index arrays of a `MeshGraph`, so no dense adjacency matrix is built anywhere.
Padding follows jraph: a batch is a disjoint union plus one padding graph, padded to
bucketed static sizes so that a run compiles one program per bucket.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from dmd_jax.topology import (  # noqa: F401  (face_adjacency, vertex_edges: re-exported)
    EdgeGroups,
    adjacent_faces,
    edge_groups,
    face_adjacency,
    sorted_unique,
    vertex_edges,
)

# --------------------------------------------------------------------------------------
# Padded-neighbour (ELL) layout: the operator of `ops.gcn_aggregate` as tables
# --------------------------------------------------------------------------------------


class EllLayout(NamedTuple):
    """A graph operator as a padded neighbour table (ELL format); see `ell_layout`.

    Attributes:
      neighbours: `[n_node, max_degree]` int32; row `i` lists the senders into node `i`;
        slot 0 is `i` itself (its self loop, or unused), and unused slots point at `i`.
      weights: `[n_node, max_degree]`, the weight of each slot; 0 on unused slots.
      reverse_slot: `[n_node, max_degree]` int32; for the entry `j -> i` in slot `k` of
        row `i`, the slot of the entry `i -> j` in row `j` (unused slots: their own slot).
    """

    neighbours: np.ndarray
    weights: np.ndarray
    reverse_slot: np.ndarray


def ell_layout(
    senders,
    receivers,
    edge_weight,
    n_node: int,
    *,
    max_fill: float | None = None,
    max_width: int | None = None,
    min_width: int = 1,
) -> EllLayout | None:
    """Builds the ELL layout of the operator `out[r] += w * x[s]` on the host (NumPy).

    Duplicate `(sender, receiver)` pairs are merged by summing their weights (the padding
    self loops of `pad_mesh_graph` become one zero-weight slot), so the layout is the same
    operator as `ops.gcn_aggregate(x, senders, receivers, edge_weight)`. The edge set must be
    structurally symmetric (every `s -> r` has an `r -> s`, as in `MeshGraph`); the
    weights need not be. The table has `max_degree` columns, so the work is
    `n_node * max_degree` rather than `n_edge`: fine for meshes (valence ≤ ~15), wasteful
    for graphs with a few very high-degree nodes.

    Args:
      senders: `[n_edge]` integer sender of each edge.
      receivers: `[n_edge]` integer receiver of each edge.
      edge_weight: `[n_edge]` weight of each edge.
      n_node: number of nodes.
      max_fill: return None, before allocating the table, when it would hold more than
        this many slots (`n_node × max_degree`) per distinct edge (None: no limit).
      max_width: return None, before allocating the table, when a row has more than
        this many slots (None: no limit).
      min_width: at least this many slots (the rest unused), allocated at once.

    Returns:
      An `EllLayout`; pass it as `ops.gcn_aggregate_ell(features, *layout)`. None if
      `max_fill` or `max_width` is exceeded.

    Raises:
      ValueError: on mismatched shapes, indices outside `[0, n_node)`, or an edge whose
        reverse is missing.
    """
    s = np.asarray(senders).astype(np.int64)
    r = np.asarray(receivers).astype(np.int64)
    w = np.asarray(edge_weight)
    if s.ndim != 1 or s.shape != r.shape or s.shape != w.shape:
        raise ValueError(
            "senders, receivers and edge_weight must be 1-D of one length, got shapes "
            f"{s.shape}, {r.shape}, {w.shape}"
        )
    if n_node < 1:
        raise ValueError(f"n_node must be positive, got {n_node}")
    if s.size and (min(s.min(), r.min()) < 0 or max(s.max(), r.max()) >= n_node):
        raise ValueError(f"edge indices must lie in [0, {n_node})")
    if not np.issubdtype(w.dtype, np.floating):
        w = w.astype(np.float32)
    # np.sort plus a mask rather than np.unique: the same result, several times faster.
    key = r * n_node + s
    # `MeshGraph` edge lists come sorted by (receiver, sender), padding last: then the
    # stable sort is the identity, and checking for that costs a fraction of it.
    if not np.all(key[1:] >= key[:-1]):
        order = np.argsort(key, kind="stable")
        key, w = key[order], w[order]
    first = np.ones(key.size, bool)
    first[1:] = key[1:] != key[:-1]
    group = np.cumsum(first) - 1
    key = key[first]
    weight = np.bincount(group, weights=w.astype(np.float64), minlength=key.size)
    r, s = np.divmod(key, n_node)
    loop = s == r
    has_loop = np.zeros(n_node, bool)
    has_loop[r[loop]] = True
    degree = np.bincount(r, minlength=n_node)
    # Slot 0 of every row is the row itself (its self loop, or an unused slot): the
    # gathers then skip it (`ops._ell_sum`, the bilateral filter).
    width = max(int((degree + ~has_loop).max()), 1)
    if max_fill is not None and n_node * width > max_fill * max(key.size, 1):
        return None
    if max_width is not None and width > max_width:
        return None
    width = max(width, int(min_width))
    slot = np.arange(key.size) - (np.cumsum(degree) - degree)[r]
    # Sorted order within a row, then the self loop moved to the front.
    slot = np.where(loop, 0, slot + np.where(has_loop[r], s < r, True))
    rows = np.arange(n_node)
    neighbours = np.repeat(rows[:, None], width, axis=1).astype(np.int32)
    weights = np.zeros((n_node, width), w.dtype)
    reverse_slot = np.repeat(np.arange(width)[None, :], n_node, axis=0).astype(np.int32)
    # The reverse of every entry: the rows are sorted by sender, so a symmetric pattern's
    # transpose (CSC, a counting sort) lists, in column j, row j's entries in order.
    indptr = np.concatenate([[0], np.cumsum(degree)])
    transposed = sp.csr_matrix((np.arange(key.size), s, indptr), shape=(n_node, n_node)).tocsc()
    reverse = transposed.data
    found = np.ones(key.size, bool)
    if not (np.array_equal(transposed.indptr, indptr) and np.array_equal(transposed.indices, s)):
        reverse = np.searchsorted(key, s * n_node + r)
        found = reverse < key.size
        found[found] = key[reverse[found]] == (s * n_node + r)[found]
    if not found.all():
        i = int(np.flatnonzero(~found)[0])
        raise ValueError(
            f"edge {s[i]} -> {r[i]} has no reverse {r[i]} -> {s[i]}; the ELL layout needs "
            "a structurally symmetric edge set"
        )
    flat = r * width + slot  # one flat index: several times faster than [r, slot]
    neighbours.reshape(-1)[flat] = s
    weights.reshape(-1)[flat] = weight
    reverse_slot.reshape(-1)[flat] = slot[reverse]
    return EllLayout(neighbours, weights, reverse_slot)


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
      vertex_ell: `None`, or the `EllLayout` of the vertex edges, three
        `[n_vertex, width]` tables.
      face_ell: `None`, or the `EllLayout` of the face edges, three
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


def _symmetric_with_self_loops(
    senders: np.ndarray, receivers: np.ndarray, n_node: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique directed edges of `A + I`, sorted by receiver, and their GCN weights."""
    loops = np.arange(n_node, dtype=np.int64)
    s = np.concatenate([senders, receivers, loops])
    r = np.concatenate([receivers, senders, loops])
    key = sorted_unique(r * n_node + s)
    r, s = np.divmod(key, n_node)
    degree = np.bincount(r, minlength=n_node).astype(np.float64)
    weight = 1.0 / np.sqrt(degree[s] * degree[r])
    return s.astype(np.int32), r.astype(np.int32), weight.astype(np.float32)


def undirected_vertex_edges(graph: MeshGraph) -> tuple[np.ndarray, np.ndarray]:
    """The unique undirected primal edges `(a, b)`, `a < b`, read off a graph's edge lists.

    The same set as `vertex_edges` of its faces, without sorting again (padding edges
    are self loops and drop out with the real ones).
    """
    s, r = np.asarray(graph.vertex_senders), np.asarray(graph.vertex_receivers)
    keep = s < r
    return s[keep], r[keep]


def build_mesh_graph(
    faces, n_vertex: int, *, groups: EdgeGroups | None = None, face_pairs=None
) -> MeshGraph:
    """Builds the `MeshGraph` of one triangle mesh on the host.

    Works on open boundaries, non-manifold edges, isolated vertices (self loop only, no
    incident face) and several components.

    Args:
      faces: `[n_face, 3]` integer vertex indices (validated with `validate_mesh` first).
      n_vertex: number of vertices, isolated ones included.
      groups: `topology.edge_groups(faces, n_vertex)`, if already known (`denoise` sorts
        the edges once for its checks and the graph).
      face_pairs: `topology.adjacent_faces(groups, n_face)`, if already known.
    """
    from dmd_jax.mesh import validate_faces

    f = validate_faces(faces, n_vertex, name="faces", allow_empty=True)
    n_vertex = int(n_vertex)
    n_face = f.shape[0]
    # One sort of the face edges gives both the unique edges and the adjacent faces.
    if groups is None:
        groups = edge_groups(f, n_vertex)
        face_pairs = None  # pairs of other groups would not match
    a, b = groups.edges(n_vertex)
    vs, vr, vw = _symmetric_with_self_loops(a, b, n_vertex)
    fa, fb = adjacent_faces(groups, n_face) if face_pairs is None else face_pairs
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


def bucket_size(n: int, *, minimum: int = 64, steps: int = 4) -> int:
    """Rounds `n` up to the next 2^k · (1 + j / steps), j = 0 … steps − 1.

    The default, 2^k · {1, 1.25, 1.5, 1.75}, gives few shapes and ≤ 25 % waste; more
    `steps` waste less and give more shapes (one compiled program each).
    """
    n = max(int(n), minimum)
    k = int(np.floor(np.log2(n)))
    for j in range(steps + 1):
        size = int(np.ceil((1.0 + j / steps) * 2**k))
        if size >= n:
            return size
    return 2 ** (k + 1)


# Upper bounds of padded sizes per padded vertex: a closed triangle mesh has f ≈ 2v,
# 2e + v ≈ 7v primal edges with self loops and 4f dual edges with self loops.
_FACE_RATIO = 2.25
_VERTEX_EDGE_RATIO = 7.5
_FACE_EDGE_RATIO = 4.0 * _FACE_RATIO


def sizes_for_vertices(
    n_vertex: int, n_face: int, n_vertex_edge: int, n_face_edge: int, n_graph: int
) -> PaddedSizes:
    """The sizing policy: every padded size derives from one vertex bucket.

    The vertex count is rounded up by `bucket_size` (with room for a padding vertex),
    and faces and edges get fixed multiples of it, so a run compiles one program per
    vertex bucket it touches. A mesh whose faces or edges exceed those multiples moves
    up a bucket.

    Args:
      n_vertex, n_face, n_vertex_edge, n_face_edge: real counts of the (batched) graph.
      n_graph: real graphs; one padding graph is added.
    """
    nv = bucket_size(n_vertex + 1)
    while (
        int(_FACE_RATIO * nv) < n_face
        or int(_VERTEX_EDGE_RATIO * nv) < n_vertex_edge
        or int(_FACE_EDGE_RATIO * nv) < n_face_edge
    ):
        nv = bucket_size(nv + 1)
    return PaddedSizes(
        n_vertex=nv,
        n_face=int(_FACE_RATIO * nv),
        n_vertex_edge=int(_VERTEX_EDGE_RATIO * nv),
        n_face_edge=int(_FACE_EDGE_RATIO * nv),
        n_graph=n_graph + 1,
    )


def padded_sizes_for(graph: MeshGraph, *, n_graph: int | None = None) -> PaddedSizes:
    """`sizes_for_vertices` of a (batched) graph: room for it plus one padding graph.

    Args:
      graph: an unpadded `MeshGraph`.
      n_graph: padded graph count (default `graph.n_graph + 1`).
    """
    return sizes_for_vertices(
        graph.n_vertex,
        graph.n_face,
        graph.vertex_senders.shape[0],
        graph.face_senders.shape[0],
        graph.n_graph if n_graph is None else n_graph - 1,
    )


def fine_padded_sizes_for(graph: MeshGraph, *, steps: int = 16) -> PaddedSizes:
    """Padded sizes for one large mesh: each count rounded up on its own.

    `padded_sizes_for` derives every size from one coarse vertex bucket, so that patches
    and batches share few programs; a single mesh then carries up to 2.25x its faces
    (100k faces: 129k rows). Here vertices, faces and both edge lists each round up by
    `bucket_size(..., steps=steps)` (≤ 1/steps waste, 6 % by default), with room for the
    padding vertex and graph: more shapes, each compiled once, and less work per pass.

    Args:
      graph: an unpadded `MeshGraph`.
      steps: buckets per doubling (see `bucket_size`).
    """
    return PaddedSizes(
        n_vertex=bucket_size(graph.n_vertex + 1, steps=steps),
        n_face=bucket_size(graph.n_face + 1, steps=steps),
        n_vertex_edge=bucket_size(graph.vertex_senders.shape[0] + 1, steps=steps),
        n_face_edge=bucket_size(graph.face_senders.shape[0] + 1, steps=steps),
        n_graph=graph.n_graph + 1,
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
    graph: MeshGraph,
    *,
    slot_multiple: int = 4,
    max_fill: float | None = None,
    max_width: int | None = None,
    min_widths: tuple[int, int] = (1, 1),
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
      max_width: leave out a table whose widest row, self loop included, has more than
        this many slots (None: keep every table).
      min_widths: the vertex and face tables have at least this many slots.

    Returns:
      `graph` with `vertex_ell` (`[n_vertex, width_v]` tables) and `face_ell`
      (`[n_face, width_f]` tables) set, or `None` where `max_fill` left one out; every
      other field is unchanged.

    Raises:
      ValueError: `slot_multiple < 1`, `max_fill < 1`, or an edge list that is not
        structurally symmetric (see `ell_layout`).
    """
    if int(slot_multiple) < 1:
        raise ValueError(f"slot_multiple must be at least 1, got {slot_multiple}")
    if max_fill is not None and not max_fill >= 1:
        raise ValueError(f"max_fill must be at least 1 (slots per edge), got {max_fill}")

    def layout(senders, receivers, weight, n_node, min_width):
        # The fill is judged before rounding: the rounding slots add at most
        # slot_multiple - 1 per row, the same for every mesh.
        ell = ell_layout(
            senders,
            receivers,
            weight,
            n_node,
            max_fill=max_fill,
            max_width=max_width,
            min_width=min_width,
        )
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
            graph.vertex_senders,
            graph.vertex_receivers,
            graph.vertex_edge_weight,
            graph.n_vertex,
            min_widths[0],
        ),
        face_ell=layout(
            graph.face_senders,
            graph.face_receivers,
            graph.face_edge_weight,
            graph.n_face,
            min_widths[1],
        ),
    )


# How inference runs the GCN aggregations (the same operator either way, equal up to
# float summation order): "ell" through padded neighbour tables, "segment_sum" over the
# edge lists, as in training, or "auto": the tables, except one padded to more than
# `AUTO_MAX_FILL` slots per edge (a vertex of very high valence).
AGGREGATIONS = ("auto", "ell", "segment_sum")
# `auto` keeps a graph's ELL table while it holds at most this many slots per distinct
# edge. The shared meshes, padded, need 1.8-2.9 (vertex graph) and 1.2-1.4 (face graph);
# truck.obj, with a vertex of valence 36, 6.6, where its table still beat the segment sum
# (benchmarks/README.md). A pole of valence 1000 would need hundreds.
AUTO_MAX_FILL = 8.0


def check_aggregation(aggregation: str) -> None:
    """Raises `ValueError` unless `aggregation` is one of `AGGREGATIONS`."""
    if aggregation not in AGGREGATIONS:
        raise ValueError(
            f"unknown aggregation {aggregation!r}; choose one of {', '.join(AGGREGATIONS)}"
        )


def with_aggregation_layout(graph: MeshGraph, aggregation: str) -> MeshGraph:
    """A padded `graph` laid out for `aggregation` (one of `AGGREGATIONS`): ELL tables
    for `"ell"`, tables within `AUTO_MAX_FILL` for `"auto"`, none for `"segment_sum"`."""
    check_aggregation(aggregation)
    if aggregation == "segment_sum":
        return graph
    return with_ell_layout(graph, max_fill=AUTO_MAX_FILL if aggregation == "auto" else None)


# A neighbour table wider than this is left out (segment sums instead): one vertex of
# high valence (the stress family's fans: 104 slots) would make the table that wide for
# every row. Typical widths: 8-12 (vertex), 4 (face). Training's run-wide tables
# (`pipeline.ell_widths`) and inference's (`shape_ladder.with_tables`) share it.
MAX_ELL_WIDTH = 16


def widen_ell_layout(layout: EllLayout, width: int) -> EllLayout:
    """An ELL table with `width` slots: the extra ones point at their own row, weight 0,
    their own reverse slot (as `with_ell_layout`'s rounding slots), so the operator is
    unchanged and graphs of different valences share one table shape.

    Raises:
      ValueError: a table already wider than `width`.
    """
    n, have = layout.neighbours.shape
    if have > width:
        raise ValueError(f"an ELL table of {have} slots does not fit in {width}")
    rows = np.arange(n, dtype=layout.neighbours.dtype)[:, None]
    slots = np.arange(have, width, dtype=layout.reverse_slot.dtype)[None, :]
    extra = width - have
    return EllLayout(
        np.concatenate([layout.neighbours, np.broadcast_to(rows, (n, extra))], 1),
        np.concatenate([layout.weights, np.zeros((n, extra), layout.weights.dtype)], 1),
        np.concatenate([layout.reverse_slot, np.broadcast_to(slots, (n, extra))], 1),
    )


def with_fixed_ell(
    graph: MeshGraph, widths: tuple[int | None, int | None], *, natural: MeshGraph | None = None
) -> MeshGraph:
    """`with_ell_layout(graph)` with tables `widths = (vertex, face)` slots wide.

    The ELL tables are the segment sums' operators as gathers (several times faster on
    CPU, the same operator up to float summation order); fixed widths keep one program.
    A width of None leaves that table out.

    Args:
      graph: a padded `MeshGraph` (NumPy).
      widths: slots of the vertex and face tables, or None.
      natural: `graph` with its tables already built (`with_ell_layout`), to reuse.
    """
    g = with_ell_layout(graph) if natural is None else natural
    return graph._replace(
        vertex_ell=None if widths[0] is None else widen_ell_layout(g.vertex_ell, widths[0]),
        face_ell=None if widths[1] is None else widen_ell_layout(g.face_ell, widths[1]),
    )


def pad_vertex_array(x: np.ndarray, n_vertex: int, value: float = 0.0) -> np.ndarray:
    """Pads a per-vertex array `[n, ...]` to `[n_vertex, ...]` with `value`."""
    x = np.asarray(x)
    if x.shape[0] > n_vertex:
        raise ValueError(f"cannot pad {x.shape[0]} rows down to {n_vertex}")
    fill = np.full((n_vertex - x.shape[0],) + x.shape[1:], value, dtype=x.dtype)
    return np.concatenate([x, fill])
