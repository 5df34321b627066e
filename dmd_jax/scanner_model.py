"""The `scanner` noise kind's model: its parameters and the displacement it draws.

`ScannerModel` names the parameters and `scanner_displacement` draws the displacement
of every vertex along one view direction, in NumPy from a generator seeded by a
`jax.random` key's bits (`host_rng`); the law is described in `dmd_jax.noise`'s
docstring and measured in `docs/noise-models.md`. `noise.scanner_noise` and
`noise.add_noise_jax(kind="scanner")` check the level and units and call it;
`dmd_jax.noise` re-exports every name defined here.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.mesh import mean_edge_length


def vertex_normals_np(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals `[n_vertex, 3]` on the host (0 where undefined).

    NumPy, so drawing noise for meshes of many sizes compiles nothing.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], cross)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.where(norm > 0, acc / np.where(norm > 0, norm, 1.0), 0.0)


class ScannerModel(NamedTuple):
    """The parameters of the `scanner` noise kind (module docstring), each a named choice.

    Attributes:
      correlation_length: length of the Gaussian correlation kernel of the smooth field, in
        mean edge lengths: the correlation of two points `r` apart is `exp(−r² / 2ℓ²)`;
        6 gives 0.80 at 4 rings, 0.41 at 8 and 0.03 at 16 (measured on real scans: alike
        over 4-8 rings, faded by ~16).
      white_share: share of the variance that is white (independent per vertex); real
        scans have "a small white part".
      grazing_max_gain: the noise along the ray grows as `1 / |cos θ|` (θ between the
        vertex normal and the view) up to this factor, reached at `acos(1 / gain)` (60°
        for 2); the gain is normalised to unit rms over the mesh.
      spike_share: share of vertices moved by a spike (range images have "a few").
      spike_gain: a spike's displacement along the view, in units of `level`, either sign.
      quant_step: the depth step at the nearest depth, in units of `level` (rounding adds
        an rms of `quant_step / √12` levels: 0.14 for 0.5).
      quant_growth: the step grows linearly with depth by this fraction of itself over
        the mesh's depth range (depth cameras quantise disparity: coarser far away).
      n_features: random Fourier features of the smooth field (its marginal is close to
        Gaussian for tens of features).
    """

    correlation_length: float = 6.0
    white_share: float = 0.15
    grazing_max_gain: float = 2.0
    spike_share: float = 0.001
    spike_gain: float = 5.0
    quant_step: float = 0.5
    quant_growth: float = 1.0
    n_features: int = 128


SCANNER_MODEL = ScannerModel()


def check_scanner_model(model: ScannerModel) -> ScannerModel:
    """`model` if every field is in range, else `ValueError` naming the field."""
    if not isinstance(model, ScannerModel):
        raise ValueError(f"scanner model must be a ScannerModel, got {type(model).__name__}")
    for name, low, high in (
        ("correlation_length", 0.0, math.inf),
        ("white_share", 0.0, 1.0),
        ("grazing_max_gain", 1.0, math.inf),
        ("spike_share", 0.0, 1.0),
        ("spike_gain", 0.0, math.inf),
        ("quant_step", 0.0, math.inf),
        ("quant_growth", 0.0, math.inf),
    ):
        value = getattr(model, name)
        ok = isinstance(value, int | float) and math.isfinite(value) and low <= value <= high
        if not ok or (name == "correlation_length" and value <= 0):
            raise ValueError(f"scanner model {name} out of range: {value!r}")
    if not isinstance(model.n_features, int) or model.n_features < 1:
        raise ValueError(
            f"scanner model n_features must be a positive int, got {model.n_features!r}"
        )
    return model


def host_rng(key) -> np.random.Generator:
    """A NumPy generator seeded by the bits of a `jax.random` key (raw or typed)."""
    if jax.dtypes.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    bits = np.asarray(key).astype(np.uint32).ravel()
    return np.random.default_rng([int(b) for b in bits])


def check_view(view) -> np.ndarray:
    """`view` as a unit `[3]` float64 vector; `ValueError` naming `view` otherwise."""
    try:
        d = np.asarray(view, np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"view must be a 3-vector, got {view!r}") from err
    if d.shape != (3,):
        raise ValueError(f"view must be a 3-vector, got shape {d.shape}")
    if not np.all(np.isfinite(d)) or not np.any(d):
        raise ValueError(f"view must be a finite non-zero 3-vector, got {d.tolist()}")
    # Divided by its largest entry first: the norm of [1e200, 1e200, 0] overflows (the
    # direction would be zero) and that of [1e-200, 0, 0] underflows.
    d = d / np.abs(d).max()
    return d / float(np.linalg.norm(d))


def random_view(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed unit view direction `[3]`."""
    while True:
        d = rng.standard_normal(3)
        norm = float(np.linalg.norm(d))
        if norm > 1e-6:
            return d / norm


def smooth_field(rng: np.random.Generator, points, length: float, n_features: int) -> np.ndarray:
    """A zero-mean random field `[n]` with correlation `exp(−r² / 2 length²)` and variance 1.

    Random Fourier features (Rahimi & Recht): `√(2/M) Σ cos(ω_m · x + φ_m)`, `ω_m ~
    N(0, I / length²)`, `φ_m ~ U(0, 2π)`: `O(n M)` work, no loop over points.

    Args:
      rng: the generator.
      points: `[n, 3]` positions.
      length: the correlation length, in the units of `points`.
      n_features: `M`.
    """
    x = np.asarray(points, np.float64)
    omega = rng.standard_normal((x.shape[1], n_features)) / length
    phase = rng.uniform(0.0, 2.0 * np.pi, n_features)
    centred = x - x.mean(axis=0)  # keeps the phases well conditioned far from the origin
    return np.sqrt(2.0 / n_features) * np.cos(centred @ omega + phase).sum(axis=1)


def _unit_rms(x: np.ndarray) -> np.ndarray:
    rms = float(np.sqrt(np.mean(x * x))) if x.size else 0.0
    return x / rms if rms > 0 else x


def scanner_displacement(
    rng: np.random.Generator,
    vertices,
    faces,
    level: float,
    unit: float,
    *,
    view=None,
    model: ScannerModel = SCANNER_MODEL,
) -> tuple[np.ndarray, np.ndarray]:
    """The scanner kind's displacement of every vertex (module docstring).

    Args:
      rng: the generator every draw comes from (`host_rng(key)`).
      vertices: `[n_vertex, 3]` positions.
      faces: `[n_face, 3]` vertex indices (normals, mean edge length).
      level: the rms of the displacement, in `unit`s.
      unit: the length of one level unit (`noise_unit_length`).
      view: the direction the sensor looks along, `[3]` (any length); None: drawn from
        `rng` (uniform on the sphere).
      model: the `ScannerModel`.

    Returns:
      `(displacement [n_vertex, 3] float64, view [3] unit)`: every row is a multiple of
      `view`.
    """
    check_scanner_model(model)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    # The view is drawn first, so a given view and a drawn one leave the rest alike.
    d = random_view(rng) if view is None else check_view(view)
    n = v.shape[0]
    if level == 0.0 or n == 0:
        return np.zeros_like(v), d
    edge = mean_edge_length(v, f)
    length = model.correlation_length * (edge if edge > 0 else 1.0)
    field = _unit_rms(smooth_field(rng, v, length, model.n_features))
    white = _unit_rms(rng.standard_normal(n))
    s = _unit_rms(np.sqrt(1.0 - model.white_share) * field + np.sqrt(model.white_share) * white)
    cos = np.abs(vertex_normals_np(v, f) @ d)
    gain = 1.0 / np.maximum(cos, 1.0 / model.grazing_max_gain)
    s = s * gain / float(np.sqrt(np.mean(gain * gain)))
    spikes = rng.random(n) < model.spike_share
    signs = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    s = np.where(spikes, model.spike_gain * signs, s)
    amount = level * unit * s
    step0 = model.quant_step * level * unit
    if step0 > 0:
        depth = v @ d
        span = float(depth.max() - depth.min())
        rel = (depth - depth.min()) / span if span > 0 else np.zeros(n)
        step = step0 * (1.0 + model.quant_growth * rel)
        amount = np.round((depth + amount) / step) * step - depth
    return amount[:, None] * d[None, :], d
