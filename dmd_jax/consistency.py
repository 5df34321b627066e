"""What `denoise` makes consistent before the network, and what it leaves exactly alone.

Three properties of the input that the result must not silently depend on (issue 56):

* **Exact vertices are fixed points** (`exact_vertices`). A vertex whose incident faces
  lie, to the precision of the input's number format (`exact_tolerance`), on at most
  `EXACT_MAX_PLANES` planes, one of which holds two faces sharing an edge, is a vertex
  of an exactly piecewise-planar surface: a flat, a crease or a corner of a clean CAD
  mesh. Noise leaves no two neighbouring faces coplanar to that precision (float64
  input: to 1e-9 radians; noise along the normals of a flat could only by a
  coincidence of measure zero), so on a noisy mesh no vertex qualifies and nothing
  changes; on a clean
  part the vertices of its flats, creases and corners are kept exactly where they are
  (through the pre-smoothing, every network pass and the relaxation), and the
  pre-smoothing's roughness reads only the faces that touch another vertex. The network
  was never trained to keep such meshes unchanged (fans of valence 100, tiny solids of
  a dozen faces, 1:50 plates: its head tilts their normals by 4–45°); the certificate
  makes the answer exact where the input already is. A free vertex whose neighbours
  are all exact is exact too when it is the **tip of a solid** (`closed_tips`): every
  face around it folds back by more than 90° onto the face across its far edge, as at a
  pyramid's apex. A spike on a flat, outward or inward, never folds (its faces rise
  less than 90° from the flat around it), so it stays free and is denoised.
* **One winding** (`oriented_faces`): faces whose winding disagrees with their
  neighbours' across a manifold edge are flipped, per connected component, keeping the
  winding of the majority of its faces (a consistent mesh is returned as it is; a
  non-orientable component is left as it is). The network reads signed face normals.
* **One scale per run** (`scale_groups`): connected components whose sizes differ by
  more than `SCALE_RATIO` are denoised in separate runs, each in its own frame, so a
  small part beside a huge one keeps its float32 precision instead of collapsing.

NumPy/SciPy on the host; no JAX.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from dmd_jax.constants import CREASE_ANGLE
from dmd_jax.mesh import face_normals_np
from dmd_jax.topology import EdgeGroups, adjacent_faces, edge_groups

# Two face normals closer than the tolerance (radians, |n1 × n2|) are one plane. The
# tolerance is what rounding the coordinates to the input's number format can do to a
# normal: `EXACT_ROUNDING` machine epsilons of the largest coordinate over the mean edge,
# at least `EXACT_TOLERANCE_FLOOR` (a float32 file of a part with 100 edges across: about
# 5e-5 rad); above `EXACT_TOLERANCE_CAP` the coordinates certify nothing (tolerance 0).
EXACT_ROUNDING = 8.0
EXACT_TOLERANCE_FLOOR = 1e-9
EXACT_TOLERANCE_CAP = 1e-4
# The most planes that may meet at an exact vertex: a flat (1), a crease (2), a box
# corner (3), a pyramid's apex or a chamfer's corner (4).
EXACT_MAX_PLANES = 4
# Components whose bounding-box extents differ by more than this run separately.
SCALE_RATIO = 1024.0


def exact_tolerance(dtype, vertices: np.ndarray, faces: np.ndarray, *, edges=None) -> float:
    """The angle (radians) within which two face normals of a mesh given in `dtype` are
    one plane: what rounding its coordinates to `dtype` can do to a normal; 0 (no plane
    is certain) where that exceeds `EXACT_TOLERANCE_CAP`.

    Args:
      dtype: the number format the caller's coordinates came in (integers are exact).
      vertices: `[n_vertex, 3]` the caller's positions (their frame: the offset counts).
      faces: `[n_face, 3]` vertex indices.
      edges: the unique undirected edges `(a, b)`, sorted (`topology.vertex_edges`), if
        already known: skips their sort (`mesh.mean_edge_length`).
    """
    from dmd_jax.mesh import mean_edge_length

    dtype = np.dtype(dtype)
    eps = float(np.finfo(dtype).eps) if np.issubdtype(dtype, np.floating) else 0.0
    v = np.asarray(vertices, np.float64)
    largest = float(np.max(np.abs(v))) if v.size else 0.0
    if not 0 < largest < np.inf:
        return EXACT_TOLERANCE_FLOOR
    # Lengths in units of a power of two near the largest coordinate: exact, and no
    # overflow (an extent near float64's limit) or underflow (one near its smallest).
    exponent = int(np.frexp(largest)[1])
    edge = mean_edge_length(np.ldexp(v, -exponent), faces, edges=edges)
    if not edge > 0:
        return EXACT_TOLERANCE_FLOOR
    tol = EXACT_ROUNDING * eps * (float(np.ldexp(largest, -exponent)) / edge)
    # Coordinates too coarse to tell a plane from light noise certify nothing.
    return 0.0 if tol > EXACT_TOLERANCE_CAP else max(tol, EXACT_TOLERANCE_FLOOR)


def _coplanar(a: np.ndarray, b: np.ndarray, tolerance: float) -> np.ndarray:
    """`[n]` whether unit normals `a`, `b` `[n, 3]` agree to `tolerance` radians (zero
    normals of degenerate faces agree with nothing)."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return (cross < tolerance) & (np.einsum("ij,ij->i", a, b) > 0)


def exact_vertices(
    vertices: np.ndarray,
    faces: np.ndarray,
    tolerance: float = EXACT_TOLERANCE_FLOOR,
    *,
    pairs=None,
    normals=None,
) -> np.ndarray:
    """Which vertices are exact (see the module docstring), as a mask.

    Args:
      vertices: `[n_vertex, 3]` positions (any frame: the test reads normals only).
      faces: `[n_face, 3]` consistently wound faces (`oriented_faces`).
      tolerance: radians within which normals are one plane (`exact_tolerance`).
      pairs: `(a, b)`, the edge-adjacent face pairs (`topology.face_adjacency`), if
        known.
      normals: `[n_face, 3]` `mesh.face_normals_np` of `vertices` (float64) and `faces`,
        if known (`denoise` reuses them for the roughness).

    Returns:
      `[n_vertex]` bool; all False on a noisy mesh.
    """
    f = np.asarray(faces, np.int64)
    n_vertex = vertices.shape[0]
    if normals is None:
        normals = face_normals_np(np.asarray(vertices, np.float64), f)
    if pairs is None:
        pairs = adjacent_faces(edge_groups(f, n_vertex), f.shape[0])
    a, b = pairs
    flat = _coplanar(normals[a], normals[b], tolerance)
    exact_face = np.zeros(f.shape[0], bool)
    exact_face[a[flat]] = True
    exact_face[b[flat]] = True
    touches = np.zeros(n_vertex, bool)
    touches[f[exact_face].ravel()] = True
    if not touches.any():
        return touches
    # Count the planes around each vertex greedily, one plane a round: the first corner
    # not yet on a plane opens one, and every corner on it is assigned. Corners of
    # degenerate faces (zero normal) constrain nothing.
    corner_vertex = f.ravel()
    order = np.argsort(corner_vertex, kind="stable")
    cv = corner_vertex[order]
    cn = normals[np.repeat(np.arange(f.shape[0]), 3)[order]]
    assigned = ~np.any(cn, axis=1)
    starts = np.searchsorted(cv, np.arange(n_vertex))
    has = np.bincount(cv, minlength=n_vertex) > 0
    position = np.arange(cv.size)
    for _ in range(EXACT_MAX_PLANES):
        first = np.where(assigned, cv.size, position)
        head = np.full(n_vertex, cv.size)
        head[has] = np.minimum.reduceat(first, starts[has])
        open_ = head[cv] < cv.size
        if not open_.any():
            break
        rep = cn[np.minimum(head[cv], cv.size - 1)]
        assigned |= open_ & _coplanar(cn, rep, tolerance)
    left = np.bincount(cv, weights=~assigned, minlength=n_vertex) > 0
    held = touches & ~left
    return held | closed_tips(f, normals, held, edge_groups(f, n_vertex))


def closed_tips(
    faces: np.ndarray, normals: np.ndarray, held: np.ndarray, groups: EdgeGroups
) -> np.ndarray:
    """Free vertices that are the tip of a solid whose every other vertex is held.

    A vertex is a tip when it has at least three faces, each neighbour is held, and
    each face around it meets the face across its far edge (the edge opposite the
    vertex) at a fold of more than 90° (negative dot product of the normals): the
    surface closes behind the tip, as a pyramid's sides close on its base. A spike
    on a held flat fails the test (its faces tilt less than 90° from the flat beyond
    its ring), and so does a vertex on an open boundary (a far edge with no face).

    Args:
      faces: `[n_face, 3]` consistently wound faces.
      normals: `[n_face, 3]` unit face normals (zero for degenerate faces).
      held: `[n_vertex]` bool, the vertices already held.
      groups: `topology.edge_groups(faces, n_vertex)`.

    Returns:
      `[n_vertex]` bool, the tips (disjoint from `held`).
    """
    f = np.asarray(faces, np.int64)
    n_vertex = held.shape[0]
    # The manifold edges (two faces) and, in each face, the corner opposite the edge.
    pair = groups.start[groups.size == 2]
    lo, hi = np.divmod(groups.key[pair], n_vertex)
    fa, fb = groups.face[pair], groups.face[pair + 1]
    ok = (np.einsum("ij,ij->i", normals[fa], normals[fb]) < 0) & held[lo] & held[hi]
    corners = np.concatenate([f[fa].sum(axis=1), f[fb].sum(axis=1)]) - np.tile(lo + hi, 2)
    good = np.bincount(corners[np.tile(ok, 2)], minlength=n_vertex)
    count = np.bincount(f.ravel(), minlength=n_vertex)
    return (count >= 3) & (good == count) & ~held


def oriented_faces(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, int]:
    """The faces with one winding per connected component, and how many were flipped.

    Two faces on a manifold edge agree when they run along it in opposite directions.
    A breadth-first walk over those edges gives each face its flip relative to its
    component's first face; each component then keeps the winding of most of its
    faces. A component with no consistent winding (a Möbius strip) is left unchanged.

    Args:
      faces: `[n_face, 3]` vertex indices.
      n_vertex: the number of vertices.

    Returns:
      `([n_face, 3]` faces of the input's dtype, number of faces flipped).
    """
    f = np.asarray(faces)
    m = f.shape[0]
    u = f[:, [0, 1, 2]].ravel().astype(np.int64)
    v = f[:, [1, 2, 0]].ravel().astype(np.int64)
    owner = np.repeat(np.arange(m), 3)
    key = np.minimum(u, v) * n_vertex + np.maximum(u, v)
    order = np.argsort(key, kind="stable")
    key, owner, forward = key[order], owner[order], (u < v)[order]
    # Runs of equal keys, as `np.unique(key, return_index=True, return_counts=True)`
    # gives them for a sorted `key` (NumPy 2.4's `np.unique` hashes: 3x slower here).
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if m else key
    count = np.diff(np.append(first, key.size))
    pair = first[count == 2]  # manifold interior edges: two half-edges
    fa, fb = owner[pair], owner[pair + 1]
    # 1: the two faces run the same way along the edge (one of them must flip).
    clash = (forward[pair] == forward[pair + 1]).astype(np.int8)
    keep = fa != fb
    fa, fb, clash = fa[keep], fb[keep], clash[keep]
    if not clash.any():
        return f, 0
    # A virtual root m joined to every face: one walk covers every component.
    rows = np.concatenate([fa, fb, np.full(m, m)])
    cols = np.concatenate([fb, fa, np.arange(m)])
    graph = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(m + 1, m + 1))
    n_comp, label = connected_components(graph[:m, :m], directed=False)
    # Root each component at its first face, so the walk stays inside components.
    roots = np.zeros(n_comp, np.int64)
    roots[label[::-1]] = np.arange(m)[::-1]
    rows = np.concatenate([fa, fb, np.full(n_comp, m)])
    cols = np.concatenate([fb, fa, roots])
    graph = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(m + 1, m + 1))
    _, pred = breadth_first_order(graph, m, directed=False, return_predecessors=True)
    parent = pred[:m].astype(np.int64)
    parent = np.where(parent == m, np.arange(m), parent)  # component roots
    # The clash on each tree edge (face, parent), from the edge lists.
    lookup = sp.csr_matrix(
        (np.concatenate([clash, clash]).astype(np.float64) + 1.0, (np.r_[fa, fb], np.r_[fb, fa])),
        shape=(m, m),
    )
    edge = (np.asarray(lookup[np.arange(m), parent]).ravel() - 1.0).clip(0).astype(np.int8)
    edge[parent == np.arange(m)] = 0
    # Flip relative to the root by pointer jumping: log2(depth) vectorised steps.
    flip, up = edge.copy(), parent.copy()
    while np.any(up != up[up]) or np.any(flip[up] & (up != np.arange(m))):
        flip, up = flip ^ np.where(up != np.arange(m), flip[up], 0), up[up]
    flip = flip.astype(bool)
    bad = (flip[fa] ^ flip[fb]) != clash.astype(bool)
    if bad.any():
        flip[np.isin(label, np.unique(label[fa[bad]]))] = False
    flipped_share = np.bincount(label, weights=flip, minlength=n_comp)
    sizes = np.bincount(label, minlength=n_comp)
    flip ^= (flipped_share > sizes / 2)[label]
    if not flip.any():
        return f, 0
    out = f.copy()
    out[flip] = out[flip][:, ::-1]
    return out, int(flip.sum())


def scale_groups(vertices: np.ndarray, faces: np.ndarray) -> list[np.ndarray] | None:
    """Vertex masks of the runs a mesh of very different component sizes needs, or None.

    Components (connected through faces) are sorted by bounding-box extent; a run takes
    the largest left and every component at least `1 / SCALE_RATIO` of its size.

    Args:
      vertices: `[n_vertex, 3]` positions (every vertex referenced by a face).
      faces: `[n_face, 3]` vertex indices.

    Returns:
      None when one run holds every component; else `[n_vertex]` bool masks, largest
      components first.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    n = v.shape[0]
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adjacency = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    n_comp, label = connected_components(adjacency, directed=False)
    if n_comp == 1:
        return None
    lo = np.full((n_comp, 3), np.inf)
    hi = np.full((n_comp, 3), -np.inf)
    np.minimum.at(lo, label, v)
    np.maximum.at(hi, label, v)
    extent = np.max(0.5 * hi - 0.5 * lo, axis=1)  # halves: no overflow near the limit
    if extent.min() * SCALE_RATIO >= extent.max():
        return None
    groups, left = [], np.argsort(-extent, kind="stable")
    while left.size:
        take = extent[left] * SCALE_RATIO >= extent[left[0]]
        groups.append(np.isin(label, left[take]))
        left = left[~take]
    return groups


# Faces whose area is below this share of their longest edge squared are taken as zero
# area: their normal is rounding noise (collinear points a float cannot place exactly).
ZERO_AREA_SHARE = 1e-12
STILL_REASON = (
    "nothing to denoise: every edge between faces of non-zero area is a crease of at "
    f"least {CREASE_ANGLE:g} degrees, or no face has an area (consistency.still_vertices)"
)


def _squared(d: np.ndarray) -> np.ndarray:
    """`[n]` squared lengths of `[n, 3]` vectors, summed as `np.sum(d**2, axis=1)` sums."""
    return (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]


def still_faces(vertices: np.ndarray, faces: np.ndarray, *, pairs=None) -> np.ndarray:
    """Which faces belong to a connected part with nothing to denoise, as a mask.

    A part has something to denoise when two of its faces of non-zero area meet on an
    edge at less than `CREASE_ANGLE` (the crease of `comparison.crease_faces` and the
    training loss): a smooth stretch the surface could be estimated over. A part with no
    such edge is all creases (a tetrahedron, an octahedron, an icosahedron: 109.5, 70.5,
    41.8 degrees), a lone triangle, or faces of zero area only: no neighbourhood to
    average over, and noise on it cannot be told from shape, so every denoiser returns
    it as given. A noisy mesh of more than a few dozen faces never qualifies (even noise
    larger than the edges leaves a tenth of its edges below 30 degrees).

    Args:
      vertices: `[n_vertex, 3]` finite positions, in any frame.
      faces: `[n_face, 3]` vertex indices (any winding: they are oriented here, unless
        `pairs` is given).
      pairs: `(a, b)`, the edge-adjacent face pairs (`topology.face_adjacency`) of
        `faces` already consistently wound (`oriented_faces`): `denoise` has both.

    Returns:
      `[n_face]` bool; all False on an ordinary noisy mesh.
    """
    if pairs is None:
        f, _ = oriented_faces(np.asarray(faces, np.int64), vertices.shape[0])
        pairs = adjacent_faces(edge_groups(f, vertices.shape[0]), f.shape[0])
    else:
        f = np.asarray(faces, np.int64)
    v = np.asarray(vertices, np.float64)
    largest = float(np.max(np.abs(v))) if v.size else 0.0
    if largest > 0:  # a power of two: exact, and no overflow of the cross products
        v = np.ldexp(v, -int(np.frexp(largest)[1]))
    corners = v[f]
    e01, e02 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    cross = np.cross(e01, e02)
    area2 = np.linalg.norm(cross, axis=1)
    # The longest edge's squared length, its sum written out as `np.sum` adds three
    # numbers (left to right): the same value, a third of the time of summing a
    # `[n_face, 3, 3]` block over its last axis.
    e12 = corners[:, 2] - corners[:, 1]
    longest2 = np.maximum(np.maximum(_squared(e02), _squared(e01)), _squared(e12))
    solid = area2 > ZERO_AREA_SHARE * longest2
    if solid.all():  # any noisy mesh: no masked copies
        normals = cross / area2[:, None]
    else:
        normals = np.zeros_like(cross)
        normals[solid] = cross[solid] / area2[solid, None]
    a, b = pairs
    smooth = (
        solid[a]
        & solid[b]
        & (np.einsum("ij,ij->i", normals[a], normals[b]) > np.cos(np.radians(CREASE_ANGLE)))
    )
    m, n = f.shape[0], v.shape[0]
    # A face with a corner on a face of a smooth edge is in a part with something to
    # denoise: when every face has one (any noisy mesh), no part is still, and the
    # parts need not be found.
    busy_vertex = np.zeros(n, bool)
    busy_vertex[f[a[smooth]].ravel()] = True
    if busy_vertex[f].any(axis=1).all():
        return np.zeros(m, bool)
    # Parts: faces joined through shared vertices (a face and its corners, one graph).
    rows = np.repeat(np.arange(m), 3)
    graph = sp.coo_matrix((np.ones(3 * m), (rows, m + f.ravel())), shape=(m + n, m + n))
    _, label = connected_components(graph, directed=False)
    busy = np.zeros(label.max() + 1, bool)
    busy[label[a[smooth]]] = True
    return ~busy[label[:m]]


def still_vertices(vertices: np.ndarray, faces: np.ndarray, *, pairs=None) -> np.ndarray:
    """`[n_vertex]` the vertices of `still_faces` (every denoiser returns them as given);
    vertices no face references are not among them. `pairs` as `still_faces`'s."""
    f = np.asarray(faces, np.int64)
    out = np.zeros(np.asarray(vertices).shape[0], bool)
    out[f[still_faces(vertices, f, pairs=pairs)].ravel()] = True
    return out
