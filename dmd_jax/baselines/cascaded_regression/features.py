"""CNR's input: padded neighbourhood arrays and the filtered facet normal descriptor.

`prepare_mesh` builds a mesh's face rings, dual edges and corners on the host
(`dmd_jax.topology`) and pads them to bucketed sizes; `face_features` computes, in JAX,
the 93-number descriptor of every face in its local frame, the base normal the regressor
corrects, and the frame itself (see the package docstring for the definitions).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.baselines._common import count_trace, face_centroids, float_dtype
from dmd_jax.baselines.cascaded_regression.config import CNRConfig
from dmd_jax.geometry import face_areas, face_normals, safe_norm, safe_normalize
from dmd_jax.graph import bucket_size
from dmd_jax.mesh import canonical_frame, validate_mesh
from dmd_jax.topology import dual_edges, face_ring_pairs, vertex_corner_arrays

# --------------------------------------------------------------------------------------
# Host-side arrays, padded to bucketed sizes
# --------------------------------------------------------------------------------------


class MeshArrays(NamedTuple):
    """Index arrays of one mesh padded to bucketed sizes (see `prepare_mesh`).

    Padding faces are the degenerate triangle on the last (padding) vertex; padding ring
    pairs are self pairs of the last padding face; padding dual edges have weight 0.
    """

    faces: np.ndarray  # [Fp, 3] int32
    ring_r: np.ndarray  # [Mp] int32, sorted
    ring_s: np.ndarray  # [Mp] int32
    dual_a: np.ndarray  # [Dp] int32
    dual_b: np.ndarray  # [Dp] int32
    dual_w: np.ndarray  # [Dp] float, 1 on real dual edges
    corner_v: np.ndarray  # [3 Fp] int32
    corner_f: np.ndarray  # [3 Fp] int32
    face_mask: np.ndarray  # [Fp] bool


_RING_RATIO = 14


def prepare_mesh(faces, n_vertex: int) -> tuple[MeshArrays, int]:
    """Builds and pads the neighbourhoods of a mesh.

    Args:
      faces: `[n_face, 3]` int vertex indices.
      n_vertex: number of vertices.

    Returns:
      `(arrays, n_vertex_padded)`; vertex arrays must be padded to `n_vertex_padded` rows.
    """
    f = np.asarray(faces, np.int64)
    n_face = f.shape[0]
    rr, rs = face_ring_pairs(f, n_vertex)
    da, db = dual_edges(f, n_vertex)
    # Every padded size derives from one face bucket, so meshes of similar size share
    # one compiled program (a closed mesh has v ≈ f/2, 1.5 f dual edges and about 13
    # ring pairs per face).
    fp = bucket_size(n_face + 1)
    while fp < n_vertex + 1 or _RING_RATIO * fp < rr.size + 1 or 2 * fp < da.size + 1:
        fp = bucket_size(fp + 1)
    vp, mp, dp = fp, _RING_RATIO * fp, 2 * fp

    faces_p = np.full((fp, 3), vp - 1, np.int32)
    faces_p[:n_face] = f
    ring_r = np.full(mp, fp - 1, np.int32)
    ring_s = np.full(mp, fp - 1, np.int32)
    ring_r[: rr.size], ring_s[: rs.size] = rr, rs
    dual_a = np.zeros(dp, np.int32)
    dual_b = np.zeros(dp, np.int32)
    dual_w = np.zeros(dp)
    dual_a[: da.size], dual_b[: db.size], dual_w[: da.size] = da, db, 1.0
    cv, cf = vertex_corner_arrays(faces_p)
    mask = np.arange(fp) < n_face
    return MeshArrays(faces_p, ring_r, ring_s, dual_a, dual_b, dual_w, cv, cf, mask), vp


def pad_rows(x: np.ndarray, n: int) -> np.ndarray:
    """`x` `[m, ...]` padded with zero rows to `[n, ...]` (`n >= m`), same dtype."""
    out = np.zeros((n,) + x.shape[1:], x.dtype)
    out[: x.shape[0]] = x
    return out


# --------------------------------------------------------------------------------------
# Filtered facet normal descriptor
# --------------------------------------------------------------------------------------


def _filtered_normals(x, arr: MeshArrays, cfg: CNRConfig):
    """`[Fp, K + 1, 3]` unfiltered then bilaterally filtered normals, and `[Fp]` areas.

    All (σ_s, σ_r) chains are filtered together as one `[Fp, C, 3]` state, so the
    program has one loop per read-out iteration count instead of one per chain.
    """
    faces, rr, rs = arr.faces, arr.ring_r, arr.ring_s
    n_face = faces.shape[0]
    dt = x.dtype
    n0 = face_normals(x, faces)
    c = face_centroids(x, faces)
    area = face_areas(x, faces)
    # Relative areas: the normalised averages do not change and the products stay far
    # from underflow.
    area = area / jnp.maximum(jnp.max(area), jnp.finfo(dt).tiny)
    n_dual = jnp.sum(arr.dual_w)
    dist = safe_norm(c[arr.dual_a] - c[arr.dual_b])
    d_bar = jnp.sum(arr.dual_w * dist) / jnp.maximum(n_dual, 1.0)
    d_bar = jnp.where(d_bar > 0, d_bar, 1.0)
    d2 = jnp.sum((c[rr] - c[rs]) ** 2, axis=-1)

    n_r = len(cfg.sigma_r)
    sig_s = jnp.asarray(np.repeat(cfg.sigma_s, n_r), dt)  # [C], chain = i_s * n_r + i_r
    # 1 / (2 σ_r²); 0 for σ_r = ∞ (no range weight).
    inv_r = jnp.asarray(
        np.tile([0.0 if r is None else 0.5 / (r * r) for r in cfg.sigma_r], len(cfg.sigma_s)),
        dt,
    )
    spatial = area[rs, None] * jnp.exp(-0.5 * d2[:, None] / (sig_s * d_bar) ** 2)  # [M, C]

    def step(_, n):
        diff = jnp.sum((n[rr] - n[rs]) ** 2, axis=-1)  # [M, C]
        w = spatial * jnp.exp(-diff * inv_r)
        acc = jax.ops.segment_sum(
            w[..., None] * n[rs], rr, num_segments=n_face, indices_are_sorted=True
        )
        norm = jnp.sqrt(jnp.sum(acc * acc, axis=-1, keepdims=True))
        ok = norm > 0
        # As `weighted_normal_average`: only an exactly zero sum keeps the old normal.
        return jnp.where(ok, acc / jnp.where(ok, norm, 1.0), n)

    n = jnp.broadcast_to(n0[:, None, :], (n_face, sig_s.shape[0], 3))
    reads, done = [], 0
    for it in cfg.iterations:
        n = jax.lax.fori_loop(0, it - done, step, n)
        done = it
        reads.append(n)
    # Descriptor order: chain-major, then iteration (see `CNRConfig.normal_index`).
    filtered = jnp.stack(reads, axis=2).reshape(n_face, -1, 3)
    return jnp.concatenate([n0[:, None, :], filtered], axis=1), area


def face_features(x, arr: MeshArrays, cfg: CNRConfig):
    """Descriptor `[Fp, D]`, regression base `[Fp, 3]` and frames `[Fp, 3, 3]`.

    Frame rows are the local axes (x, y, z) in world coordinates: `R @ v` expresses a
    world vector `v` in the local frame.
    """
    normals, area = _filtered_normals(x, arr, cfg)
    n_face = normals.shape[0]
    g = normals[:, cfg.normal_index(cfg.guide)]
    m = normals[:, cfg.normal_index(cfg.feature)]
    ms = m[arr.ring_s]
    tensor = jax.ops.segment_sum(
        area[arr.ring_s, None, None] * ms[:, :, None] * ms[:, None, :],
        arr.ring_r,
        num_segments=n_face,
        indices_are_sorted=True,
    )
    # Any tangent basis (u, v) gives the same principal direction; u only has to be
    # well defined, so cross z with the axis it is least aligned with.
    e = jax.nn.one_hot(jnp.argmin(jnp.abs(g), axis=1), 3, dtype=x.dtype)
    u = safe_normalize(jnp.cross(g, e))
    v = jnp.cross(g, u)
    tu = jnp.einsum("fij,fj->fi", tensor, u)
    tv = jnp.einsum("fij,fj->fi", tensor, v)
    m00 = jnp.sum(u * tu, axis=1)
    m11 = jnp.sum(v * tv, axis=1)
    m01 = jnp.sum(u * tv, axis=1)
    theta = 0.5 * jnp.arctan2(2.0 * m01, m00 - m11)
    ax = jnp.cos(theta)[:, None] * u + jnp.sin(theta)[:, None] * v
    ax = jnp.where(jnp.sum(ax * m, axis=1, keepdims=True) < 0, -ax, ax)
    ay = jnp.cross(g, ax)
    frames = jnp.stack([ax, ay, g], axis=1)
    local = jnp.einsum("fij,fkj->fki", frames, normals)
    desc = local.reshape(n_face, -1)
    base = local[:, cfg.normal_index(cfg.feature)]
    return desc, base, frames


@partial(jax.jit, static_argnames=("cfg",))
def face_features_jit(x, arr, cfg):
    """`face_features` compiled once per padded size and config (traces are counted)."""
    count_trace("cnr_features")
    return face_features(x, arr, cfg)


def fnd(vertices, faces, *, config: CNRConfig | None = None):
    """The filtered facet normal descriptor of every face, and its local frames.

    Computed in the mesh's canonical frame (a similarity: the descriptor does not
    depend on it).

    Args:
      vertices: `[n_vertex, 3]` positions.
      faces: `[n_face, 3]` vertex indices.
      config: descriptor settings (default `CNRConfig()`).

    Returns:
      `(descriptor [n_face, D], frames [n_face, 3, 3])` float64 NumPy arrays; frame
      rows are the local x, y, z axes in the input's orientation.
    """
    cfg = config or CNRConfig()
    v, f = validate_mesh(vertices, faces, name="fnd")
    x = canonical_frame(v).apply(v)
    arr, vp = prepare_mesh(f, v.shape[0])
    dt = float_dtype()
    desc, _, frames = face_features_jit(jnp.asarray(pad_rows(x, vp), dt), to_jax(arr, dt), cfg)
    n_face = f.shape[0]
    return (
        np.asarray(desc[:n_face], np.float64),
        np.asarray(frames[:n_face], np.float64),
    )


def to_jax(arr: MeshArrays, dtype) -> MeshArrays:
    """`arr` as JAX arrays: float fields in `dtype`, index and mask fields as they are."""
    return MeshArrays(
        *(
            jnp.asarray(a, dtype) if np.issubdtype(a.dtype, np.floating) else jnp.asarray(a)
            for a in arr
        )
    )
