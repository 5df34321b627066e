"""CNR: Wang, Liu & Tong, "Mesh denoising via cascaded normal regression", SIGGRAPH Asia 2016.

The learned baseline of the paper's comparison tables. Each cascade stage computes a
per-face *filtered facet normal descriptor* (FND) of the current mesh, regresses the
clean face normal from it, and moves the vertices onto the regressed normals with Sun et
al.'s update (`fit_vertices_to_normals`, the one BNF and GNF use). This module's version:

* **FND.** Bilateral normal filtering (Zheng et al. 2011, local scheme, as `bnf`) of the
  face normals of the current mesh over the vertex 1-ring (faces sharing a vertex, the
  face itself included), weight `A_j · exp(−|c_i − c_j|² / 2σ_s²) · exp(−|n_i − n_j|² /
  2σ_r²)`, for every pair of σ_s ∈ {1, 2} × d̄ (d̄ the mean distance between the
  centroids of edge-adjacent faces, re-measured on each stage's mesh) and σ_r ∈ {0.1,
  0.2, 0.35, 0.5, ∞}, each read after 1, 3 and 8 iterations: 30 filtered normals plus
  the unfiltered one, 93 numbers per face (`CNRConfig` holds the sets).
* **Rotation invariance.** Every normal of the descriptor is written in a local frame
  per face: z is the most smoothed normal (σ_s = 2d̄, σ_r = ∞, 8 iterations); x is the
  principal direction, in the plane ⟂ z, of the area-weighted normal tensor
  `Σ_j A_j m_j m_jᵀ` over the 1-ring of the feature-preserving filtered normals m
  (σ_s = d̄, σ_r = 0.35, 3 iterations); its sign makes `x · m_i ≥ 0` (the face's own
  filtered normal leans to +x: at a crease that is the face's side); y = z × x. The
  paper aligns the descriptor with the eigenvectors of a normal tensor too; this frame
  is that idea made unique (sign and in-plane angle fixed) wherever the tensor's two
  tangent eigenvalues differ. The regressed normal is predicted in this frame and
  rotated back.
* **Regressor.** The paper clusters the descriptors and trains one single-hidden-layer
  network per cluster; here one MLP per stage (hidden widths `CNRConfig.hidden`, ReLU)
  predicts a correction added to the feature-preserving filtered normal (in the local
  frame), normalised. Zero-initialised output layer: an untrained stage is one
  bilateral-filter step.
* **Cascade.** Two stages by default (the paper uses 2–4); each stage's vertex update
  runs `vertex_iterations` Jacobi passes.

Training (`train_cnr`, or `dmd-jax train-cnr --data data/gen_v1 --out FILE`)
corrupts the clean training meshes the way `dmd_jax.pipeline.corrupt` does (random
rotation, mixed noise of four kinds with canonical and edge-relative levels), samples
faces, fits stage 1 with Adam on the squared distance between unit normals, runs stage
1 on every training mesh, fits stage 2 on the stage-1 outputs, and so on. Weights are
one msgpack file (`flax.serialization`, no pickle) holding the params of every stage and
the `CNRConfig` as JSON; `cnr_small.msgpack` ships in `dmd_jax/weights/`.

All computation runs in the mesh's canonical frame (like the classic baselines), so
`cnr` is translation and scale equivariant. Host-side index arrays are padded to bucketed
sizes so that meshes of similar size share one compiled program.
"""

from __future__ import annotations

import dataclasses
import math
import platform
import time
from collections.abc import Callable, Sequence
from functools import lru_cache, partial
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from dmd_jax.baselines._common import (
    count_trace,
    face_centroids,
    fit_vertices_to_normals,
    float_dtype,
    run_in_canonical_frame,
)
from dmd_jax.checkpoints import read_weights_file, write_weights_file
from dmd_jax.geometry import face_areas, face_normals, safe_norm, safe_normalize
from dmd_jax.graph import bucket_size
from dmd_jax.mesh import canonical_frame, validate_mesh
from dmd_jax.topology import dual_edges, face_ring_pairs, vertex_corner_arrays

WEIGHTS_FORMAT = "dmd_jax-cnr-weights"
WEIGHTS_VERSION = 1
BUNDLED_NAME = "cnr_small.msgpack"


# --------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CNRConfig:
    """Descriptor, regressor and cascade settings (hashable: a static jit argument).

    Attributes:
      sigma_s: spatial σ of the bilateral filters, multiples of d̄.
      sigma_r: range σ on `|n_i − n_j|`; `None` means ∞ (no range weight).
      iterations: increasing filter iteration counts at which the normals are read.
      guide: `(i_s, i_r, i_it)` indices of the filtered normal that is the frame's z.
      feature: indices of the filtered normal that sets the frame's x and is the base
        the regressor corrects.
      hidden: hidden layer widths of each stage's MLP.
      n_stages: cascade length.
      vertex_iterations: vertex update passes per stage.
    """

    sigma_s: tuple[float, ...] = (1.0, 2.0)
    sigma_r: tuple[float | None, ...] = (0.1, 0.2, 0.35, 0.5, None)
    iterations: tuple[int, ...] = (1, 3, 8)
    guide: tuple[int, int, int] = (1, 4, 2)
    feature: tuple[int, int, int] = (0, 2, 1)
    hidden: tuple[int, ...] = (128, 128, 64)
    n_stages: int = 2
    vertex_iterations: int = 20

    def __post_init__(self):
        for name in ("sigma_s", "sigma_r", "iterations", "guide", "feature", "hidden"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if not self.sigma_s or any(not (math.isfinite(s) and s > 0) for s in self.sigma_s):
            raise ValueError(f"sigma_s must be finite numbers > 0, got {self.sigma_s}")
        if not self.sigma_r or any(
            r is not None and not (math.isfinite(r) and r > 0) for r in self.sigma_r
        ):
            raise ValueError(f"sigma_r must be numbers > 0 or None (∞), got {self.sigma_r}")
        its = self.iterations
        if not its or any(int(i) != i or i < 1 for i in its) or list(its) != sorted(set(its)):
            raise ValueError(f"iterations must be increasing integers >= 1, got {its}")
        sizes = (len(self.sigma_s), len(self.sigma_r), len(self.iterations))
        for name in ("guide", "feature"):
            idx = getattr(self, name)
            if len(idx) != 3 or any(not 0 <= i < n for i, n in zip(idx, sizes, strict=True)):
                raise ValueError(f"{name} must index (sigma_s, sigma_r, iterations), got {idx}")
        if any(int(w) != w or w < 1 for w in self.hidden):
            raise ValueError(f"hidden widths must be integers >= 1, got {self.hidden}")
        if int(self.n_stages) != self.n_stages or self.n_stages < 1:
            raise ValueError(f"n_stages must be an integer >= 1, got {self.n_stages}")
        if int(self.vertex_iterations) != self.vertex_iterations or self.vertex_iterations < 0:
            raise ValueError(f"vertex_iterations must be >= 0, got {self.vertex_iterations}")

    @property
    def n_filtered(self) -> int:
        return len(self.sigma_s) * len(self.sigma_r) * len(self.iterations)

    @property
    def descriptor_dim(self) -> int:
        """Numbers per face: 3 × (filtered normals + the unfiltered one)."""
        return 3 * (self.n_filtered + 1)

    def normal_index(self, which: tuple[int, int, int]) -> int:
        """Position of a filtered normal in the descriptor (0 is the unfiltered normal)."""
        i_s, i_r, i_it = which
        return 1 + (i_s * len(self.sigma_r) + i_r) * len(self.iterations) + i_it

    def to_dict(self) -> dict:
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> CNRConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown CNRConfig field(s): {', '.join(unknown)}")
        return cls(**d)


def _jsonable(x):
    return list(x) if isinstance(x, tuple) else x


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


def _pad_rows(x: np.ndarray, n: int) -> np.ndarray:
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


def _features(x, arr: MeshArrays, cfg: CNRConfig):
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
def _features_jit(x, arr, cfg):
    count_trace("cnr_features")
    return _features(x, arr, cfg)


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
    desc, _, frames = _features_jit(jnp.asarray(_pad_rows(x, vp), dt), _to_jax(arr, dt), cfg)
    n_face = f.shape[0]
    return (
        np.asarray(desc[:n_face], np.float64),
        np.asarray(frames[:n_face], np.float64),
    )


def _to_jax(arr: MeshArrays, dtype) -> MeshArrays:
    return MeshArrays(
        *(
            jnp.asarray(a, dtype) if np.issubdtype(a.dtype, np.floating) else jnp.asarray(a)
            for a in arr
        )
    )


# --------------------------------------------------------------------------------------
# Regressor and cascade stage
# --------------------------------------------------------------------------------------


class CNRRegressor(nn.Module):
    """MLP: descriptor `[f, D]` and base normal `[f, 3]` (local frame) → unit normal `[f, 3]`."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, desc, base):
        h = desc
        for width in self.hidden:
            h = nn.relu(nn.Dense(width)(h))
        delta = nn.Dense(3, kernel_init=nn.initializers.zeros)(h)
        return safe_normalize(base + delta)


def _stage(params, x, arr: MeshArrays, cfg: CNRConfig):
    """One cascade stage: `[Vp, 3]` vertices → updated vertices and `[Fp, 3]` normals."""
    desc, base, frames = _features(x, arr, cfg)
    y = CNRRegressor(cfg.hidden).apply({"params": params}, desc, base)
    normals = jnp.einsum("fji,fj->fi", frames, y)
    normals = jnp.where(arr.face_mask[:, None], normals, 0.0)
    free = jnp.ones(x.shape[0], x.dtype)
    moved = fit_vertices_to_normals(
        x, arr.faces, normals, arr.corner_v, arr.corner_f, free, cfg.vertex_iterations
    )
    return moved, normals


@partial(jax.jit, static_argnames=("cfg",))
def _stage_jit(params, x, arr, cfg):
    count_trace("cnr")
    return _stage(params, x, arr, cfg)


# --------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------


class CNRWeights(NamedTuple):
    """Per-stage regressor params, the config that built them, and provenance."""

    params: tuple  # one flax params dict per stage
    config: CNRConfig
    meta: dict


def _abstract_stage_params(cfg: CNRConfig):
    d = jnp.zeros((1, cfg.descriptor_dim), jnp.float32)
    b = jnp.zeros((1, 3), jnp.float32)
    return jax.eval_shape(
        lambda: CNRRegressor(cfg.hidden).init(jax.random.PRNGKey(0), d, b)["params"]
    )


def _check_stage_params(params, cfg: CNRConfig, name: str) -> None:
    expected = _abstract_stage_params(cfg)
    exp = {
        jax.tree_util.keystr(p): x.shape for p, x in jax.tree_util.tree_leaves_with_path(expected)
    }
    got = {
        jax.tree_util.keystr(p): np.shape(x) for p, x in jax.tree_util.tree_leaves_with_path(params)
    }
    if exp != got:
        raise ValueError(f"{name}: stage params do not match the config ({got} vs {exp})")


def save_cnr_weights(path, weights: CNRWeights, *, overwrite: bool = False) -> Path:
    """Writes a `CNRWeights` as one msgpack file (float32 params), atomically."""
    if len(weights.params) < 1:
        raise ValueError("CNRWeights holds no stage")
    params = {
        str(i): jax.tree.map(lambda a: np.asarray(a, np.float32), p)
        for i, p in enumerate(weights.params)
    }
    return write_weights_file(
        path,
        fmt=WEIGHTS_FORMAT,
        version=WEIGHTS_VERSION,
        config=weights.config.to_dict(),
        meta=weights.meta,
        params=params,
        overwrite=overwrite,
    )


def load_cnr_weights(path) -> CNRWeights:
    """Reads a file written by `save_cnr_weights`, checking format, version and shapes."""
    cfg, meta, raw = read_weights_file(
        path,
        fmt=WEIGHTS_FORMAT,
        version=WEIGHTS_VERSION,
        kind="CNR",
        parse_config=CNRConfig.from_dict,
    )
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: params must be a dict of stages")
    stages = tuple(raw[str(i)] for i in range(len(raw)))
    if len(stages) != cfg.n_stages:
        raise ValueError(f"{path}: {len(stages)} stages stored, config says {cfg.n_stages}")
    for i, p in enumerate(stages):
        _check_stage_params(p, cfg, f"{path} stage {i}")
    return CNRWeights(params=stages, config=cfg, meta=meta)


def bundled_weights_path() -> Path:
    """Where the bundled `cnr_small.msgpack` lives in the installed package."""
    return Path(str(resources.files("dmd_jax") / "weights" / BUNDLED_NAME))


@lru_cache(maxsize=1)
def load_bundled_cnr() -> CNRWeights:
    """The bundled CNR weights (trained on `data/gen_v1`; provenance in `.meta`)."""
    path = bundled_weights_path()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the bundled CNR weights are missing")
    return load_cnr_weights(path)


def _resolve_weights(weights) -> CNRWeights:
    if weights is None:
        return load_bundled_cnr()
    if isinstance(weights, CNRWeights):
        return weights
    if isinstance(weights, (str, Path)):
        return load_cnr_weights(weights)
    raise ValueError(f"weights must be None, a path or CNRWeights, got {type(weights).__name__}")


# --------------------------------------------------------------------------------------
# Denoising
# --------------------------------------------------------------------------------------


def cnr(vertices, faces, *, weights=None, stages: int | None = None) -> np.ndarray:
    """Cascaded normal regression (Wang, Liu & Tong 2016), this project's version.

    Args:
      vertices: `[n_vertex, 3]` noisy positions (any frame).
      faces: `[n_face, 3]` vertex indices.
      weights: `CNRWeights`, a weights file, or `None` for the bundled weights.
      stages: run only the first `stages` cascade stages (default: all).

    Returns:
      `[n_vertex, 3]` float64 denoised positions.
    """
    w = _resolve_weights(weights)
    n_stages = len(w.params) if stages is None else stages
    if (
        isinstance(n_stages, bool)
        or int(n_stages) != n_stages
        or not 0 <= n_stages <= len(w.params)
    ):
        raise ValueError(f"cnr: stages must be an integer in [0, {len(w.params)}], got {stages!r}")

    def core(v, f):
        dt = float_dtype()
        arr, vp = prepare_mesh(f, v.shape[0])
        arr = _to_jax(arr, dt)
        x = jnp.asarray(_pad_rows(v, vp), dt)
        for p in w.params[: int(n_stages)]:
            x, _ = _stage_jit(jax.tree.map(lambda a: jnp.asarray(a, dt), p), x, arr, w.config)
        return np.asarray(x[: v.shape[0]])

    return run_in_canonical_frame(vertices, faces, core, name="cnr")


# --------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------


class StageSamples(NamedTuple):
    """Training samples of one stage (NumPy): descriptor, base and target, local frame."""

    desc: np.ndarray  # [s, D]
    base: np.ndarray  # [s, 3]
    target: np.ndarray  # [s, 3] clean unit normal in the face's local frame


def stage_samples(x, clean, arr: MeshArrays, n_face: int, cfg: CNRConfig, idx) -> StageSamples:
    """Descriptors of the faces `idx` of a padded mesh and their clean normals.

    Args:
      x: `[Vp, 3]` current (noisy or partly denoised) vertices, padded.
      clean: `[Vp, 3]` clean vertices, same frame, padded.
      arr: `prepare_mesh` arrays (JAX).
      n_face: number of real faces.
      cfg: the config.
      idx: `[s]` indices of the faces to sample, in `[0, n_face)`.
    """
    del n_face
    desc, base, frames = _features_jit(x, arr, cfg)
    n_clean = face_normals(clean, arr.faces)
    target = jnp.einsum("fij,fj->fi", frames, n_clean)
    idx = np.asarray(idx)
    return StageSamples(np.asarray(desc)[idx], np.asarray(base)[idx], np.asarray(target)[idx])


def stage_loss(params, cfg: CNRConfig, desc, base, target):
    """Mean squared distance between regressed and clean unit normals (`2 − 2 cos`)."""
    y = CNRRegressor(cfg.hidden).apply({"params": params}, desc, base)
    return jnp.mean(jnp.sum((y - target) ** 2, axis=-1))


def fit_stage(
    samples: StageSamples,
    cfg: CNRConfig,
    *,
    steps: int,
    batch_size: int = 1024,
    learning_rate: float = 2e-3,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> tuple[Any, list[float]]:
    """Fits one stage's regressor with Adam (cosine-decayed learning rate).

    Args:
      samples: the stage's training samples.
      cfg: the config.
      steps: Adam steps.
      batch_size: samples per step (drawn with replacement).
      learning_rate: peak learning rate.
      seed: initialisation and batch sampling seed.
      log: optional progress printer.

    Returns:
      `(params, losses)`: the fitted params and the mini-batch loss of every step.
    """
    n = samples.desc.shape[0]
    if n == 0:
        raise ValueError("fit_stage: no training samples")
    if steps < 1 or batch_size < 1:
        raise ValueError("fit_stage: steps and batch_size must be >= 1")
    model = CNRRegressor(cfg.hidden)
    dt = samples.desc.dtype
    params = model.init(
        jax.random.PRNGKey(seed), jnp.asarray(samples.desc[:1]), jnp.asarray(samples.base[:1])
    )["params"]
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, steps, alpha=0.05))
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, d, b, t):
        loss, grads = jax.value_and_grad(stage_loss)(params, cfg, d, b, t)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    rng = np.random.default_rng(seed)
    desc = jnp.asarray(samples.desc, dt)
    base = jnp.asarray(samples.base, dt)
    target = jnp.asarray(samples.target, dt)
    losses = []
    for i in range(int(steps)):
        idx = jnp.asarray(rng.integers(0, n, min(batch_size, n)))
        params, opt_state, loss = step(params, opt_state, desc[idx], base[idx], target[idx])
        losses.append(float(loss))
        if log is not None and (i + 1) % max(1, steps // 10) == 0:
            log(f"  step {i + 1}/{steps}  loss {np.mean(losses[-100:]):.5f}")
    return params, losses


def train_cnr(
    meshes: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    config: CNRConfig | None = None,
    draws: int = 1,
    faces_per_mesh: int = 512,
    steps: int = 2000,
    batch_size: int = 1024,
    learning_rate: float = 2e-3,
    seed: int = 0,
    noise=None,
    log: Callable[[str], None] | None = None,
) -> CNRWeights:
    """Trains every cascade stage on noisy copies of clean meshes.

    Each clean mesh is corrupted `draws` times with `dmd_jax.pipeline.corrupt` (random
    rotation, mixed noise; the key of draw d of mesh i is `fold_in(fold_in(seed, i), d)`;
    the vertex array is padded to a size bucket first, see below),
    and `faces_per_mesh` faces of each copy are sampled. Stage k is trained on the
    outputs of stages 0..k−1.

    Args:
      meshes: clean `(vertices, faces)` pairs.
      config: descriptor and regressor settings.
      draws: noisy copies per mesh.
      faces_per_mesh: faces sampled per copy and stage (all when fewer).
      steps, batch_size, learning_rate: Adam settings per stage.
      seed: the run's seed.
      noise: `dmd_jax.config.NoiseConfig` (default: the paper's mixed noise).
      log: optional progress printer.

    Returns:
      The trained `CNRWeights` (meta records the settings and per-stage losses).
    """
    from dmd_jax.config import NoiseConfig
    from dmd_jax.pipeline import corrupt

    cfg = config or CNRConfig()
    noise = noise or NoiseConfig()
    if not meshes:
        raise ValueError("train_cnr: no training meshes")
    dt = float_dtype()
    say = log or (lambda _msg: None)
    base_key = jax.random.PRNGKey(seed)
    rng = np.random.default_rng(seed)
    # Noisy copies and targets, padded; the current mesh of every copy is advanced
    # stage by stage.
    copies = []
    for i, (v, f) in enumerate(meshes):
        v = np.asarray(v, np.float64)
        f = np.asarray(f, np.int32)
        n = v.shape[0]
        # Padding rows repeat vertex 0 (no face uses them; the clean bounding box and
        # edge lengths do not change), so the noise sampler compiles once per size
        # bucket instead of once per mesh. Their noise may stretch the noisy frame a
        # little, which CNR cannot see: its descriptor is similarity invariant.
        vp = np.concatenate([v, np.repeat(v[:1], bucket_size(n + 1) - n, axis=0)])
        for d in range(draws):
            key = jax.random.fold_in(jax.random.fold_in(base_key, i), d)
            noisy, clean, _ = corrupt(key, vp, f, rotate=True, noise=noise)
            copies.append((i, noisy[:n], clean[:n]))
        if (i + 1) % 50 == 0:
            say(f"corrupted {i + 1}/{len(meshes)} meshes")
    say(f"{len(copies)} noisy copies of {len(meshes)} meshes")

    stage_params, meta_losses = [], []
    t0 = time.perf_counter()
    for stage in range(cfg.n_stages):
        parts = []
        arrays_of = {}
        for j, (i, x, clean) in enumerate(copies):
            f = np.asarray(meshes[i][1], np.int32)
            if i not in arrays_of:
                arrays_of.clear()
                arr, vp = prepare_mesh(f, x.shape[0])
                arrays_of[i] = (_to_jax(arr, dt), vp)
            arr, vp = arrays_of[i]
            xp = jnp.asarray(_pad_rows(x, vp), dt)
            if stage > 0:
                xp, _ = _stage_jit(stage_params[-1], xp, arr, cfg)
                copies[j] = (i, np.asarray(xp[: x.shape[0]], np.float64), clean)
            n_face = f.shape[0]
            idx = rng.choice(n_face, min(n_face, faces_per_mesh), replace=False)
            cp = jnp.asarray(_pad_rows(clean, vp), dt)
            parts.append(stage_samples(xp, cp, arr, n_face, cfg, idx))
        samples = StageSamples(*(np.concatenate(a) for a in zip(*parts, strict=True)))
        say(
            f"stage {stage}: {samples.desc.shape[0]} samples "
            f"({time.perf_counter() - t0:.0f} s); fitting"
        )
        params, losses = fit_stage(
            samples,
            cfg,
            steps=steps,
            batch_size=batch_size,
            learning_rate=learning_rate,
            seed=seed + stage,
            log=say,
        )
        stage_params.append(jax.tree.map(np.asarray, params))
        meta_losses.append(
            {"first_100": float(np.mean(losses[:100])), "last_100": float(np.mean(losses[-100:]))}
        )
        say(f"stage {stage} done ({time.perf_counter() - t0:.0f} s)")
    meta = {
        "method": "CNR (Wang, Liu & Tong 2016), dmd_jax version",
        "n_meshes": len(meshes),
        "draws": draws,
        "faces_per_mesh": faces_per_mesh,
        "steps": steps,
        "batch_size": batch_size,
        "learning_rate": learning_rate,
        "seed": seed,
        "noise": noise.to_dict(),
        "stage_losses": meta_losses,
        "train_seconds": round(time.perf_counter() - t0, 1),
    }
    return CNRWeights(params=tuple(stage_params), config=cfg, meta=meta)


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def train_main(args, command: str) -> Path:
    """Trains CNR on a dataset's train split and writes the weights (`dmd-jax train-cnr`).

    Args:
      args: namespace with `data`, `out`, `overwrite`, `max_meshes`, `draws`,
        `faces_per_mesh`, `steps`, `batch_size`, `lr`, `seed`, `stages`, `hidden`,
        `vertex_iterations`, `eval_meshes` (see the `train-cnr` subcommand).
      command: the command line, stored in the weights' provenance.

    Returns:
      The path written.
    """
    from dmd_jax.config import NoiseConfig
    from dmd_jax.data import load_dataset
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.pipeline import corrupt

    ds = load_dataset(args.data)
    records = ds.split("train")
    if args.max_meshes is not None:
        records = records[: args.max_meshes]
    meshes = [r.load() for r in records]
    cfg = CNRConfig(
        hidden=tuple(args.hidden), n_stages=args.stages, vertex_iterations=args.vertex_iterations
    )
    t0 = time.perf_counter()
    weights = train_cnr(
        meshes,
        config=cfg,
        draws=args.draws,
        faces_per_mesh=args.faces_per_mesh,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        seed=args.seed,
        log=lambda m: print(m, flush=True),
    )
    wall = time.perf_counter() - t0
    meta = dict(weights.meta)
    meta.update(
        command=command,
        dataset=str(args.data),
        wall_seconds=round(wall, 1),
        machine=f"{platform.machine()} {platform.processor() or ''}".strip(),
        jax=jax.__version__,
    )
    # A held-out check on test-intra meshes with fixed noise.
    evals = []
    for k, rec in enumerate(ds.split("test_intra")[: args.eval_meshes]):
        v, f = rec.load()
        noisy, clean, _ = corrupt(
            jax.random.fold_in(jax.random.PRNGKey(10_000 + args.seed), k),
            v,
            f,
            rotate=True,
            noise=NoiseConfig(),
        )
        before = mesh_metrics(noisy, clean, f)["normal_deg"]
        after = mesh_metrics(cnr(noisy, f, weights=weights), clean, f)["normal_deg"]
        evals.append((before, after))
    if evals:
        b, a = np.mean(evals, axis=0)
        meta["test_intra_check"] = {
            "meshes": len(evals),
            "noisy_normal_deg": round(float(b), 3),
            "cnr_normal_deg": round(float(a), 3),
        }
        print(f"test-intra check ({len(evals)} meshes): normal {b:.2f}° → {a:.2f}°")
    weights = weights._replace(meta=meta)
    out = save_cnr_weights(args.out, weights, overwrite=args.overwrite)
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB) in {wall:.0f} s")
    return out
