"""CNR's model: the per-stage regressor, one cascade stage, the weights file and `cnr`.

Weights are one msgpack file (`dmd_jax.checkpoints.write_weights_file`, no pickle):
format `WEIGHTS_FORMAT` version `WEIGHTS_VERSION`, the `CNRConfig` as JSON, provenance,
and the float32 params of every stage under `"0"`, `"1"`, ...; the bundled
`cnr_small.msgpack` ships in `dmd_jax/weights/`.
"""

from __future__ import annotations

from functools import lru_cache, partial
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.baselines._common import (
    count_trace,
    fit_vertices_to_normals,
    float_dtype,
    run_in_canonical_frame,
)
from dmd_jax.baselines.cascaded_regression.config import CNRConfig
from dmd_jax.baselines.cascaded_regression.features import (
    MeshArrays,
    face_features,
    pad_rows,
    prepare_mesh,
    to_jax,
)
from dmd_jax.checkpoints import read_weights_file, write_weights_file
from dmd_jax.geometry import safe_normalize

WEIGHTS_FORMAT = "dmd_jax-cnr-weights"
WEIGHTS_VERSION = 1
BUNDLED_NAME = "cnr_small.msgpack"


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
    desc, base, frames = face_features(x, arr, cfg)
    y = CNRRegressor(cfg.hidden).apply({"params": params}, desc, base)
    normals = jnp.einsum("fji,fj->fi", frames, y)
    normals = jnp.where(arr.face_mask[:, None], normals, 0.0)
    free = jnp.ones(x.shape[0], x.dtype)
    moved = fit_vertices_to_normals(
        x, arr.faces, normals, arr.corner_v, arr.corner_f, free, cfg.vertex_iterations
    )
    return moved, normals


@partial(jax.jit, static_argnames=("cfg",))
def stage_jit(params, x, arr, cfg):
    """`_stage` compiled once per padded size and config (traces are counted)."""
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
    """The shapes and dtypes of one stage's params under `cfg`, without initialising."""
    d = jnp.zeros((1, cfg.descriptor_dim), jnp.float32)
    b = jnp.zeros((1, 3), jnp.float32)
    return jax.eval_shape(
        lambda: CNRRegressor(cfg.hidden).init(jax.random.PRNGKey(0), d, b)["params"]
    )


def check_stage_params(params, cfg: CNRConfig, name: str) -> None:
    """Raises `ValueError` (naming `name`) unless `params` has the tree and shapes of one
    stage's regressor under `cfg`."""
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
        check_stage_params(p, cfg, f"{path} stage {i}")
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
        arr = to_jax(arr, dt)
        x = jnp.asarray(pad_rows(v, vp), dt)
        for p in w.params[: int(n_stages)]:
            x, _ = stage_jit(jax.tree.map(lambda a: jnp.asarray(a, dt), p), x, arr, w.config)
        return np.asarray(x[: v.shape[0]])

    return run_in_canonical_frame(vertices, faces, core, name="cnr")
