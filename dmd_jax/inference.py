"""`denoise`: a noisy mesh in any frame in, denoised vertices in the same frame out.

Weights travel as a `ModelBundle` (params + the config that built them + provenance),
stored as one msgpack file (`flax.serialization`, never pickle). The bundled `small`
model ships in `dmd_jax/weights/` and is read by `load_pretrained()`.
"""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.config import ExperimentConfig
from dmd_jax.graph import build_mesh_graph, pad_vertex_array, with_ell_layout
from dmd_jax.io import atomic_write
from dmd_jax.mesh import canonical_frame, validate_mesh
from dmd_jax.pipeline import collate

WEIGHTS_FORMAT = "dmd_jax-weights"
WEIGHTS_VERSION = 1
PRETRAINED_NAME = "dmd_small.msgpack"
AGGREGATIONS = ("auto", "ell", "segment_sum")
# `auto` keeps a graph's ELL table while it holds at most this many slots per distinct
# edge. The shared meshes, padded, need 1.8-2.9 (vertex graph) and 1.2-1.4 (face graph);
# truck.obj, with a vertex of valence 36, 6.6, where its table still beat the segment sum
# (benchmarks/README.md). A pole of valence 1000 would need hundreds.
AUTO_MAX_FILL = 8.0


class ModelBundle(NamedTuple):
    """Trained params with the config that built them and where they came from."""

    params: Any
    config: ExperimentConfig
    meta: dict


def write_weights_file(
    path, *, fmt: str, version: int, config: dict, meta: dict, params, overwrite: bool = False
) -> Path:
    """Writes one msgpack weights file (format tag, version, config, meta, params), atomically.

    The container of every weights file of this project (DMD-Net's and CNR's); `fmt`
    tells them apart and `read_weights_file` checks it.
    """
    from flax import serialization

    payload = {
        "format": fmt,
        "version": version,
        "config": json.dumps(config),
        "meta": json.dumps(meta),
        "params": serialization.to_state_dict(jax.device_get(params)),
    }
    data = serialization.msgpack_serialize(payload)

    def write(tmp):
        with open(tmp, "wb") as fh:
            fh.write(data)

    return atomic_write(path, write, overwrite=overwrite)


def read_weights_file(path, *, fmt: str, version: int, kind: str, parse_config):
    """Reads a file of `write_weights_file`: `(config, meta, params)`.

    Args:
      path: the file.
      fmt, version: the format tag and version it must carry.
      kind: names the format in errors ("not a {kind} weights file").
      parse_config: builds the config object from the stored dict.

    Raises:
      FileNotFoundError: no such file.
      ValueError: a truncated or corrupt file, another format or version, a missing
        field, or an unreadable config or meta.
    """
    from flax import serialization

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such weights file")
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except Exception as exc:  # msgpack raises several types on truncated data
        raise ValueError(
            f"{path}: not a readable weights file (truncated or corrupt: {exc})"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise ValueError(f"{path}: not a {kind} weights file")
    if payload.get("version") != version:
        raise ValueError(
            f"{path}: weights format version {payload.get('version')} is not supported "
            f"(this dmd_jax reads version {version})"
        )
    missing = [k for k in ("config", "meta", "params") if k not in payload]
    if missing:
        raise ValueError(f"{path}: incomplete weights file (no {', '.join(missing)})")
    try:
        config = parse_config(json.loads(payload["config"]))
        meta = json.loads(payload["meta"])
    except (TypeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: unreadable config or meta in the weights file ({exc})") from exc
    return config, meta, payload["params"]


def save_weights(
    path, params, config: ExperimentConfig, meta: dict | None = None, *, overwrite: bool = False
) -> Path:
    """Writes params + config + meta to one msgpack file, atomically."""
    return write_weights_file(
        path,
        fmt=WEIGHTS_FORMAT,
        version=WEIGHTS_VERSION,
        config=config.to_dict(),
        meta=meta or {},
        params=params,
        overwrite=overwrite,
    )


def load_weights(path) -> ModelBundle:
    """Reads a weights file written by `save_weights`, checking format, version and config.

    Raises:
      ValueError: not a dmd_jax weights file, another format version, a truncated file,
        or params whose structure or shapes do not match the stored config.
    """
    config, meta, params = read_weights_file(
        path,
        fmt=WEIGHTS_FORMAT,
        version=WEIGHTS_VERSION,
        kind="dmd_jax",
        parse_config=ExperimentConfig.from_dict,
    )
    if not isinstance(params, dict):
        raise ValueError(f"{path}: params must be a nested dict of arrays")
    _check_params(params, config, str(path))
    return ModelBundle(params=params, config=config, meta=meta)


def _abstract_params(config: ExperimentConfig):
    return _abstract_params_of(json.dumps(config.to_dict(), sort_keys=True))


@lru_cache(maxsize=8)
def _abstract_params_of(config_json: str):
    """Param shapes and dtypes of a config (traced once per config and process)."""
    from dmd_jax.graph import build_mesh_graph as _build
    from dmd_jax.model import DMDNet

    config = ExperimentConfig.from_dict(json.loads(config_json))
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], np.int32)
    batch = collate([v], [v], [_build(f, 4)])
    model = DMDNet(config.model)
    key = jax.random.PRNGKey(0)
    return jax.eval_shape(
        lambda: model.init(
            {"params": key, "dropout": key},
            jnp.asarray(batch.noisy),
            jax.tree.map(jnp.asarray, batch.graph),
            deterministic=True,
        )
    )["params"]


def _check_params(params, config: ExperimentConfig, name: str) -> None:
    expected = _abstract_params(config)
    exp_paths = {
        jax.tree_util.keystr(p): x.shape
        for p, x in jax.tree_util.tree_flatten_with_path(expected)[0]
    }
    got_paths = {
        jax.tree_util.keystr(p): np.shape(x)
        for p, x in jax.tree_util.tree_flatten_with_path(params)[0]
    }
    exp_dtypes = {
        jax.tree_util.keystr(p): np.dtype(x.dtype)
        for p, x in jax.tree_util.tree_flatten_with_path(expected)[0]
    }
    for p, x in jax.tree_util.tree_flatten_with_path(params)[0]:
        key = jax.tree_util.keystr(p)
        dtype = getattr(x, "dtype", None)
        if key in exp_dtypes and dtype != exp_dtypes[key]:
            raise ValueError(
                f"{name}: param {key} has dtype {dtype}, its config builds {exp_dtypes[key]}"
            )
        if key in exp_dtypes and not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: param {key} holds NaN or infinite values")
    if exp_paths != got_paths:
        missing = sorted(set(exp_paths) - set(got_paths))[:3]
        extra = sorted(set(got_paths) - set(exp_paths))[:3]
        wrong = [k for k in exp_paths if k in got_paths and exp_paths[k] != got_paths[k]][:3]
        raise ValueError(
            f"{name}: params do not match their config (missing {missing}, unexpected "
            f"{extra}, wrong shapes {wrong})"
        )


def pretrained_path() -> Path:
    return Path(str(resources.files("dmd_jax") / "weights" / PRETRAINED_NAME))


def load_pretrained() -> ModelBundle:
    """The bundled `small`-preset model (see README, "Bundled weights")."""
    path = pretrained_path()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the bundled weights are missing from this installation")
    return load_weights(path)


@lru_cache(maxsize=8)
def _predictor(config_json: str):
    from dmd_jax.model import DMDNet

    config = ExperimentConfig.from_dict(json.loads(config_json))
    model = DMDNet(config.model)

    @jax.jit
    def predict(params, noisy, graph):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True)
        return out

    return predict


def as_bundle(params, config: ExperimentConfig | None = None) -> ModelBundle:
    """Accepts a `ModelBundle`, a weights path, or raw params plus `config`."""
    if isinstance(params, ModelBundle):
        return params
    if isinstance(params, (str, Path)):
        return load_weights(params)
    if config is None:
        raise ValueError(
            "raw params need their config: pass config=..., or use load_pretrained() / "
            "load_weights() which carry it"
        )
    return ModelBundle(params=params, config=config, meta={})


def denoise(
    vertices,
    faces,
    params,
    *,
    config: ExperimentConfig | None = None,
    iterations: int = 1,
    aggregation: str = "auto",
) -> np.ndarray:
    """Denoises a triangle mesh with a trained DMD-Net.

    The mesh is mapped to its canonical frame (bounding box centred, longest side 1),
    denoised, and mapped back, so the result is translation- and scale-equivariant.

    Args:
      vertices: `[n_vertex, 3]` in any frame; float16/32/64 or integer.
      faces: `[n_face, 3]` integer indices.
      params: a `ModelBundle` (from `load_pretrained()`, `load_weights()` or a training
        checkpoint via `dmd_jax.train.load_params`), a weights path, or raw params with
        `config`.
      config: the experiment config, needed only with raw params.
      iterations: how many times to apply the network (each pass starts from the last).
      aggregation: how the GCN aggregations run (the same operator either way, equal up
        to float summation order): `"ell"` through padded neighbour tables
        (`mesh.with_ell_layout`; faster on CPU, no scatter), `"segment_sum"` over the
        edge lists, as in training, or `"auto"`: the tables of the vertex and face
        graphs, except a table padded to more than `AUTO_MAX_FILL` slots per edge (a
        vertex of very high valence), whose graph then uses its edge lists. Attention
        models use the edge lists regardless.

    Returns:
      `[n_vertex, 3]` denoised vertices in the input frame; float32 for float32 input,
      float64 otherwise.

    Raises:
      ValueError: bad mesh (see `dmd_jax.mesh.validate_mesh`), bad params, or an
        unknown `aggregation`.
    """
    if int(iterations) < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations}")
    if aggregation not in AGGREGATIONS:
        raise ValueError(
            f"unknown aggregation {aggregation!r}; choose one of {', '.join(AGGREGATIONS)}"
        )
    v, f = validate_mesh(vertices, faces)
    in_dtype = np.asarray(vertices).dtype
    bundle = as_bundle(params, config)
    frame = canonical_frame(v)
    x = frame.apply(v)
    # The padded graph does not change between passes: build it (edge lists, ELL
    # tables) and move it to the device once, not once per pass.
    graph = collate([x], [x], [build_mesh_graph(f, v.shape[0])]).graph
    if aggregation != "segment_sum":
        graph = with_ell_layout(graph, max_fill=AUTO_MAX_FILL if aggregation == "auto" else None)
    graph = jax.tree.map(jnp.asarray, graph)
    predict = _predictor(json.dumps(bundle.config.to_dict(), sort_keys=True))
    n, n_padded = v.shape[0], graph.n_vertex
    for _ in range(int(iterations)):
        # As `collate` pads the noisy positions: float32, zeros on padding rows.
        noisy = pad_vertex_array(x.astype(np.float32), n_padded)
        out = predict(bundle.params, jnp.asarray(noisy), graph)
        x = np.asarray(out[:n], np.float64)
        if not np.all(np.isfinite(x)):
            raise ValueError("the network produced non-finite vertices (broken weights?)")
    result = frame.invert(x)
    return result.astype(np.float32) if in_dtype == np.float32 else result
