"""Synthetic vertex noise with explicit PRNG keys: Gaussian, uniform, gamma, impulse, scanner.

For the paper's four kinds (`PAPER_NOISE_KINDS`),
`add_noise_jax(key, vertices, faces, kind, level)` adds `level · X` to every coordinate,
with `level` measured in one of two units (`dmd_jax.add_noise(seed, ...)` is the NumPy
version, with an integer seed):

* `units="canonical"` (the paper's convention): `level` is a length in the canonical
  frame of the mesh (bounding box longest side 1), so the noise added to world
  coordinates is `level · scale · X`, `scale` the longest bounding-box side;
* `units="edge"` (the CNR / GCN-Denoiser benchmark convention): `level` is a multiple
  of the mesh's mean edge length.

The unit-level distributions `X`, drawn independently per coordinate:

* `gaussian`  `N(0, 1)`: `N(0, σ)` with `σ = level`;
* `uniform`   `U(−1, 1)`;
* `gamma`     `s · G` with `G ~ Γ(shape 2, rate 2)` (mean 1, `E[G²] = 1.5`) and a random
  sign `s = ±1` per coordinate;
* `impulse`   `δ(p, q)`: `+1` with probability `p`, `−1` with probability `q`, else `0`
  (salt-and-pepper noise, per coordinate).

The paper's noise table fixes the two parametrisations it leaves open. Its "reference"
vertex errors (noisy vs clean, ×10⁻⁴) are `level² · E[X²]` in the per-coordinate mean
squared error: Gaussian 0.025/0.05/0.1 → 6.18/24.7/98.8 (predicted 6.25/25/100);
uniform 0.05/0.1/0.2 → 8.23/32.9/132 (`E[X²] = 1/3`: 8.33/33.3/133); gamma
0.03/0.04/0.05 → 13.3/23.7/37.1, which is `E[X²] = 1.5`, i.e. rate 2 (13.5/24/37.5; a
scale-2 gamma, `E[X²] = 24`, would give 216/384/600); impulse δ(0.15, 0.15) at
0.05/0.1/0.2 → 7.41/29.6/119, which is `E[X²] = p + q = 0.3` (7.5/30/120). A
per-vertex reading of δ (a random unit direction with probability p) would give
`p·(1 + q²)/3 ≈ 0.051`, six times too small; it is kept as `impulse_mode="vertex"`
(the vertex moves by `level · |1 + q z|`, `z ~ N(0, 1)`, in a uniform random direction).
`level · Γ(2, scale 2)` in the other common parametrisation is `4 · level` here.

Determinism: every draw comes from `jax.random` with the given key, so the same key,
mesh, kind and level give bit-identical noise on the same backend.

Compilation: outside `jit`, each new array shape compiles a new program, and sampling
programs take about a second to compile. So the unit noise of a concrete shape is drawn
for a row count rounded up to a power of two of at least 4,096 (`_noise_rows`) and
sliced on the host, and `add_noise_jax` combines on the host: a training epoch over meshes
of hundreds of sizes up to 4,096 vertices compiles one program per noise kind and
direction instead of one per mesh. The rounding changes no value: with JAX's
partitionable threefry (the default) the draws of the first rows do not depend on how
many rows are drawn (`tests/test_noise.py`).

The `scanner` kind (`scanner_displacement`, parameters in `ScannerModel`, both in
`dmd_jax.scanner_model`) is not a
per-coordinate law: it models a depth sensor, as measured on public depth-camera scans
with ground truth (see `docs/noise-models.md`). Every vertex moves along one view
direction `d` (drawn from the key, or given) by `level · unit · s`, where `s` is

* a smooth random field over the surface (random Fourier features of a Gaussian kernel
  in 3D, correlation length `correlation_length` mean edges: neighbours alike over 4-8
  rings, faded by ~16, as measured), plus a small white part (`white_share` of the
  variance), scaled to unit rms on the mesh;
* multiplied by the grazing-angle gain `1 / max(|n · d|, 1 / grazing_max_gain)` (`n` the
  vertex normal), normalised to unit rms, so the rms stays `level` mean edges
  (measured: 0.4-0.9 on depth-camera scans, ~0.15 on careful reconstructions);
* with a few spikes (`spike_share` of the vertices moved by `± spike_gain · level`);
* and the noisy depth rounded to steps of `quant_step · level` that grow by
  `quant_growth` over the depth range (depth cameras quantise depth, coarser far away).

It is drawn on the host in NumPy from a generator seeded by the key's bits (no program
compiles), so the same key, mesh, level and view give the same noise; it needs the faces
(normals, edge lengths) and is not traceable under `jit`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.constants import NOISE_KINDS, PAPER_NOISE_KINDS, SCANNER_KIND
from dmd_jax.mesh import mean_edge_length

# Re-exported: the scanner kind's names have always been read from `dmd_jax.noise`.
from dmd_jax.scanner_model import (
    SCANNER_MODEL,
    ScannerModel,
    _unit_rms,  # noqa: F401 (re-exported)
    check_scanner_model,  # noqa: F401 (re-exported)
    check_view,  # noqa: F401 (re-exported)
    host_rng,
    random_view,  # noqa: F401 (re-exported)
    scanner_displacement,
    smooth_field,  # noqa: F401 (re-exported)
    vertex_normals_np,
)
from dmd_jax.topology import vertex_edges

NOISE_UNITS = ("canonical", "edge")
IMPULSE_MODES = ("coordinate", "vertex")
# "isotropic": every coordinate gets its own draw; "normal": one draw per vertex, along
# the (area-weighted) vertex normal of the input mesh, the protocol of the mesh-denoising
# benchmarks (CNR, GCN-Denoiser: Gaussian noise along normals, 0.1-0.3 × mean edge).
NOISE_DIRECTIONS = ("isotropic", "normal")

GAMMA_SHAPE = 2.0
GAMMA_RATE = 2.0

# Training levels in the canonical frame, five per kind (the paper trains on "four
# noise types each with five noise levels" but does not list them). Chosen to span
# the levels the paper shows: Gaussian σ 0.005-0.05 (SOTA table, bust figure),
# uniform 0.035 (Fertility) to 0.1, gamma 0.015 (Bunny) to 0.04, impulse 0.05-0.2
# (noise table). Per-coordinate RMS ranges: Gaussian 0.005-0.05, uniform
# 0.006-0.058, gamma 0.006-0.049, impulse 0.005-0.11.
PAPER_LEVELS = MappingProxyType(
    {
        "gaussian": (0.005, 0.01, 0.02, 0.03, 0.05),
        "uniform": (0.01, 0.02, 0.035, 0.05, 0.1),
        "gamma": (0.005, 0.01, 0.015, 0.03, 0.04),
        "impulse": (0.01, 0.02, 0.05, 0.1, 0.2),
    }
)

# Levels in units of the mean edge length (the CNR benchmark's Gaussian levels).
EDGE_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5)

# Training levels of the scanner kind, in mean edge lengths (always edge units): from a
# careful reconstruction (~0.15 measured) to the depth-camera range (0.4-0.9 measured).
SCANNER_LEVELS = (0.15, 0.3, 0.5, 0.8)


class NoiseSpec(NamedTuple):
    """One noise setting: `kind` in `NOISE_KINDS`, `level`, `units` in `NOISE_UNITS`,
    `direction` in `NOISE_DIRECTIONS`."""

    kind: str
    level: float
    units: str
    direction: str = "isotropic"


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def check_kind(kind):
    if kind not in NOISE_KINDS:
        raise ValueError(f"unknown noise kind {kind!r}; expected one of {NOISE_KINDS}")


def check_units(units):
    if units not in NOISE_UNITS:
        raise ValueError(f"unknown noise units {units!r}; expected one of {NOISE_UNITS}")


def check_direction(direction):
    if direction not in NOISE_DIRECTIONS:
        raise ValueError(
            f"unknown noise direction {direction!r}; expected one of {NOISE_DIRECTIONS}"
        )


def check_level(level) -> float:
    """`level` as a float; `ValueError` unless it is a finite number >= 0 (a string or
    a bool is not a number here, though `float()` takes them)."""
    if isinstance(level, bool | np.bool_ | str | bytes):
        raise ValueError(f"noise level must be a number, got {level!r}")
    try:
        value = float(level)
    except (TypeError, ValueError) as err:
        raise ValueError(f"noise level must be a number, got {level!r}") from err
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"noise level must be finite and >= 0, got {level!r}")
    return value


def _check_probability(name, p) -> float:
    if isinstance(p, bool | np.bool_) or not isinstance(p, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a number in [0, 1], got {p!r}")
    value = float(p)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {p!r}")
    return value


def check_impulse(impulse_p, impulse_q, impulse_mode) -> tuple[float, float]:
    """The impulse kind's `(p, q)` as floats, checked with its mode (`unit_noise`)."""
    p = _check_probability("impulse_p", impulse_p)
    q = _check_probability("impulse_q", impulse_q)
    if impulse_mode not in IMPULSE_MODES:
        raise ValueError(f"unknown impulse_mode {impulse_mode!r}; expected one of {IMPULSE_MODES}")
    if impulse_mode == "coordinate" and p + q > 1.0:
        raise ValueError(f"impulse_p + impulse_q must be <= 1, got {p} + {q}")
    return p, q


def seed_key(seed):
    """The `jax.random` key of a public function's `seed`: an integer in [-2**63, 2**63)
    (as `dmd-jax add-noise --seed`), or a `jax.random` key (typed, or raw uint32 `[2]`).

    Raises:
      TypeError: a seed of another type (a float, a string, None).
      ValueError: a bool, an integer beyond 64 bits, or an array that is not a key.
    """
    if isinstance(seed, bool | np.bool_):  # an int to Python, never meant as a seed
        raise ValueError(f"seed must be an integer or a jax.random key, got {seed!r}")
    if isinstance(seed, int | np.integer):
        if not -(2**63) <= int(seed) < 2**63:
            # jax.random.PRNGKey takes a 64-bit signed integer and overflows past it.
            raise ValueError(f"seed must lie in [-2**63, 2**63), got {seed}")
        return jax.random.PRNGKey(int(seed))
    if isinstance(seed, jax.Array | np.ndarray) and not isinstance(seed, jax.core.Tracer):
        if jax.dtypes.issubdtype(seed.dtype, jax.dtypes.prng_key):
            if seed.shape == ():
                return seed
        elif seed.shape == (2,) and seed.dtype == np.uint32:
            return jnp.asarray(seed)
        raise ValueError(
            "seed must be an integer or one jax.random key (jax.random.key(n), or "
            f"PRNGKey(n): uint32 [2]), got an array of shape {seed.shape}, dtype {seed.dtype}"
        )
    raise TypeError(f"seed must be an integer or a jax.random key, got {seed!r}")


# --------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------


def unit_noise(
    key,
    shape,
    kind,
    *,
    dtype=jnp.float32,
    impulse_p=0.15,
    impulse_q=0.15,
    impulse_mode="coordinate",
):
    """Samples the unit-level noise `X` of `kind` (see the module docstring).

    Args:
      key: a `jax.random` key.
      shape: output shape; the last axis is the coordinate axis (3) for
        `impulse_mode="vertex"`.
      kind: one of `NOISE_KINDS`.
      dtype: float dtype of the result.
      impulse_p, impulse_q: the probabilities of `δ(p, q)`.
      impulse_mode: `"coordinate"` (salt-and-pepper) or `"vertex"`.

    Returns:
      Array of `shape`.
    """
    check_kind(kind)
    if kind == SCANNER_KIND:
        raise ValueError(
            "the scanner kind is not drawn per coordinate: use scanner_displacement "
            "(or add_noise_jax / dmd_jax.add_noise with kind='scanner')"
        )
    if kind == "impulse":
        impulse_p, impulse_q = check_impulse(impulse_p, impulse_q, impulse_mode)
    shape = tuple(shape)
    if shape and isinstance(shape[0], int | np.integer):
        # Eager call: sample a bucketed row count (one compile per bucket), slice on host.
        rows = int(shape[0])
        padded = _unit_noise_jit(
            key,
            (_noise_rows(rows),) + shape[1:],
            kind,
            jnp.dtype(dtype),
            float(impulse_p),
            float(impulse_q),
            impulse_mode,
        )
        return jnp.asarray(np.asarray(padded)[:rows])
    return _unit_noise(key, shape, kind, dtype, impulse_p, impulse_q, impulse_mode)


def _unit_noise(key, shape, kind, dtype, impulse_p, impulse_q, impulse_mode):
    if kind == "gaussian":
        return jax.random.normal(key, shape, dtype)
    if kind == "uniform":
        return jax.random.uniform(key, shape, dtype, minval=-1.0, maxval=1.0)
    if kind == "gamma":
        k_gamma, k_sign = jax.random.split(key)
        magnitude = jax.random.gamma(k_gamma, GAMMA_SHAPE, shape, dtype) / GAMMA_RATE
        return jax.random.rademacher(k_sign, shape, dtype) * magnitude
    p = _check_probability("impulse_p", impulse_p)
    q = _check_probability("impulse_q", impulse_q)
    if impulse_mode == "coordinate":
        if p + q > 1.0:
            raise ValueError(f"impulse_p + impulse_q must be <= 1, got {p} + {q}")
        u = jax.random.uniform(key, shape, dtype)
        return jnp.where(u < p, 1.0, jnp.where(u < p + q, -1.0, 0.0)).astype(dtype)
    if impulse_mode == "vertex":
        if not shape or shape[-1] != 3:
            raise ValueError(f"impulse_mode='vertex' needs shape [..., 3], got {shape}")
        k_hit, k_dir, k_mag = jax.random.split(key, 3)
        hit = jax.random.bernoulli(k_hit, p, shape[:-1])
        direction = jax.random.normal(k_dir, shape, dtype)
        direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
        magnitude = jnp.abs(1.0 + q * jax.random.normal(k_mag, shape[:-1], dtype))
        return jnp.where(hit, magnitude, 0.0)[..., None] * direction
    raise ValueError(f"unknown impulse_mode {impulse_mode!r}; expected one of {IMPULSE_MODES}")


_unit_noise_jit = jax.jit(_unit_noise, static_argnums=(1, 2, 3, 4, 5, 6))


def _noise_rows(rows: int) -> int:
    """Rows drawn for `rows` noise rows. Few programs: `graph.bucket_size`'s finer steps
    gave one per kind, direction and bucket, up to 4 x 2 x 7 = 56 on meshes of 1k-4k
    vertices; drawing up to twice the rows costs far less than a ~0.3 s compile."""
    return max(4096, 1 << (max(int(rows), 1) - 1).bit_length())


def noise_unit_length(vertices, faces, units):
    """The length one noise level unit stands for, in the coordinates of `vertices`.

    `"canonical"`: the longest side of the bounding box; `"edge"`: the mean length of
    the unique undirected edges (as `dmd_jax.mesh.mean_edge_length`). `faces` must be a
    concrete array for `"edge"` (the edge list is built on the host).
    """
    check_units(units)
    v = jnp.asarray(vertices)
    if units == "canonical":
        return jnp.max(jnp.max(v, axis=0) - jnp.min(v, axis=0))
    if faces is None:
        raise ValueError("units='edge' needs the faces of the mesh")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape [n_face, 3], got {f.shape}")
    if not isinstance(v, jax.core.Tracer):
        return jnp.asarray(mean_edge_length(np.asarray(v), f), v.dtype)
    a, b = vertex_edges(f, v.shape[0])
    return jnp.mean(jnp.linalg.norm(v[a] - v[b], axis=-1))


# --------------------------------------------------------------------------------------
# Scanner noise
# --------------------------------------------------------------------------------------


def scanner_noise(
    key, vertices, faces, level, *, units="edge", view=None, model: ScannerModel = SCANNER_MODEL
) -> np.ndarray:
    """`vertices` with the scanner kind's noise, in float64 NumPy (any JAX x64 mode).

    Args:
      key: a `jax.random` key (`host_rng` seeds the draws with its bits).
      vertices: `[n_vertex, 3]` finite positions.
      faces: `[n_face, 3]` vertex indices.
      level: the rms displacement in `units`.
      units: `"canonical"` or `"edge"` (the measurements are in edges).
      view: the direction the sensor looks along, `[3]`; None draws it from `key`.
      model: the `ScannerModel`.

    Returns:
      `[n_vertex, 3]` float64 noisy positions.
    """
    check_units(units)
    level = check_level(level)
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[-1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape [n_vertex, 3], got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite (NaN or inf found)")
    if faces is None:
        raise ValueError("kind='scanner' needs the faces of the mesh")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape [n_face, 3], got {f.shape}")
    # noise_unit_length in float64 NumPy, so JAX's x64 mode changes no bit.
    unit = mean_edge_length(v, f) if units == "edge" else float(np.max(np.ptp(v, axis=0)))
    moved, _ = scanner_displacement(host_rng(key), v, faces, level, unit, view=view, model=model)
    return v + moved


def add_noise_jax(
    key,
    vertices,
    faces,
    kind,
    level,
    *,
    units="canonical",
    impulse_p=0.15,
    impulse_q=0.15,
    impulse_mode="coordinate",
    direction="isotropic",
    view=None,
    scanner: ScannerModel = SCANNER_MODEL,
):
    """Adds noise of one kind and level to the vertices of a mesh, from a `jax.random` key.

    JAX arrays in and out, traceable under `jit` except with `direction="normal"` or
    `kind="scanner"`; `dmd_jax.add_noise(seed, ...)` is the same noise for NumPy users.

    Args:
      key: a `jax.random` key; the same key gives the same noise.
      vertices: `[n_vertex, 3]` positions, in any frame.
      faces: `[n_face, 3]` int vertex indices (needed for `units="edge"` only; may be
        `None` otherwise).
      kind: one of `NOISE_KINDS`.
      level: non-negative noise level (σ for Gaussian, amplitude for the others).
      units: `"canonical"` (level in the canonical frame) or `"edge"` (level × mean
        edge length).
      impulse_p, impulse_q: the probabilities of `δ(p, q)` (paper: 0.15, 0.15).
      impulse_mode: `"coordinate"` (default, matches the paper's table) or `"vertex"`.
      direction: `"isotropic"` (default: per coordinate) or `"normal"`: one scalar draw
        per vertex along its vertex normal (the benchmark protocol; needs `faces` and
        concrete arrays). The scanner kind moves along its view and takes the default.
      view: `kind="scanner"` only: the direction the sensor looks along, `[3]`; None
        draws it from `key`.
      scanner: `kind="scanner"` only: its `ScannerModel`.

    Returns:
      `[n_vertex, 3]` noisy positions, in the frame of `vertices`.

    Raises:
      ValueError: on an unknown kind, units or impulse mode, a negative level, vertices
        that are not `[n, 3]`, or a bad `view` (zero, not finite, not a 3-vector).
    """
    check_kind(kind)
    check_units(units)
    level = check_level(level)
    v = jnp.asarray(vertices)
    if v.ndim != 2 or v.shape[-1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape [n_vertex, 3], got {tuple(v.shape)}")
    if not jnp.issubdtype(v.dtype, jnp.floating):
        v = v.astype(jnp.result_type(float))
    check_direction(direction)
    if kind == SCANNER_KIND:
        if faces is None or isinstance(v, jax.core.Tracer):
            raise ValueError("kind='scanner' needs concrete vertices and the faces")
        if direction != "isotropic":
            raise ValueError("kind='scanner' moves vertices along its view: leave direction")
        noisy = scanner_noise(key, vertices, faces, level, units=units, view=view, model=scanner)
        return jnp.asarray(noisy.astype(v.dtype))
    if view is not None:
        raise ValueError(f"view is the scanner kind's; kind {kind!r} takes none")
    if direction == "normal":
        if faces is None or isinstance(v, jax.core.Tracer):
            raise ValueError("direction='normal' needs concrete vertices and the faces")
        v_np = np.asarray(v)
        x = unit_noise(
            key,
            (v.shape[0], 1),
            kind,
            dtype=v.dtype,
            impulse_p=impulse_p,
            impulse_q=impulse_q,
            impulse_mode="coordinate",
        )
        normals = vertex_normals_np(v_np, faces).astype(v_np.dtype)
        unit = np.asarray(noise_unit_length(v_np, faces, units), v_np.dtype)
        return jnp.asarray(v_np + (level * unit).astype(v_np.dtype) * np.asarray(x) * normals)
    x = unit_noise(
        key,
        v.shape,
        kind,
        dtype=v.dtype,
        impulse_p=impulse_p,
        impulse_q=impulse_q,
        impulse_mode=impulse_mode,
    )
    if isinstance(v, jax.core.Tracer) or isinstance(x, jax.core.Tracer):
        return v + (level * noise_unit_length(v, faces, units)).astype(v.dtype) * x
    # Eager: combine on the host so no per-shape elementwise program is compiled.
    v_np = np.asarray(v)
    unit = np.asarray(noise_unit_length(v_np, faces, units), v_np.dtype)
    return jnp.asarray(v_np + (level * unit).astype(v_np.dtype) * np.asarray(x))


# --------------------------------------------------------------------------------------
# Mixed noise for training
# --------------------------------------------------------------------------------------


def _levels_for(levels, kind, name):
    chosen = levels[kind] if isinstance(levels, Mapping) else levels
    chosen = tuple(chosen)
    if not chosen:
        raise ValueError(f"{name} for {kind!r} is empty")
    for level in chosen:
        check_level(level)
    return chosen


def sample_noise_spec(
    key,
    *,
    kinds: Sequence[str] = PAPER_NOISE_KINDS,
    canonical_levels: Mapping[str, Sequence[float]] | Sequence[float] | None = PAPER_LEVELS,
    edge_levels: Mapping[str, Sequence[float]] | Sequence[float] | None = EDGE_LEVELS,
    p_edge: float = 0.5,
    p_normal: float = 0.0,
    p_clean: float = 0.0,
    p_scanner: float = 0.0,
    scanner_levels: Sequence[float] = SCANNER_LEVELS,
) -> NoiseSpec:
    """Draws a noise kind, units and level uniformly at random (on the host) from `key`.

    Args:
      key: a `jax.random` key.
      kinds: kinds to choose from.
      canonical_levels: levels per kind (a mapping) or for all kinds (a sequence), used
        with `units="canonical"`; `None` means `PAPER_LEVELS`.
      edge_levels: the same for `units="edge"`; `None` means `EDGE_LEVELS`.
      p_edge: probability of `units="edge"`.
      p_normal: probability that an edge-unit draw is along the vertex normals.
      p_clean: probability of level 0 (a clean input: the model must learn to leave a
        clean mesh alone).
      p_scanner: probability that the draw is the scanner kind whatever `kinds` says (a
        share of scanner samples in a mix of the paper's kinds).
      scanner_levels: the scanner kind's levels, always in edge units (it is drawn so
        whether it comes from `kinds` or from `p_scanner`).

    Returns:
      A `NoiseSpec` of Python values.
    """
    kinds = tuple(kinds)
    if not kinds:
        raise ValueError("kinds is empty")
    for kind in kinds:
        check_kind(kind)
    p_edge = _check_probability("p_edge", p_edge)
    p_normal = _check_probability("p_normal", p_normal)
    p_clean = _check_probability("p_clean", p_clean)
    p_scanner = _check_probability("p_scanner", p_scanner)
    canonical_levels = PAPER_LEVELS if canonical_levels is None else canonical_levels
    edge_levels = EDGE_LEVELS if edge_levels is None else edge_levels
    k_kind, k_units, k_level = jax.random.split(key, 3)
    kind = kinds[int(jax.random.randint(k_kind, (), 0, len(kinds)))]
    # Scanner draws use keys of their own: with p_scanner 0 and no "scanner" in kinds,
    # every other spec stays bit-identical to older configs.
    if kind == SCANNER_KIND or (
        p_scanner > 0.0 and bool(jax.random.uniform(jax.random.fold_in(key, 11)) < p_scanner)
    ):
        return _scanner_spec(key, scanner_levels, p_clean)
    use_edge = bool(jax.random.uniform(k_units) < p_edge)
    units = "edge" if use_edge else "canonical"
    levels = _levels_for(
        edge_levels if use_edge else canonical_levels,
        kind,
        "edge_levels" if use_edge else "canonical_levels",
    )
    level = levels[int(jax.random.randint(k_level, (), 0, len(levels)))]
    if p_normal == 0.0 and p_clean == 0.0:
        # Draw nothing more: keeps the specs of older configs bit-identical.
        return NoiseSpec(kind=kind, level=float(level), units=units)
    k_dir, k_clean = jax.random.split(jax.random.fold_in(key, 7))
    normal = use_edge and bool(jax.random.uniform(k_dir) < p_normal)
    if bool(jax.random.uniform(k_clean) < p_clean):
        level = 0.0
    return NoiseSpec(
        kind=kind,
        level=float(level),
        units=units,
        direction="normal" if normal else "isotropic",
    )


def _scanner_spec(key, scanner_levels, p_clean) -> NoiseSpec:
    levels = tuple(scanner_levels)
    if not levels:
        raise ValueError("scanner_levels is empty")
    for level in levels:
        check_level(level)
    k_level, k_clean = jax.random.split(jax.random.fold_in(key, 12))
    level = levels[int(jax.random.randint(k_level, (), 0, len(levels)))]
    if p_clean > 0.0 and bool(jax.random.uniform(k_clean) < p_clean):
        level = 0.0
    return NoiseSpec(kind=SCANNER_KIND, level=float(level), units="edge")


def add_mixed_noise(
    key,
    vertices,
    faces,
    *,
    kinds: Sequence[str] = PAPER_NOISE_KINDS,
    canonical_levels: Mapping[str, Sequence[float]] | Sequence[float] | None = PAPER_LEVELS,
    edge_levels: Mapping[str, Sequence[float]] | Sequence[float] | None = EDGE_LEVELS,
    p_edge: float = 0.5,
    p_normal: float = 0.0,
    p_clean: float = 0.0,
    p_scanner: float = 0.0,
    scanner_levels: Sequence[float] = SCANNER_LEVELS,
    impulse_p=0.15,
    impulse_q=0.15,
    impulse_mode="coordinate",
    view=None,
):
    """Adds noise of a randomly drawn kind, units and level (`sample_noise_spec`).

    `view`: the scanner kind's view direction when it is drawn (None: drawn from the
    key); the other kinds ignore it.

    Returns:
      `(noisy [n_vertex, 3], spec)`.
    """
    k_spec, k_noise = jax.random.split(key)
    spec = sample_noise_spec(
        k_spec,
        kinds=kinds,
        canonical_levels=canonical_levels,
        edge_levels=edge_levels,
        p_edge=p_edge,
        p_normal=p_normal,
        p_clean=p_clean,
        p_scanner=p_scanner,
        scanner_levels=scanner_levels,
    )
    noisy = add_noise_jax(
        k_noise,
        vertices,
        faces,
        spec.kind,
        spec.level,
        units=spec.units,
        impulse_p=impulse_p,
        impulse_q=impulse_q,
        impulse_mode=impulse_mode,
        direction=spec.direction,
        view=view if spec.kind == SCANNER_KIND else None,
    )
    return noisy, spec


def __getattr__(name: str):
    # `noise.add_noise` was this module's name for `add_noise_jax` until it clashed with
    # the root `dmd_jax.add_noise(seed, ...)`; old code keeps working, with a warning.
    if name == "add_noise":
        import warnings

        warnings.warn(
            "dmd_jax.noise.add_noise is deprecated: use dmd_jax.noise.add_noise_jax (a "
            "jax.random key) or dmd_jax.add_noise (an integer seed)",
            DeprecationWarning,
            stacklevel=2,
        )
        return add_noise_jax
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
