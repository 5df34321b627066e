"""Where weights live: the weights-file format, Orbax training checkpoints, `load_model`.

Two stores, one way in:

* a weights file: one msgpack file (`flax.serialization`, never pickle) holding a format
  tag, a version, the config that built the params, provenance and the params. DMD-Net's
  (`save_weights` / `load_weights`) and CNR's share the container
  (`write_weights_file` / `read_weights_file`); the bundled `small` model ships in
  `dmd_jax/weights/` and is read by `load_pretrained()`. DMD-Net's version 2 adds a
  `policy` section (`dmd_jax.policy.DenoisePolicy`: how `denoise` uses the network);
  version 1 files, whose rules were `ModelConfig` fields, still load, their rules moved
  into the policy, and so do version 2 files with the retired selector fields (dropped
  with a warning, `policy.stored_policy`).
* a training checkpoint: an Orbax `CheckpointManager` directory written during
  training (`checkpoint_managers`, `save_checkpoint`, `restore_checkpoint`); its newest
  params and config come back from `load_params`.

`load_model(path)` takes either (or nothing, for the bundled model) and returns a
`ModelBundle`, which is what `denoise` runs.
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
from dmd_jax.io import atomic_write
from dmd_jax.policy import (
    DenoisePolicy,
    from_legacy_model_fields,
    stored_policy,
    trained_policy,
)

WEIGHTS_FORMAT = "dmd_jax-weights"
# 2: a `policy` section beside the config (2026-12-02). 1: the rules inside the model config.
WEIGHTS_VERSION = 2
READABLE_WEIGHTS_VERSIONS = (1, 2)
PRETRAINED_NAME = "dmd_small.msgpack"


class ModelBundle(NamedTuple):
    """Trained params with the config that built them, where they came from, and the
    policy `denoise` runs them with (for a training checkpoint, `policy.trained_policy`:
    the passes the run trained, no pre-smoothing, no relaxation)."""

    params: Any
    config: ExperimentConfig
    meta: dict
    policy: DenoisePolicy = DenoisePolicy()
    # The learned smoothing controller (`dmd_jax.controller.ControllerParams`) stored
    # beside the network, or None.
    controller: Any = None

    def with_vertex_update(self, update: str) -> ModelBundle:
        """The same network run with another vertex update (`"jacobi"` or `"solve"`):
        a controller's option, a search over both."""
        model = self.config.model.replace(vertex_update=update)
        return self._replace(config=self.config.replace(model=model))

    def vertex_updates(self) -> tuple[str, ...]:
        """Every vertex update a default `denoise` call may run these weights with: the
        config's, and those of the controller's options that run the network when the
        policy switches the controller on (what `dmd-jax warmup` compiles)."""
        updates = [self.config.model.vertex_update]
        if self.controller is not None and self.policy.controller:
            updates += [o.update for o in self.controller.options if o.passes and o.update]
        return tuple(dict.fromkeys(updates))


def write_weights_file(
    path,
    *,
    fmt: str,
    version: int,
    config: dict,
    meta: dict,
    params,
    overwrite: bool = False,
    sections: dict | None = None,
) -> Path:
    """Writes one msgpack weights file (format tag, version, config, meta, params), atomically.

    The container of every weights file of this project (DMD-Net's and CNR's); `fmt`
    tells them apart and `read_weights_file` checks it. `sections` adds further named
    JSON sections (DMD-Net's `policy`).
    """
    from flax import serialization

    payload = {
        "format": fmt,
        "version": version,
        "config": json.dumps(config),
        "meta": json.dumps(meta),
        **{name: json.dumps(value) for name, value in (sections or {}).items()},
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
    payload = read_weights_payload(path, fmt=fmt, versions=(version,), kind=kind)
    config = _parse_section(path, payload, "config", parse_config)
    meta = _parse_section(path, payload, "meta", lambda d: d)
    return config, meta, payload["params"]


def _parse_section(path, payload: dict, name: str, parse):
    """`parse(json.loads(payload[name]))`, any failure a `ValueError` naming the file."""
    try:
        return parse(json.loads(payload[name]))
    except (TypeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: unreadable {name} in the weights file ({exc})") from exc
    except RecursionError:  # JSON nested thousands deep: no config is, so no traceback
        raise ValueError(
            f"{path}: unreadable {name} in the weights file (JSON nested too deeply)"
        ) from None


def msgpack_restore(data: bytes):
    """`flax.serialization.msgpack_restore`, without importing Flax: the tree of dicts,
    lists and NumPy arrays `write_weights_file` wrote (arrays read-only views of `data`).

    Every `dmd-jax denoise` process reads the weights, and importing Flax cost it
    0.15-0.25 s on 2 cores (docs/cold-start.md). The same encoding as Flax 0.12's: msgpack
    with extension types 1 (an array: shape, dtype name, C-order bytes), 2 (a complex
    number) and 3 (a NumPy scalar), and arrays above 2^30 bytes stored as
    `__msgpack_chunked_array__` dicts of flat chunks; unknown extensions stay
    `msgpack.ExtType`, as in Flax.

    Raises:
      Exception: whatever msgpack or NumPy raise on truncated or corrupt data.
    """
    import msgpack

    def array(ext: bytes) -> np.ndarray:
        shape, dtype, buffer = msgpack.unpackb(ext, raw=True)
        if dtype == b"bfloat16":  # not a NumPy name: JAX's (ml_dtypes') type
            import ml_dtypes

            dtype = ml_dtypes.bfloat16
        return np.frombuffer(buffer, dtype=np.dtype(dtype), count=-1, offset=0).reshape(
            shape, order="C"
        )

    def ext_hook(code: int, ext: bytes):
        if code == 1:
            return array(ext)
        if code == 2:
            real, imag = msgpack.unpackb(ext)
            return complex(real, imag)
        if code == 3:
            return array(ext)[()]
        return msgpack.ExtType(code, ext)

    def in_order(d: dict) -> tuple:
        return tuple(d[str(i)] for i in range(len(d)))

    def unchunk(d):
        if isinstance(d, dict):
            if "__msgpack_chunked_array__" in d:
                return np.concatenate(in_order(d["chunks"])).reshape(in_order(d["shape"]))
            for k, v in d.items():
                d[k] = unchunk(v) if isinstance(v, dict) else v
        return d

    return unchunk(msgpack.unpackb(data, ext_hook=ext_hook, raw=False, strict_map_key=False))


def read_weights_payload(path, *, fmt: str, versions: tuple[int, ...], kind: str) -> dict:
    """The raw payload of a weights file: format tag and version checked, sections
    `config`, `meta` and `params` present (JSON sections still as text).

    Raises:
      FileNotFoundError: no such file.
      ValueError: a truncated or corrupt file, another format or version, a missing field.
    """
    from dmd_jax.io import check_readable_file

    path = Path(path)
    # A FIFO would block the read, a symlink loop is not a missing file: say which.
    check_readable_file(path, "weights file")
    try:
        payload = msgpack_restore(path.read_bytes())
    except Exception as exc:  # msgpack raises several types on truncated data
        raise ValueError(
            f"{path}: not a readable weights file (truncated or corrupt: {exc})"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise ValueError(f"{path}: not a {kind} weights file")
    if type(payload.get("version")) is not int or payload["version"] not in versions:
        readable = " or ".join(str(v) for v in versions)
        raise ValueError(
            f"{path}: weights format version {payload.get('version')!r} is not supported "
            f"(this dmd_jax reads version {readable})"
        )
    missing = [k for k in ("config", "meta", "params") if k not in payload]
    if missing:
        raise ValueError(f"{path}: incomplete weights file (no {', '.join(missing)})")
    return payload


def save_weights(
    path,
    params,
    config: ExperimentConfig,
    meta: dict | None = None,
    *,
    policy: DenoisePolicy | None = None,
    controller=None,
    overwrite: bool = False,
) -> Path:
    """Writes params + config + policy + meta to one msgpack file (version 2), atomically.

    Args:
      path: the file to write.
      params: the model's params.
      config: the config that built them.
      meta: provenance (JSON types).
      policy: how `denoise` runs them; None stores the default policy.
      controller: a `controller.ControllerParams` to store beside them (a `controller`
        section), or None.
      overwrite: replace an existing file.
    """
    policy = DenoisePolicy() if policy is None else policy
    sections = {"policy": policy.to_dict()}
    if controller is not None:
        sections["controller"] = controller.to_json()
    return write_weights_file(
        path,
        fmt=WEIGHTS_FORMAT,
        version=WEIGHTS_VERSION,
        config=config.to_dict(),
        meta=meta or {},
        params=params,
        overwrite=overwrite,
        sections=sections,
    )


def _config_and_policy(stored: dict, version: int) -> tuple[ExperimentConfig, dict | None]:
    """The config of a stored dict, and for version 1 the policy its model fields held."""
    if version != 1 or not isinstance(stored, dict) or not isinstance(stored.get("model"), dict):
        return ExperimentConfig.from_dict(stored), None
    model, policy = from_legacy_model_fields(stored["model"])
    return ExperimentConfig.from_dict({**stored, "model": model}), policy.to_dict()


def load_weights(path) -> ModelBundle:
    """Reads a weights file written by `save_weights`, checking format, version and config.

    Version 1 files (before the policy had its own section) load with the policy their
    model config held (`policy.from_legacy_model_fields`). Version 2 files written
    before issue 54 load without the fitted selectors' fields of their policy, with one
    `policy.RetiredPolicyWarning` naming them (`policy.stored_policy`).

    Raises:
      ValueError: not a dmd_jax weights file, another format version, a truncated file,
        an unreadable config, policy or meta, or params whose structure or shapes do not
        match the stored config.
    """
    payload = read_weights_payload(
        path, fmt=WEIGHTS_FORMAT, versions=READABLE_WEIGHTS_VERSIONS, kind="dmd_jax"
    )
    version = payload["version"]
    config, legacy = _parse_section(
        path, payload, "config", lambda d: _config_and_policy(d, version)
    )
    if version == 1:
        policy = DenoisePolicy.from_dict(legacy) if legacy else DenoisePolicy()
    elif "policy" not in payload:
        raise ValueError(f"{path}: incomplete weights file (no policy)")
    else:
        policy = _parse_section(path, payload, "policy", lambda d: stored_policy(d, str(path)))
    meta = _parse_section(path, payload, "meta", lambda d: d)
    params = payload["params"]
    if not isinstance(params, dict):
        raise ValueError(f"{path}: params must be a nested dict of arrays")
    check_params(params, config, str(path))
    controller = None
    if "controller" in payload:
        from dmd_jax.controller import ControllerParams

        controller = _parse_section(path, payload, "controller", ControllerParams.from_dict)
    return ModelBundle(
        params=params, config=config, meta=meta, policy=policy, controller=controller
    )


@lru_cache(maxsize=8)
def abstract_params(config: ExperimentConfig):
    """Param shapes and dtypes of a config (`model.param_shapes`, traced once per config
    and process; configs are frozen and hashable, so they are their own cache key)."""
    from dmd_jax.model import param_shapes

    return param_shapes(config.model)


def expected_params(config: ExperimentConfig) -> dict[str, tuple[tuple[int, ...], str]]:
    """`{param path: (shape, dtype name)}` of a config's model.

    Tracing the model's init to learn them takes 0.4 s, a tenth of a `dmd-jax denoise`
    process; the compile cache keeps them beside the compiled network, keyed by the
    model config and every source the network's code reaches
    (`compile_cache.remembered`), so a second process reads them instead.
    """
    from dmd_jax import compile_cache

    def trace():
        return [
            [jax.tree_util.keystr(p), list(x.shape), np.dtype(x.dtype).name]
            for p, x in jax.tree_util.tree_flatten_with_path(abstract_params(config))[0]
        ]

    rows = compile_cache.remembered("param-shapes", repr(config.model), trace)
    return {key: (tuple(shape), dtype) for key, shape, dtype in rows}


def check_params(params, config: ExperimentConfig, name: str) -> None:
    expected = expected_params(config)
    exp_paths = {key: shape for key, (shape, _) in expected.items()}
    got_paths = {
        jax.tree_util.keystr(p): np.shape(x)
        for p, x in jax.tree_util.tree_flatten_with_path(params)[0]
    }
    exp_dtypes = {key: np.dtype(dtype) for key, (_, dtype) in expected.items()}
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
    """Where the bundled `small` weights are installed."""
    return Path(str(resources.files("dmd_jax") / "weights" / PRETRAINED_NAME))


def graft_params(fresh, trained):
    """`fresh` with every parameter `trained` has copied in (fine-tuning a grown model).

    Args:
      fresh: the params of the new model (e.g. `model.init_params`).
      trained: params of a model whose every parameter the new one has, same shape.

    Raises:
      ValueError: a parameter of `trained` is missing from `fresh` or has another shape.
    """
    flat = {jax.tree_util.keystr(p): v for p, v in jax.tree_util.tree_flatten_with_path(trained)[0]}
    seen = set()

    def take(path, leaf):
        key = jax.tree_util.keystr(path)
        if key not in flat:
            return leaf
        if np.shape(flat[key]) != np.shape(leaf):
            raise ValueError(f"{key}: shape {np.shape(flat[key])} cannot replace {np.shape(leaf)}")
        seen.add(key)
        return jnp.asarray(flat[key], leaf.dtype)

    out = jax.tree_util.tree_map_with_path(take, fresh)
    missing = sorted(set(flat) - seen)
    if missing:
        raise ValueError(f"the new model has no parameter {missing[0]} ({len(missing)} missing)")
    return out


def load_pretrained() -> ModelBundle:
    """The bundled `small`-preset model (its model card: docs/bundled-model.md)."""
    path = pretrained_path()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the bundled weights are missing from this installation")
    return load_weights(path)


def as_bundle(params=None, config: ExperimentConfig | None = None) -> ModelBundle:
    """Accepts a `ModelBundle`, a path for `load_model`, raw params plus `config`, or
    None for the bundled model."""
    if params is None:
        if config is not None:
            raise ValueError("config=... needs the raw params it describes")
        return load_pretrained()
    if isinstance(params, ModelBundle):
        return params
    if isinstance(params, (str, Path)):
        return load_model(params)
    if config is None:
        raise ValueError(
            "raw params need their config: pass config=..., or use load_pretrained() / "
            "load_weights() which carry it"
        )
    return ModelBundle(params=params, config=config, meta={}, policy=trained_policy(config))


def load_model(path=None) -> ModelBundle:
    """The model to run: the bundled weights, a weights file, or a checkpoint directory.

    Args:
      path: None for `load_pretrained()`; a file written by `save_weights` (`dmd-jax
        export-weights`); or an Orbax checkpoint directory written by training (its
        newest step, see `load_params`).

    Returns:
      A `ModelBundle`; for a checkpoint its meta is `{"source": str(path)}` and its
      policy `policy.trained_policy(config)`.

    Raises:
      FileNotFoundError: the bundled weights or `path` are missing.
      ValueError: not a valid weights file or checkpoint.
    """
    if path is None:
        return load_pretrained()
    path = Path(path)
    if path.is_dir():
        params, config = load_params(path)
        return ModelBundle(
            params=params, config=config, meta={"source": str(path)}, policy=trained_policy(config)
        )
    return load_weights(path)


# --------------------------------------------------------------------------------------
# Orbax training checkpoints
# --------------------------------------------------------------------------------------


def checkpoint_managers(workdir, keep: int):
    """`(latest, best)` Orbax managers of a run directory.

    `<workdir>/checkpoints/latest` keeps the last `keep` states;
    `<workdir>/checkpoints/best` the one with the lowest `normal_deg` metric.
    """
    import orbax.checkpoint as ocp

    workdir = Path(workdir)
    latest = ocp.CheckpointManager(
        (workdir / "checkpoints" / "latest").absolute(),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=True, enable_async_checkpointing=False
        ),
    )
    best = ocp.CheckpointManager(
        (workdir / "checkpoints" / "best").absolute(),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=1,
            create=True,
            best_fn=lambda m: m["normal_deg"],
            best_mode="min",
            enable_async_checkpointing=False,
        ),
    )
    return latest, best


def save_checkpoint(manager, state, cfg: ExperimentConfig, metrics: dict | None = None):
    """Saves a training state (a NamedTuple of arrays) and its config at `state.step`."""
    import orbax.checkpoint as ocp

    manager.save(
        int(state.step),
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(jax.device_get(state._asdict())),
            config=ocp.args.JsonSave(cfg.to_dict()),
        ),
        metrics=metrics,
    )
    manager.wait_until_finished()


def restore_checkpoint(manager, template, step: int | None = None):
    """The state saved at `step` (default: the newest), shaped like `template`.

    Args:
      manager: an Orbax `CheckpointManager`.
      template: a state of the same NamedTuple type, structure, shapes and dtypes.
      step: which step; None takes the newest.
    """
    import orbax.checkpoint as ocp

    step = manager.latest_step() if step is None else step
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, jax.device_get(template._asdict()))
    restored = manager.restore(
        step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))
    )
    return type(template)(**restored["state"])


def load_params(checkpoint_dir) -> tuple[dict, ExperimentConfig]:
    """Params and config of the newest checkpoint in an Orbax manager directory.

    Training keeps params as halves (`{"fe": ..., "rest": ...}`, see `dmd_jax.train`);
    they come back merged into the model's own param dict.

    Raises:
      FileNotFoundError: no such directory.
      ValueError: the directory holds no checkpoint, or an unreadable one.
    """
    import orbax.checkpoint as ocp

    checkpoint_dir = Path(checkpoint_dir).absolute()
    if not checkpoint_dir.is_dir():
        raise FileNotFoundError(f"{checkpoint_dir}: no such checkpoint directory")
    manager = ocp.CheckpointManager(checkpoint_dir)
    step = manager.latest_step()
    if step is None:
        raise ValueError(f"{checkpoint_dir}: holds no checkpoint")
    try:
        cfg_dict = manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        cfg = ExperimentConfig.from_dict(cfg_dict["config"])
        state = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))
    except FileNotFoundError:
        raise
    except Exception as exc:  # orbax raises assorted types on corrupt directories
        message = " ".join(str(exc).split())[:300]
        raise ValueError(
            f"{checkpoint_dir}: unreadable checkpoint of step {step} "
            f"({type(exc).__name__}: {message})"
        ) from exc
    halves = state["state"]["params"]
    return {**halves["fe"], **halves["rest"]}, cfg
