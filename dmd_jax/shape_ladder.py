"""The whole-mesh path's program shapes: a ladder of sizes fixed before any mesh is seen.

XLA compiles one program per input shape, seconds each on a CPU. A whole-mesh run pads
its graph to a *rung*: a vertex count from a fixed ladder, every other count a fixed
multiple of it, and neighbour tables of fixed widths. So the programs a mesh of any
size needs are known in advance: `dmd-jax warmup` (`dmd_jax.warmup`) compiles them
into the on-disk cache (`dmd_jax.compile_cache`) once, and a new process on a mesh of
any size then loads its program instead of compiling it (docs/cold-start.md).

The rungs: 2^k · (1 + j / 8) vertices (8 per doubling, at most 12.5 % of the rows
padding, 6 % on average; the network's time grows with its rows: 25 % more rows took
22 % longer at 100k faces) from `FINE_FROM` vertices up, 2 per doubling below it
(small meshes run in milliseconds, where a compile costs seconds). Faces, primal and
dual edges get `FACES_PER_VERTEX`, `VERTEX_EDGES_PER_VERTEX` and
`FACE_EDGES_PER_VERTEX` rows per rung vertex: a closed triangle mesh of genus g has
f = 2v - 4 + 4g faces, 2e + v = 7v - 12 + 12g primal edges with self loops and
4f dual ones, so a mesh exceeds a multiple only with a genus in the thousands or
non-manifold edges, and then takes a higher rung.

The neighbour tables (`graph.with_ell_layout`) are padded to `STANDARD_WIDTHS`: vertices
of valence up to 15 and faces of a manifold mesh. A table that does not fit is left out
under `aggregation="auto"` (segment sums instead, as in training: 14 % slower on the
vertex stream at 100k faces), a program of its own, compiled on first use or by
`dmd-jax warmup --all-layouts`.
"""

from __future__ import annotations

import numpy as np

from dmd_jax import graph as graph_lib
from dmd_jax.graph import (
    MAX_ELL_WIDTH,
    MeshGraph,
    PaddedSizes,
    bucket_size,
    check_aggregation,
)

# Rung steps per doubling, and where the finer steps start (vertices).
COARSE_STEPS = 2
FINE_STEPS = 8
FINE_FROM = 8192
# The smallest rung: any mesh below it pads to it.
SMALLEST_RUNG = 1024
# Rows per rung vertex (see the module docstring).
FACES_PER_VERTEX = 2
VERTEX_EDGES_PER_VERTEX = 7
FACE_EDGES_PER_VERTEX = 8
# `(vertex, face)` neighbour-table widths every standard program has: the vertex table
# holds valences up to 15 plus the self loop (the training pipeline's limit too,
# `graph.MAX_ELL_WIDTH`); the face table a manifold mesh's 3 neighbours plus self. Width
# 16 instead of a regular grid's 8 cost 1-2 % of the network's time at 100k faces.
STANDARD_WIDTHS = (MAX_ELL_WIDTH, 4)
# The layouts of `dmd-jax warmup --all-layouts`: the standard one, and a vertex of
# valence above 15 (a fan, a UV sphere's pole, a scanner's hole filling).
LAYOUTS = (STANDARD_WIDTHS, (None, 4))


def rung_above(n_vertex: int) -> int:
    """The smallest rung with at least `n_vertex` vertices."""
    n = max(int(n_vertex), SMALLEST_RUNG)
    return bucket_size(
        n, minimum=SMALLEST_RUNG, steps=COARSE_STEPS if n < FINE_FROM else FINE_STEPS
    )


def rung_sizes(rung: int) -> PaddedSizes:
    """The padded sizes of a rung (one mesh and its padding graph)."""
    return PaddedSizes(
        n_vertex=rung,
        n_face=FACES_PER_VERTEX * rung,
        n_vertex_edge=VERTEX_EDGES_PER_VERTEX * rung,
        n_face_edge=FACE_EDGES_PER_VERTEX * rung,
        n_graph=2,
    )


def rung_for(n_vertex: int, n_face: int, n_vertex_edge: int, n_face_edge: int) -> int:
    """The smallest rung that holds a mesh of these counts (edges with self loops, as
    `MeshGraph` holds them) and one padding vertex."""

    def fits(r: int) -> bool:
        return (
            r > n_vertex
            and FACES_PER_VERTEX * r >= n_face
            and VERTEX_EDGES_PER_VERTEX * r >= n_vertex_edge
            and FACE_EDGES_PER_VERTEX * r >= n_face_edge
        )

    r = rung_above(n_vertex + 1)
    while not fits(r):
        r = rung_above(r + 1)
    return r


def padded_sizes(graph: MeshGraph) -> PaddedSizes:
    """The rung sizes of one unpadded mesh graph.

    Raises:
      ValueError: a batch of several graphs (the ladder is for one mesh).
    """
    if graph.n_graph != 1:
        raise ValueError(f"the shape ladder pads one mesh, got a batch of {graph.n_graph}")
    return rung_sizes(
        rung_for(
            graph.n_vertex,
            graph.n_face,
            graph.vertex_senders.shape[0],
            graph.face_senders.shape[0],
        )
    )


def rung_estimate(n_vertex: int, n_face: int) -> int:
    """The rung of a mesh from its vertex and face counts alone (edges as a closed
    manifold mesh has them: 3f + v primal with self loops, 4f dual)."""
    return rung_for(n_vertex, n_face, 3 * n_face + n_vertex, 4 * n_face)


def rungs_between(min_faces: int, max_faces: int) -> list[int]:
    """Every rung a mesh of `min_faces` to `max_faces` faces (half as many vertices, as a
    closed mesh has) may take, ascending.

    Raises:
      ValueError: a range that is empty or not positive.
    """
    if not 1 <= min_faces <= max_faces:
        raise ValueError(
            f"need 1 <= min_faces <= max_faces, got min_faces={min_faces}, max_faces={max_faces}"
        )
    last = rung_estimate(max_faces // 2 + 1, max_faces)
    rungs = [rung_estimate(max(min_faces // 2, 1), min_faces)]
    while rungs[-1] < last:
        rungs.append(rung_above(rungs[-1] + 1))
    return rungs


def with_tables(graph: MeshGraph, aggregation: str) -> MeshGraph:
    """A padded graph with the neighbour tables `aggregation` asks for, at fixed widths.

    `"segment_sum"`: none. `"auto"`: each table padded to its `STANDARD_WIDTHS` entry,
    or, where the mesh needs a wider one, to the next multiple of 4 up to
    `graph.MAX_ELL_WIDTH` (the face table of a non-manifold mesh); left out beyond that.
    `"ell"`: every table, at least the standard widths.

    Args:
      graph: a padded `MeshGraph` (NumPy).
      aggregation: one of `graph.AGGREGATIONS`.
    """
    check_aggregation(aggregation)
    if aggregation == "segment_sum":
        return graph
    # The width decides, not the fill: a small mesh's rung is mostly padding rows. The
    # tables are allocated at the standard widths at once (no widening copy).
    limit = MAX_ELL_WIDTH if aggregation == "auto" else None
    return graph_lib.with_ell_layout(graph, max_width=limit, min_widths=STANDARD_WIDTHS)


def layout_of(graph: MeshGraph) -> tuple[int | None, int | None]:
    """The `(vertex, face)` table widths of a graph (None: no table)."""
    return tuple(
        None if t is None else int(t.neighbours.shape[1])
        for t in (graph.vertex_ell, graph.face_ell)
    )


def abstract_graph(rung: int, widths=STANDARD_WIDTHS, dtype=np.float32) -> MeshGraph:
    """`jax.ShapeDtypeStruct`s of a padded graph of `rung` with tables `widths`: what a
    program is compiled for, without a mesh (`dmd_jax.warmup`)."""
    import jax

    from dmd_jax.graph import EllLayout

    sizes = rung_sizes(rung)

    def s(shape, dt):
        return jax.ShapeDtypeStruct(shape, np.dtype(dt))

    def table(rows, width):
        if width is None:
            return None
        return EllLayout(
            s((rows, width), np.int32), s((rows, width), dtype), s((rows, width), np.int32)
        )

    nv, nf = sizes.n_vertex, sizes.n_face
    ne, nfe, ng = sizes.n_vertex_edge, sizes.n_face_edge, sizes.n_graph
    return MeshGraph(
        faces=s((nf, 3), np.int32),
        vertex_senders=s((ne,), np.int32),
        vertex_receivers=s((ne,), np.int32),
        vertex_edge_weight=s((ne,), dtype),
        face_senders=s((nfe,), np.int32),
        face_receivers=s((nfe,), np.int32),
        face_edge_weight=s((nfe,), dtype),
        vertex_face_degree=s((nv,), dtype),
        vertex_graph=s((nv,), np.int32),
        face_graph=s((nf,), np.int32),
        vertex_mask=s((nv,), np.bool_),
        face_mask=s((nf,), np.bool_),
        n_vertex_per_graph=s((ng,), np.int32),
        n_face_per_graph=s((ng,), np.int32),
        vertex_ell=table(nv, widths[0]),
        face_ell=table(nf, widths[1]),
    )
