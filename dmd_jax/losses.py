"""DMD-Net's training losses (paper, appendix C), as pure jit-able JAX functions.

Every loss takes predicted and ground-truth arrays in the canonical frame of the mesh
(bounding box centred, longest side 1), returns a scalar, and accepts optional boolean
masks so the padding of a batch (`MeshGraph.vertex_mask`, `face_mask`) changes nothing.
Hyper-parameters are keyword-only. Shapes are checked with a `ValueError` (shapes are
static, so the checks also run under `jax.jit`).

* `vertex_loss`       mean squared Euclidean distance between corresponding vertices;
* `normal_loss`       mean angle between corresponding face normals;
* `curvature_loss`    Meyer et al. mean / Gaussian curvature errors weighted by the squared
                      ground-truth curvature, `γ_H L_H + γ_G L_G`;
* `chamfer_distance`  symmetric chamfer distance of squared distances, computed blockwise
                      (`chamfer_distance_batched` for a disjoint union of meshes);
* `feature_extractor_loss`  squared error of the feature extractor's `[n, 5]` output;
* `total_loss`        the weighted sum, skipping every term whose weight is 0.

Each mean is a `Term` (a sum and the count it is over) divided at the end: the `*_term`
functions return the `Term`, `loss_terms` every weighted `Term` of a batch, and
`reduce_terms` is the one place that divides and weighs them. Data-parallel training adds
the `Term`s of every device's group first, so it is the same loss as on one device.

Degenerate faces (zero area, or corners at the same position, as the padding faces
`(p, p, p)` are) give finite values and finite gradients everywhere.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax import geometry
from dmd_jax.config import LossConfig
from dmd_jax.constants import CREASE_ANGLE

# --------------------------------------------------------------------------------------
# Validation and masked reductions
# --------------------------------------------------------------------------------------


def _check_points(name: str, x, width: int = 3):
    if x.ndim != 2 or x.shape[-1] != width:
        raise ValueError(f"{name} must have shape [n, {width}], got {tuple(x.shape)}")


def _check_same(name_a: str, a, name_b: str, b):
    if a.shape != b.shape:
        raise ValueError(
            f"{name_a} and {name_b} must have the same shape, got {tuple(a.shape)} and "
            f"{tuple(b.shape)}"
        )


def _check_faces(faces):
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must have shape [n_face, 3], got {tuple(faces.shape)}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must hold integer vertex indices, got dtype {faces.dtype}")


def _check_per_item(name: str, x, n: int):
    """`x` as an array of shape `[n]` (None stays None), or a `ValueError` naming it."""
    if x is None:
        return None
    x = jnp.asarray(x)
    if x.shape != (n,):
        raise ValueError(f"{name} must have shape [{n}], got {tuple(x.shape)}")
    return x


def _check_mask(name: str, mask, n: int):
    mask = _check_per_item(name, mask, n)
    return None if mask is None else mask.astype(bool)


class Term(NamedTuple):
    """A loss term before its mean: `total` summed over `count` items.

    The items are valid vertices, faces or meshes, depending on the term. Sums and
    counts add across the groups of a data-parallel batch; the mean is taken once, by
    `mean` (0 when there is no item).
    """

    total: jax.Array
    count: jax.Array

    def mean(self):
        return self.total / jnp.maximum(self.count, 1).astype(self.total.dtype)


def _masked_term(values, mask, weight=None) -> Term:
    """Sum of `values [n]` over `mask [n]` (all if `None`) and how many were selected.

    With `weight [n]` (relative, > 0) the sum is weighted, the weights rescaled to
    average 1 over the selected items: the mean is the weighted mean, and the count
    stays the item count, so terms of several groups still add.
    """
    if mask is None and weight is None:
        return Term(jnp.sum(values), jnp.asarray(values.shape[0], jnp.int32))
    if mask is None:
        mask = jnp.ones(values.shape[0], bool)
    if weight is not None:
        weight = jnp.where(mask, weight, 0.0)
        values = values * weight * (jnp.sum(mask) / jnp.maximum(jnp.sum(weight), 1e-12))
    return Term(jnp.sum(jnp.where(mask, values, 0.0)), jnp.sum(mask, dtype=jnp.int32))


def crease_face_mask(target, faces, face_senders, face_receivers, *, angle=CREASE_ANGLE):
    """`[n_face]` bool: faces with a neighbour across an edge whose normal differs by at
    least `angle` degrees (the crease faces of `comparison.crease_faces`, on device).

    Args:
      target: `[n_vertex, 3]` positions (the clean mesh).
      faces: `[n_face, 3]` int vertex indices.
      face_senders, face_receivers: `[n_face_edge]` int dual edges (`MeshGraph`: faces
        sharing an edge, both ways; self loops and padding edges between degenerate
        faces add nothing).
      angle: the crease threshold in degrees.

    Returns:
      `[n_face]` bool; a zero-area face and its neighbours across it are no crease.
    """
    target, faces = jnp.asarray(target), jnp.asarray(faces)
    _check_points("target", target)
    _check_faces(faces)
    n = geometry.face_normals(target, faces)
    s, r = jnp.asarray(face_senders), jnp.asarray(face_receivers)
    if s.shape != r.shape or s.ndim != 1:
        raise ValueError(f"face_senders {s.shape} and face_receivers {r.shape} must be [n_edge]")
    pair_angle, ok = _unit_normal_angles(n[s], n[r])
    sharp = ok & (pair_angle >= math.radians(angle))
    return jax.ops.segment_max(sharp.astype(jnp.int32), r, num_segments=faces.shape[0]) > 0


# --------------------------------------------------------------------------------------
# Vertex loss
# --------------------------------------------------------------------------------------


def vertex_loss(pred, target, *, vertex_mask=None):
    """Mean squared Euclidean distance between corresponding vertices (eq. vertex_loss).

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.

    Returns:
      Scalar `mean_v |pred_v − target_v|²`. (This is three times the per-coordinate mean
      squared error, `torch.nn.MSELoss` on `[n, 3]`.)
    """
    return vertex_term(pred, target, vertex_mask=vertex_mask).mean()


def vertex_term(pred, target, *, vertex_mask=None) -> Term:
    """`vertex_loss` as a `Term`: squared distances summed over the valid vertices.

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.

    Returns:
      `Term` over the vertices selected by `vertex_mask` (all without it).
    """
    pred, target = jnp.asarray(pred), jnp.asarray(target)
    _check_points("pred", pred)
    _check_same("pred", pred, "target", target)
    mask = _check_mask("vertex_mask", vertex_mask, pred.shape[0])
    return _masked_term(jnp.sum((pred - target) ** 2, axis=-1), mask)


# --------------------------------------------------------------------------------------
# Normal loss
# --------------------------------------------------------------------------------------


def face_normal_angles(pred, target, faces):
    """Angle between corresponding unit face normals, per face.

    The angle is `atan2(|n_p × n_t|, n_p · n_t)`, which equals `arccos(n_p · n_t)` but is
    exact near 0 and π and has a bounded gradient there (an arccos of a clipped argument
    would have a floor of `sqrt(2ε)` and a `1/sqrt(ε)` gradient). A face that is
    degenerate in `pred` (zero normal) gets π/2, the mean angle between a random
    direction and a fixed one, with zero gradient.

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.

    Returns:
      `(angles, target_valid)`: `[n_face]` radians in `[0, π]`, and `[n_face]` bool,
      `False` where the target face has zero area (its normal is undefined; its angle
      is set to π/2 and should be left out of any mean).
    """
    pred, target, faces = jnp.asarray(pred), jnp.asarray(target), jnp.asarray(faces)
    _check_points("pred", pred)
    _check_same("pred", pred, "target", target)
    _check_faces(faces)
    n_t = geometry.face_normals(target, faces)
    angle, ok = _unit_normal_angles(geometry.face_normals(pred, faces), n_t)
    target_ok = jnp.sum(n_t * n_t, axis=-1) > 0.5
    return jnp.where(ok, angle, 0.5 * math.pi), target_ok


def _unit_normal_angles(n_p, n_t):
    """`(angle, ok)` per row between unit (or exactly zero) normals `[n, 3]`.

    `ok` is False where either normal is zero (`geometry.face_normals` of a degenerate
    face); there the angle is 0 with a zero gradient, for the caller to replace or mask.
    """
    ok = (jnp.sum(n_p * n_p, axis=-1) > 0.5) & (jnp.sum(n_t * n_t, axis=-1) > 0.5)
    sin = geometry.safe_norm(jnp.cross(n_p, n_t))
    cos = jnp.sum(n_p * n_t, axis=-1)
    # Double where: atan2(0, 0) has a NaN gradient, so the untaken branch sees (0, 1).
    return jnp.arctan2(jnp.where(ok, sin, 0.0), jnp.where(ok, cos, 1.0)), ok


def normal_loss(pred, target, faces, *, face_mask=None, degrees=False):
    """Mean angle between corresponding face normals (eq. normal_loss).

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      face_mask: optional `[n_face]` bool, `False` on padding.
      degrees: return degrees instead of radians (the paper reports degrees).

    Returns:
      Scalar mean angle over the faces that are selected by `face_mask` and have
      non-zero area in `target`; see `face_normal_angles` for degenerate `pred` faces.
    """
    loss = normal_term(pred, target, faces, face_mask=face_mask).mean()
    return loss * (180.0 / math.pi) if degrees else loss


def normal_term(pred, target, faces, *, face_mask=None, face_weight=None) -> Term:
    """`normal_loss` (radians) as a `Term` over the selected faces with a target normal;
    with `face_weight [n_face]` (relative, > 0) their weighted mean (`_masked_term`)."""
    faces = jnp.asarray(faces)
    angles, target_ok = face_normal_angles(pred, target, faces)
    mask = _check_mask("face_mask", face_mask, faces.shape[0])
    mask = target_ok if mask is None else mask & target_ok
    return _masked_term(angles, mask, _check_per_item("face_weight", face_weight, faces.shape[0]))


def predicted_normal_loss(pred_normals, target, faces, *, face_mask=None):
    """Mean angle between predicted unit face normals and the target mesh's.

    See `predicted_normal_term`; this is its mean.
    """
    return predicted_normal_term(pred_normals, target, faces, face_mask=face_mask).mean()


def predicted_normal_term(pred_normals, target, faces, *, face_mask=None, face_weight=None) -> Term:
    """Angles between predicted unit face normals and the target mesh's, as a `Term`.

    The loss of the normal-first head's own output (before its vertex update), in
    radians like `normal_loss`.

    Args:
      pred_normals: `[n_face, 3]` unit normals.
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      face_mask: optional `[n_face]` bool, `False` on padding.
      face_weight: optional `[n_face]` relative weights (> 0): a weighted mean.

    Returns:
      `Term` over the selected faces whose target (and prediction) is non-degenerate.
    """
    pred_normals, target, faces = map(jnp.asarray, (pred_normals, target, faces))
    _check_points("target", target)
    _check_faces(faces)
    if pred_normals.shape != faces.shape:
        raise ValueError(
            f"pred_normals must have shape [n_face, 3] = {faces.shape}, got {pred_normals.shape}"
        )
    angle, ok = _unit_normal_angles(pred_normals, geometry.face_normals(target, faces))
    mask = _check_mask("face_mask", face_mask, faces.shape[0])
    mask = ok if mask is None else mask & ok
    return _masked_term(angle, mask, _check_per_item("face_weight", face_weight, faces.shape[0]))


# --------------------------------------------------------------------------------------
# Curvature loss
# --------------------------------------------------------------------------------------

# A fixed non-degenerate triangle that stands in for faces whose corners coincide.
_STAND_IN_TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _without_coincident_faces(vertices, faces):
    """Routes faces with two coincident corners to a stand-in triangle.

    Such a face (the padding face `(p, p, p)` is one) adds only exact zeros to the angle
    sums, mixed areas and cotangent Laplacian of `dmd_jax.geometry`, but the gradient
    of `atan2(0, 0)` in its interior angles is NaN. Moving it onto three extra vertices
    leaves every curvature of the real vertices unchanged and the gradient finite.

    Returns:
      `([n_vertex + 3, 3] vertices, [n_face, 3] faces)`.
    """
    n = vertices.shape[0]
    p = vertices[faces]
    edge_sq = jnp.sum((p - jnp.roll(p, 1, axis=1)) ** 2, axis=-1)
    coincident = jnp.any(edge_sq == 0, axis=1)
    extra = jnp.asarray(_STAND_IN_TRIANGLE, dtype=vertices.dtype)
    stand_in = jnp.arange(n, n + 3, dtype=faces.dtype)
    return (
        jnp.concatenate([vertices, extra]),
        jnp.where(coincident[:, None], stand_in[None, :], faces),
    )


def _curvatures(vertices, faces):
    """`(κ_H [n], κ_G [n])` from `dmd_jax.geometry`, finite gradients on degenerate faces."""
    n = vertices.shape[0]
    v, f = _without_coincident_faces(vertices, faces)
    return geometry.mean_curvature(v, f)[:n], geometry.gaussian_curvature(v, f)[:n]


def _vertex_features(vertices, faces):
    """`geometry.vertex_features` with finite gradients on faces with coincident corners."""
    v, f = _without_coincident_faces(vertices, faces)
    return geometry.vertex_features(v, f)[: vertices.shape[0]]


def curvature_terms(pred, target, faces, *, vertex_mask=None):
    """The two unweighted curvature losses `(L_H, L_G)` (eqs. L_H and L_G).

    `L_H = mean_v |κH_out − κH_gt| · κH_gt²` and likewise for the Gaussian curvature,
    with Meyer et al.'s unsigned mean curvature and angle-defect Gaussian curvature.

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.
    """
    pred, target, faces = jnp.asarray(pred), jnp.asarray(target), jnp.asarray(faces)
    _check_points("pred", pred)
    _check_same("pred", pred, "target", target)
    _check_faces(faces)
    term_h, term_g = _curvature_terms(pred, target, faces, vertex_mask=vertex_mask)
    return term_h.mean(), term_g.mean()


def _curvature_terms(pred, target, faces, *, vertex_mask=None) -> tuple[Term, Term]:
    pred, target, faces = jnp.asarray(pred), jnp.asarray(target), jnp.asarray(faces)
    _check_points("pred", pred)
    _check_same("pred", pred, "target", target)
    _check_faces(faces)
    mask = _check_mask("vertex_mask", vertex_mask, pred.shape[0])
    kh_out, kg_out = _curvatures(pred, faces)
    kh_gt, kg_gt = _curvatures(target, faces)
    term_h = _masked_term(jnp.abs(kh_out - kh_gt) * kh_gt**2, mask)
    term_g = _masked_term(jnp.abs(kg_out - kg_gt) * kg_gt**2, mask)
    return term_h, term_g


def curvature_loss(pred, target, faces, *, gamma_h=1e-6, gamma_g=1.0, vertex_mask=None):
    """Curvature loss `γ_H L_H + γ_G L_G` (eq. curvature_loss); see `curvature_terms`.

    Args:
      pred: `[n_vertex, 3]` predicted positions.
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      gamma_h: weight of the mean-curvature term (paper: 1e-6).
      gamma_g: weight of the Gaussian-curvature term (paper: 1).
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.

    Returns:
      Scalar.
    """
    return curvature_term(
        pred, target, faces, gamma_h=gamma_h, gamma_g=gamma_g, vertex_mask=vertex_mask
    ).mean()


def curvature_term(pred, target, faces, *, gamma_h=1e-6, gamma_g=1.0, vertex_mask=None) -> Term:
    """`curvature_loss` as a `Term`: `γ_H L_H + γ_G L_G` summed over the valid vertices."""
    term_h, term_g = _curvature_terms(pred, target, faces, vertex_mask=vertex_mask)
    return Term(gamma_h * term_h.total + gamma_g * term_g.total, term_h.count)


# --------------------------------------------------------------------------------------
# Chamfer distance
# --------------------------------------------------------------------------------------


def _nearest_indices(x, x_graph, y, y_graph, y_valid, block_size: int, single_graph: bool):
    """Index of the nearest valid same-graph point of `y` for every point of `x`.

    Works on blocks of `block_size` points of `x` against all of `y`, so the largest
    intermediate is `[block_size, n_y]`. No gradient flows through the search.

    Returns:
      `(index [n_x] int, found [n_x] bool)`; `found` is `False` where `x`'s graph has no
      valid point in `y` (the index is then meaningless).
    """
    x, y = jax.lax.stop_gradient(x), jax.lax.stop_gradient(y)
    n_x = x.shape[0]
    n_block = -(-n_x // block_size)
    pad = n_block * block_size - n_x
    x_blocks = jnp.pad(x, ((0, pad), (0, 0))).reshape(n_block, block_size, 3)
    g_blocks = jnp.pad(x_graph, (0, pad)).reshape(n_block, block_size)
    # Ranking key |y|² − 2 x·y (|x|² is constant per row); invalid points never win.
    y_key = jnp.where(y_valid, jnp.sum(y * y, axis=-1), jnp.inf)

    def search(block):
        xs, gs = block
        # HIGHEST keeps TF32 matmuls (GPU default) out of the ranking.
        d = y_key[None, :] - 2.0 * jnp.dot(xs, y.T, precision=jax.lax.Precision.HIGHEST)
        if not single_graph:
            d = jnp.where(gs[:, None] == y_graph[None, :], d, jnp.inf)
        index = jnp.argmin(d, axis=1)
        found = jnp.isfinite(jnp.take_along_axis(d, index[:, None], axis=1)[:, 0])
        return index, found

    index, found = jax.lax.map(search, (x_blocks, g_blocks))
    return index.reshape(-1)[:n_x], found.reshape(-1)[:n_x]


def _one_sided(x, x_graph, x_valid, y, y_graph, y_valid, n_graph: int, block_size: int):
    """Per graph: sum over valid `x` of the squared distance to the nearest `y`, and count."""
    index, found = _nearest_indices(
        x, x_graph, y, y_graph, y_valid, block_size, single_graph=n_graph == 1
    )
    # Exact differences on the chosen pairs: no cancellation, and the gradient is the
    # gradient of the min almost everywhere.
    d = jnp.sum((x - y[index]) ** 2, axis=-1)
    use = x_valid & found
    total = jax.ops.segment_sum(jnp.where(use, d, 0.0), x_graph, num_segments=n_graph)
    count = jax.ops.segment_sum(x_valid.astype(d.dtype), x_graph, num_segments=n_graph)
    return total, count


def _check_block_size(block_size):
    if not isinstance(block_size, (int, np.integer)) or block_size < 1:
        raise ValueError(f"block_size must be a positive int, got {block_size!r}")
    return int(block_size)


def chamfer_distance_batched(
    a, b, a_graph, n_graph, *, b_graph=None, a_mask=None, b_mask=None, block_size=1024
):
    """Per-mesh chamfer distance of a disjoint union of meshes, averaged over meshes.

    Points are matched only to points of the same graph id. Graphs with no valid point in
    `a` or in `b` (the padding graph of a batch, say) are left out of the average.

    Args:
      a: `[n_a, 3]` points (predicted vertices).
      b: `[n_b, 3]` points (ground-truth vertices).
      a_graph: `[n_a]` int graph id of each point of `a`, in `[0, n_graph)`.
      n_graph: static number of graphs.
      b_graph: `[n_b]` graph ids of `b`; `a_graph` if omitted (then `n_a == n_b`).
      a_mask: optional `[n_a]` bool, `False` on padding.
      b_mask: optional `[n_b]` bool, `False` on padding.
      block_size: points of one side compared at once with all of the other; memory is
        `O(block_size · n)`.

    Returns:
      Scalar mean over graphs of the chamfer distance (eq. chamfer_loss).
    """
    return chamfer_term(
        a,
        b,
        a_graph,
        n_graph,
        b_graph=b_graph,
        a_mask=a_mask,
        b_mask=b_mask,
        block_size=block_size,
    ).mean()


def chamfer_term(
    a, b, a_graph, n_graph, *, b_graph=None, a_mask=None, b_mask=None, block_size=1024
) -> Term:
    """`chamfer_distance_batched` as a `Term`: per-graph distances summed over the graphs
    with a valid point on both sides, and how many there are."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    _check_points("a", a)
    _check_points("b", b)
    block_size = _check_block_size(block_size)
    n_graph = int(n_graph)
    if n_graph < 1:
        raise ValueError(f"n_graph must be at least 1, got {n_graph}")
    a_graph = jnp.asarray(a_graph)
    b_graph = a_graph if b_graph is None else jnp.asarray(b_graph)
    if a_graph.shape != (a.shape[0],):
        raise ValueError(f"a_graph must have shape [{a.shape[0]}], got {tuple(a_graph.shape)}")
    if b_graph.shape != (b.shape[0],):
        raise ValueError(f"b_graph must have shape [{b.shape[0]}], got {tuple(b_graph.shape)}")
    a_valid = _check_mask("a_mask", a_mask, a.shape[0])
    b_valid = _check_mask("b_mask", b_mask, b.shape[0])
    a_valid = jnp.ones(a.shape[0], bool) if a_valid is None else a_valid
    b_valid = jnp.ones(b.shape[0], bool) if b_valid is None else b_valid
    return _chamfer_per_graph_term(
        a, a_graph, a_valid, b, b_graph, b_valid, n_graph=n_graph, block_size=block_size
    )


# Jitted so that eager calls (metrics) compile the blockwise search once per shape.
@functools.partial(jax.jit, static_argnames=("n_graph", "block_size"))
def _chamfer_per_graph_term(a, a_graph, a_valid, b, b_graph, b_valid, *, n_graph, block_size):
    sum_ab, count_a = _one_sided(a, a_graph, a_valid, b, b_graph, b_valid, n_graph, block_size)
    sum_ba, count_b = _one_sided(b, b_graph, b_valid, a, a_graph, a_valid, n_graph, block_size)
    present = (count_a > 0) & (count_b > 0)
    per_graph = sum_ab / jnp.maximum(count_a, 1.0) + sum_ba / jnp.maximum(count_b, 1.0)
    return Term(jnp.sum(jnp.where(present, per_graph, 0.0)), jnp.sum(present, dtype=jnp.int32))


def chamfer_distance(a, b, *, a_mask=None, b_mask=None, block_size=1024):
    """Symmetric chamfer distance of squared distances between two point sets.

    `mean_{u∈a} min_{v∈b} |u − v|² + mean_{v∈b} min_{u∈a} |u − v|²` (eq. chamfer_loss),
    computed blockwise: memory is `O(block_size · n)`, never `n_a × n_b`.

    Args:
      a: `[n_a, 3]` points.
      b: `[n_b, 3]` points.
      a_mask: optional `[n_a]` bool, `False` on padding.
      b_mask: optional `[n_b]` bool, `False` on padding.
      block_size: points compared at once with the whole other set.

    Returns:
      Scalar (0 if either set has no valid point).
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    _check_points("a", a)
    _check_points("b", b)
    return chamfer_distance_batched(
        a,
        b,
        jnp.zeros(a.shape[0], jnp.int32),
        1,
        b_graph=jnp.zeros(b.shape[0], jnp.int32),
        a_mask=a_mask,
        b_mask=b_mask,
        block_size=block_size,
    )


# --------------------------------------------------------------------------------------
# Feature extractor loss
# --------------------------------------------------------------------------------------


def feature_extractor_loss(pred_features, target_features, *, vertex_mask=None):
    """Squared error of the feature extractor's output (eq. feature_extractor_loss).

    `mean_v |n_fe − n_gt|² + (κH_fe − κH_gt)² + (κG_fe − κG_gt)²`.

    Args:
      pred_features: `[n_vertex, 5]` estimated unit normal, κ_H, κ_G.
      target_features: `[n_vertex, 5]` the same of the clean mesh
        (`dmd_jax.geometry.vertex_features`).
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.

    Returns:
      Scalar.
    """
    return feature_term(pred_features, target_features, vertex_mask=vertex_mask).mean()


def feature_term(pred_features, target_features, *, vertex_mask=None) -> Term:
    """`feature_extractor_loss` as a `Term` over the valid vertices."""
    pred, target = jnp.asarray(pred_features), jnp.asarray(target_features)
    _check_points("pred_features", pred, width=5)
    _check_same("pred_features", pred, "target_features", target)
    mask = _check_mask("vertex_mask", vertex_mask, pred.shape[0])
    return _masked_term(jnp.sum((pred - target) ** 2, axis=-1), mask)


# --------------------------------------------------------------------------------------
# Weighted total
# --------------------------------------------------------------------------------------

# Every term `loss_terms` can compute, in the order they are reported.
TERMS = ("vertex", "normal", "curvature", "chamfer", "feature", "face_normal")


def _static_weight(name: str, value) -> float:
    try:
        w = float(value)
    except (TypeError, jax.errors.ConcretizationTypeError) as err:
        raise ValueError(
            f"loss weight {name!r} must be a static Python number (a traced value cannot "
            "decide whether the term is computed); close over the weights or mark them "
            "static in jax.jit"
        ) from err
    if not math.isfinite(w) or w < 0:
        raise ValueError(f"loss weight {name!r} must be finite and >= 0, got {value!r}")
    return w


def _weights(weights: LossConfig) -> dict[str, float]:
    return {name: _static_weight(name, getattr(weights, name)) for name in TERMS}


def loss_terms(
    pred,
    target,
    faces,
    pred_features=None,
    target_features=None,
    *,
    weights: LossConfig | None = None,
    pred_face_normals=None,
    vertex_mask=None,
    face_mask=None,
    face_weight=None,
    vertex_graph=None,
    n_graph=None,
) -> dict[str, Term]:
    """Every loss term with a non-zero weight, as a `Term` (not yet divided or weighted).

    Vertex, curvature and feature terms are over the valid vertices of the batch, the
    normal terms over its valid faces; the chamfer term is matched within each mesh and
    counts meshes when `vertex_graph` is given (a batch that is a disjoint union of
    meshes), otherwise the batch is one point set.

    Args:
      pred: `[n_vertex, 3]` predicted positions (canonical frame).
      target: `[n_vertex, 3]` ground-truth positions.
      faces: `[n_face, 3]` int vertex indices.
      pred_features: `[n_vertex, 5]` feature extractor output; needed when
        `weights.feature > 0`.
      target_features: `[n_vertex, 5]`; computed from `target` with
        `geometry.vertex_features` if omitted.
      weights: the static weights and curvature and chamfer settings (`LossConfig`;
        default: the paper's final weights).
      pred_face_normals: `[n_face, 3]` unit normals of a normal-first head; the
        `face_normal` term is computed when they are given and weighted.
      vertex_mask: optional `[n_vertex]` bool, `False` on padding.
      face_mask: optional `[n_face]` bool, `False` on padding.
      face_weight: optional `[n_face]` relative weights (> 0) of the faces in the normal
        and face-normal terms (e.g. `LossConfig.crease_weight` on `crease_face_mask`).
      vertex_graph: optional `[n_vertex]` int graph id per vertex (`MeshGraph.vertex_graph`).
      n_graph: static number of graphs; required with `vertex_graph`.

    Returns:
      `{name: Term}` for the computed terms, named as in `TERMS`.
    """
    weights = LossConfig() if weights is None else weights
    pred, target, faces = jnp.asarray(pred), jnp.asarray(target), jnp.asarray(faces)
    _check_points("pred", pred)
    _check_same("pred", pred, "target", target)
    _check_faces(faces)
    w = _weights(weights)
    if (vertex_graph is None) != (n_graph is None):
        raise ValueError("vertex_graph and n_graph must be given together")

    terms = {}
    if w["vertex"]:
        terms["vertex"] = vertex_term(pred, target, vertex_mask=vertex_mask)
    if w["normal"]:
        terms["normal"] = normal_term(
            pred, target, faces, face_mask=face_mask, face_weight=face_weight
        )
    if w["curvature"]:
        terms["curvature"] = curvature_term(
            pred,
            target,
            faces,
            gamma_h=weights.gamma_h,
            gamma_g=weights.gamma_g,
            vertex_mask=vertex_mask,
        )
    if w["chamfer"]:
        single = vertex_graph is None
        terms["chamfer"] = chamfer_term(
            pred,
            target,
            jnp.zeros(pred.shape[0], jnp.int32) if single else vertex_graph,
            1 if single else n_graph,
            a_mask=vertex_mask,
            b_mask=vertex_mask,
            block_size=weights.chamfer_block,
        )
    if w["feature"]:
        if pred_features is None:
            raise ValueError("weights.feature > 0 needs pred_features (the extractor output)")
        if target_features is None:
            target_features = _vertex_features(target, faces)
        terms["feature"] = feature_term(pred_features, target_features, vertex_mask=vertex_mask)
    if w["face_normal"] and pred_face_normals is not None:
        terms["face_normal"] = predicted_normal_term(
            pred_face_normals, target, faces, face_mask=face_mask, face_weight=face_weight
        )
    return terms


def reduce_terms(terms: dict[str, Term], weights: LossConfig | None = None):
    """The loss from its terms: each `Term`'s mean, weighted and summed.

    The one place where terms are divided, so a data-parallel step that adds the
    `Term`s of its groups first gives the loss of the whole batch.

    Args:
      terms: `{name: Term}` from `loss_terms` (or their sums over groups).
      weights: the `LossConfig` the terms were computed with.

    Returns:
      `(total, means)`: the scalar weighted sum, and `{name: mean}` unweighted.
    """
    w = _weights(LossConfig() if weights is None else weights)
    means = {name: term.mean() for name, term in terms.items()}
    dtype = next(iter(means.values())).dtype if means else jnp.float32
    total = sum((w[name] * value for name, value in means.items()), jnp.zeros((), dtype))
    return total, means


def total_loss(pred, target, faces, pred_features=None, target_features=None, **kwargs):
    """Weighted sum of the DMD-Net losses; terms with weight 0 are skipped entirely.

    `reduce_terms(loss_terms(...))`; the arguments are those of `loss_terms`.

    Returns:
      `(total, components)`: scalar weighted sum, and a dict of the unweighted means
      of the terms that were computed, keyed as in `TERMS`.
    """
    terms = loss_terms(pred, target, faces, pred_features, target_features, **kwargs)
    return reduce_terms(terms, kwargs.get("weights"))
