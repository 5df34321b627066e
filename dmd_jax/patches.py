"""Patch-wise inference: a large mesh as vertex patches with halos, on the host (NumPy).

DMD-Net is local except for its per-mesh pools (`model.pooled_names`): the output at a
vertex depends only on the mesh within `receptive_field(config).output` vertex rings of
it, once the pools are known. So a mesh too large to run at once is cut into disjoint
*owned* vertex sets (`compact_partition`: graph Voronoi cells, close to discs), each
grown by a halo of `halo_rings` rings (breadth-first over the vertex–face incidence,
vectorised per ring); the network runs on each patch and only its owned vertices are
kept. The pools are computed first, by the same patches with the pool masks restricted
to the owned vertices (`dmd_jax.inference` sums them over patches), and given to the
last pass. The result equals whole-mesh inference up to float32 summation order.

Ring counting (`receptive_field`). A vertex quantity has reach `r` when it depends on
vertices within `r` rings of its vertex; a face quantity, within `r` rings of any of its
three vertices. Then P2D (face from its vertices) keeps the reach, D2P (vertex from its
incident faces, whose vertices are one ring away) adds 1, one GCN aggregation on the
vertex graph adds 1, `k` consecutive hops on the face graph (faces sharing an edge:
GCN aggregations of the dual stream, bilateral pre-filter passes) add `ceil(k / 2)`
(`dual_rings`), one iteration of the normal-driven vertex update adds 1. A patch of
halo `h` has complete vertex stars (degrees, incident faces, face adjacency) within
`h - 1` rings of its owned vertices, so an owned vertex is exact when
`h >= reach + 1` (`halo_rings`). `tests/test_patches.py` checks both: perturbing one
vertex moves nothing beyond the reach, and patches with that halo reproduce the
whole-mesh output.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dmd_jax.config import ModelConfig
from dmd_jax.encoding import snapshot_passes, taubin_snapshots


class ReceptiveField(NamedTuple):
    """How far DMD-Net's outputs reach, in vertex rings (see the module docstring).

    Attributes:
      output: rings the denoised position of a vertex depends on, with every per-mesh
        pool given (`DMDNet(pooled=...)`).
      pools: one entry per stage of `model.pooled_names(config)`: rings the per-vertex
        values averaged by that stage's pools depend on (earlier stages given).
    """

    output: int
    pools: tuple[int, ...]


def dual_rings(hops: int) -> int:
    """Vertex rings reached by `hops` consecutive hops between faces sharing an edge.

    `ceil(hops / 2)`: measure a face's vertices by their ring distance from a start
    face's vertices. A hop keeps the shared edge and adds a vertex adjacent to both of
    its ends, so one ring beyond the nearer end at most; the maximum over the face can
    therefore grow only by crossing an edge whose two ends both hold it, and the new
    face then holds the new maximum at one vertex only, so the next hop cannot grow it.
    Counting a hop as a whole ring, as a vertex aggregation, would make the 60-pass
    pre-filters of the bundled model a 60-ring halo instead of 30.
    """
    return (int(hops) + 1) // 2


def receptive_field(config: ModelConfig) -> ReceptiveField:
    """The receptive field of `DMDNet(config)` in vertex rings, counted hop by hop.

    Counts, in the model's order: the `"local"` encoding (bilateral pre-filters:
    `max(snapshot_passes(filter_iterations))` dual passes on the face normals; their
    vertex averages, the vertex normals and the Laplacian coordinates one ring more),
    the STN's pooled MLP input (the Laplacian coordinates or xyz), the feature
    extractor's and the denoiser's two-stream networks (`n_agg` aggregations per stream,
    P2D into the dual stream, DAP and D2P back), the transformer (its `dense_layers + 1`
    trunk aggregations feed only the pool; the transformed features pass one more
    aggregation), and the head (offset: per vertex; normal-first: the face normals of the
    last dual stream mixed with the pre-filtered candidates, then `vertex_iterations`
    vertex updates).

    Args:
      config: the model config.

    Returns:
      A `ReceptiveField`.
    """
    cfg = config
    if cfg.encoding == "local":
        face_in = dual_rings(max(snapshot_passes(cfg.filter_iterations)))  # pre-filters
        # A λ|μ pair is two umbrella steps, a vertex ring each; a face sees its corners.
        face_in = max(face_in, 2 * max(taubin_snapshots(cfg.taubin_iterations), default=0))
        vertex_in = face_in + 1  # their vertex averages (D2P); Laplacian, normals: 1
        stn_in = 1  # the STN sees the Laplacian coordinates
    else:
        face_in, vertex_in, stn_in = 0, 0, 0  # xyz; no face input

    def two_stream(r, two: bool) -> tuple[int, int | None]:
        """`(vertex reach, face reach of [d ‖ DAP] or None)` of one two-stream network."""
        p = r + cfg.n_agg
        if not two:
            return p, None
        d = max(r, face_in) + dual_rings(cfg.n_agg)  # P2D keeps the reach; face_x joins
        fused = max(p, d)  # DAP: a face and its own vertices
        return fused + 1, fused  # D2P

    pools: list[int] = []
    if cfg.stn:
        pools.append(stn_in)
    features = None
    if cfg.uses_feature_extractor:
        r = vertex_in
        for _ in range(cfg.fe_two_streams):
            r, _ = two_stream(r, cfg.fe_two_stream)
        features = r
    if cfg.uses_transformer:
        pools.append(features + cfg.dense_layers + 1)
        t_in = vertex_in if cfg.variant == "fgt3" else max(vertex_in, features)
        den_in = max(t_in + 1, vertex_in)  # agg_out on the transformed features
    elif features is not None:
        den_in = max(vertex_in, features)
    else:
        den_in = vertex_in
    r, face = den_in, None
    for _ in range(cfg.depth):
        r, face = two_stream(r, cfg.denoiser_two_stream)
    if cfg.head == "offset":
        return ReceptiveField(r, tuple(pools))
    if face is None:  # single-stream denoiser: a Dense of [P2D(primal) ‖ face_x]
        face = r
    face = max(face, face_in)  # mixed with the pre-filtered candidates
    if cfg.head_consistency:  # the candidates' roughness: one face hop more
        face = max(face, face_in + dual_rings(1))
    # Each vertex update reads the normals and centroids of the incident faces.
    return ReceptiveField(face + cfg.vertex_iterations, tuple(pools))


def halo_rings(config: ModelConfig) -> ReceptiveField:
    """Halo depths that make owned vertices exact: `receptive_field` plus one ring.

    The extra ring: a patch's outermost ring has incomplete stars (missing faces, so
    wrong degrees and GCN weights), which nothing within the reach may touch.
    """
    rf = receptive_field(config)
    return ReceptiveField(rf.output + 1, tuple(p + 1 for p in rf.pools))


# --------------------------------------------------------------------------------------
# Partition and halos
# --------------------------------------------------------------------------------------


def morton_order(vertices: np.ndarray) -> np.ndarray:
    """A permutation of the vertices along a 3-D Morton (Z-order) curve.

    Consecutive runs of it are compact in space, so equal chunks of it make owned sets
    of equal size with short boundaries (little halo). 21 bits per axis of the bounding
    box.

    Args:
      vertices: `[n_vertex, 3]` positions.

    Returns:
      `[n_vertex]` int64 vertex indices.
    """
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = np.where(hi > lo, hi - lo, 1.0)
    q = ((v - lo) / extent * (2**21 - 1)).astype(np.uint64)

    def spread(x):
        # Inserts two zero bits between the bits of a 21-bit integer (magic numbers).
        x = x & np.uint64(0x1FFFFF)
        x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
        return x

    code = spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


class Incidence(NamedTuple):
    """The faces of every vertex (CSR): faces of `v` are `face[start[v]:start[v + 1]]`."""

    start: np.ndarray  # [n_vertex + 1] int64
    face: np.ndarray  # [3 n_face] int32


def vertex_faces(faces: np.ndarray, n_vertex: int) -> Incidence:
    """The vertex–face incidence of a mesh as CSR arrays (4 bytes a corner)."""
    corner_vertex = np.asarray(faces).reshape(-1)
    order = np.argsort(corner_vertex, kind="stable")
    face = (order // 3).astype(np.int32)
    del order
    start = np.zeros(n_vertex + 1, np.int64)
    np.cumsum(np.bincount(corner_vertex, minlength=n_vertex), out=start[1:])
    return Incidence(start, face)


def _rows(inc: Incidence, vertices: np.ndarray, *, with_row: bool = False):
    """The incident faces of every vertex in `vertices`, concatenated (with repeats).

    With `with_row`, also the position in `vertices` each face came from.
    """
    begin = inc.start[vertices]
    count = inc.start[vertices + 1] - begin
    total = int(count.sum())
    if total == 0:
        empty = np.empty(0, np.int32)
        return (empty, np.empty(0, np.int64)) if with_row else empty
    # Position of each output entry: its row's start plus its offset within the row.
    offset = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
    face = inc.face[np.repeat(begin, count) + offset]
    if with_row:
        return face, np.repeat(np.arange(vertices.size), count)
    return face


class Partition(NamedTuple):
    """Disjoint owned vertex sets covering a mesh: set `c` is `vertices[start[c]:start[c+1]]`."""

    vertices: np.ndarray  # [n_vertex] int64, set by set
    start: np.ndarray  # [n_set + 1] int64

    def sets(self):
        """Yields the owned sets, `[k]` int64 vertex indices each."""
        for c in range(self.start.size - 1):
            yield self.vertices[self.start[c] : self.start[c + 1]]


def _grow_cells(faces, incidence: Incidence, label: np.ndarray, seeds: np.ndarray) -> None:
    """Breadth-first from all `seeds` at once (already labelled): every unlabelled vertex
    they reach takes the label of a seed fewest rings away. Vectorised per ring."""
    frontier = seeds
    while frontier.size:
        f, row = _rows(incidence, frontier, with_row=True)
        nb = faces[f].reshape(-1).astype(np.int64)
        nb_label = np.repeat(label[frontier][row], 3)
        free = label[nb] < 0
        nb, nb_label = nb[free], nb_label[free]
        # A vertex reached from two cells in the same ring joins the first listed.
        frontier, first = np.unique(nb, return_index=True)
        label[frontier] = nb_label[first]


def compact_partition(
    vertices: np.ndarray, faces: np.ndarray, incidence: Incidence, order: np.ndarray, size: int
) -> Partition:
    """Owned sets of about `size` vertices each, compact on the surface (graph Voronoi).

    Consecutive runs of a Morton order are compact in space but not on a surface: a run
    is a union of boxes, and a box cuts a curved sheet into strips, whose halos hold
    several times their own vertices. Here every `size`-th vertex of `order` (the middle
    of its run) seeds a cell, a breadth-first search from all seeds at once gives each
    vertex the cell of a seed fewest rings away, and one Lloyd step (each cell reseeded
    at its vertex nearest its centroid, then grown again) evens out the cell sizes:
    cells close to discs, whose halos are the smallest for their size. Components that
    no seed reaches are seeded from their own vertices, ever more densely; cells smaller
    than `size` then join their successors in seed order while the sum stays within
    `size`. Within a cell, vertices keep `order`'s order (so halving a cell that is too
    large splits it in space).

    Args:
      vertices: `[n_vertex, 3]` positions.
      faces: `[n_face, 3]` faces.
      incidence: `vertex_faces(faces, n_vertex)`.
      order: `[n_vertex]` a permutation of the vertices (e.g. `morton_order`).
      size: target vertices per set (>= 1).

    Returns:
      A `Partition`.
    """
    if size < 1:
        raise ValueError(f"a patch needs at least one owned vertex, got size {size}")
    n = order.size
    label = np.full(n, -1, np.int64)
    seeds = order[min(size // 2, n - 1) :: size]
    label[seeds] = np.arange(seeds.size)
    _grow_cells(faces, incidence, label, seeds)
    # Lloyd step over the reached vertices: the vertex nearest its cell's centroid.
    reached = np.flatnonzero(label >= 0)
    cell = label[reached]
    count = np.bincount(cell, minlength=seeds.size).astype(np.float64)[:, None]
    x = np.asarray(vertices, np.float64)[reached]
    centre = np.stack([np.bincount(cell, x[:, i], seeds.size) for i in range(3)], 1) / count
    d2 = ((x - centre[cell]) ** 2).sum(axis=1)
    del x
    by = np.lexsort((d2, cell))
    first = np.r_[True, cell[by][1:] != cell[by][:-1]]
    seeds = reached[by[first]]
    del reached, cell, d2, by, first
    label[:] = -1
    label[seeds] = np.arange(seeds.size)
    n_cell = seeds.size
    _grow_cells(faces, incidence, label, seeds)
    todo, stride = order[label[order] < 0], size
    while todo.size:
        # Components no seed reached (and vertices without faces), seeded ever more
        # densely: at most log2(size) + 1 rounds however many components there are.
        seeds = todo[min(stride // 2, todo.size - 1) :: stride]
        label[seeds] = np.arange(n_cell, n_cell + seeds.size)
        n_cell += seeds.size
        _grow_cells(faces, incidence, label, seeds)
        todo = todo[label[todo] < 0]
        stride = max(stride // 2, 1)
    count = np.bincount(label, minlength=n_cell)
    group = np.empty(n_cell, np.int64)
    g, total = 0, 0
    for c, k in enumerate(count.tolist()):
        if total and total + k > size:
            g, total = g + 1, 0
        group[c] = g
        total += k
    label = group[label]
    by_cell = order[np.argsort(label[order], kind="stable")]
    start = np.zeros(g + 2, np.int64)
    np.cumsum(np.bincount(label, minlength=g + 1), out=start[1:])
    return Partition(by_cell, start)


class Patch(NamedTuple):
    """One patch: owned vertices and their halo, re-indexed.

    Attributes:
      vertices: `[n]` int64 global indices, ascending (so every sum over neighbours runs
        in the whole mesh's order).
      faces: `[m, 3]` int32 faces in patch indices: every face of the whole mesh incident
        to a vertex within `rings - 1` of the owned set, in ascending global order.
      owned: `[n]` bool, the vertices whose result this patch gives.
    """

    vertices: np.ndarray
    faces: np.ndarray
    owned: np.ndarray


class PatchGrower:
    """Grows owned vertex sets into patches by breadth-first search over rings.

    Holds the incidence of the whole mesh and two stamp arrays (one int32 per vertex and
    per face), so a patch costs work proportional to its own size, not the mesh's.

    Args:
      faces: `[n_face, 3]` int32 faces of the whole mesh.
      n_vertex: vertices of the whole mesh.
    """

    def __init__(self, faces: np.ndarray, n_vertex: int):
        self.faces = np.asarray(faces)
        self.n_vertex = int(n_vertex)
        self.incidence = vertex_faces(self.faces, n_vertex)
        self._vertex_stamp = np.zeros(n_vertex, np.int32)
        self._face_stamp = np.zeros(self.faces.shape[0], np.int32)
        self._stamp = 0

    def _ring(self, frontier: np.ndarray, stamp: int) -> tuple[np.ndarray, np.ndarray]:
        """`(faces, vertices)` one ring out from `frontier`, neither stamped before; stamps
        both with `stamp`."""
        f = _rows(self.incidence, frontier)
        f = np.unique(f[self._face_stamp[f] != stamp])
        self._face_stamp[f] = stamp
        nb = self.faces[f].reshape(-1).astype(np.int64)
        nb = np.unique(nb[self._vertex_stamp[nb] != stamp])
        self._vertex_stamp[nb] = stamp
        return f, nb

    def _start(self, vertices: np.ndarray) -> int:
        """A fresh stamp, with `vertices` stamped."""
        self._stamp += 1
        self._vertex_stamp[vertices] = self._stamp
        return self._stamp

    def disc(self, seed: int, size: int) -> np.ndarray:
        """`size` vertices around `seed`, ring by ring (fewer if its component is smaller).

        Returns:
          `[k]` int64 global vertex indices, `k <= size`, in ring order.
        """
        frontier = np.array([seed], np.int64)
        stamp = self._start(frontier)
        layers, total = [frontier], 1
        while total < size and frontier.size:
            _, frontier = self._ring(frontier, stamp)
            layers.append(frontier)
            total += frontier.size
        return np.concatenate(layers)[:size]

    def grow(self, owned: np.ndarray, rings: int) -> Patch:
        """The patch of `owned` (global vertex indices) with a halo of `rings` rings.

        Args:
          owned: `[k]` distinct global vertex indices.
          rings: halo depth (>= 1).

        Returns:
          A `Patch`.
        """
        if rings < 1:
            raise ValueError(f"a halo needs at least one ring, got {rings}")
        frontier = np.asarray(owned, np.int64)
        stamp = self._start(frontier)
        layers, face_parts = [frontier], []
        for _ in range(rings):
            f, frontier = self._ring(frontier, stamp)
            face_parts.append(f)
            layers.append(frontier)
            if frontier.size == 0:
                break
        verts = np.sort(np.concatenate(layers))
        face_ids = np.sort(np.concatenate(face_parts))
        # Global -> patch indices through a lookup on the patch's own vertices.
        local = np.searchsorted(verts, self.faces[face_ids].reshape(-1))
        owned_mask = np.zeros(verts.size, bool)
        owned_mask[np.searchsorted(verts, np.asarray(owned, np.int64))] = True
        return Patch(verts, local.reshape(-1, 3).astype(np.int32), owned_mask)
