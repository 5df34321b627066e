"""The compiled forward passes of a trained DMD-Net, one per model config.

Configs are frozen and hashable, so a config is its own cache key: every `denoise` call
(and every patch of one) with the same config reuses one jitted function, and XLA
compiles it once per padded shape.

* `predictor`: the whole network on a whole mesh.
* `patch_predictor`: the network on a patch, every per-mesh pool (the transformer's
  `W_tf`, the STN's) given from outside (`DMDNet(pooled=...)`).
* `pool_predictor`: the network up to some pools only, for the patch path's first sweeps.
"""

from __future__ import annotations

from functools import lru_cache

import jax

from dmd_jax.config import ExperimentConfig, ModelConfig


def _model_config(config: ExperimentConfig | ModelConfig) -> ModelConfig:
    return config.model if isinstance(config, ExperimentConfig) else config


def predictor(config: ExperimentConfig | ModelConfig):
    """`predict(params, noisy, graph) -> [n_vertex, 3]`, jitted, for `config`'s network."""
    return _predictor(_model_config(config))


@lru_cache(maxsize=8)
def _predictor(config: ModelConfig):
    from dmd_jax.model import DMDNet

    model = DMDNet(config)

    @jax.jit
    def predict(params, noisy, graph):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True)
        return out

    return predict


def patch_predictor(config: ExperimentConfig | ModelConfig):
    """`predict(params, noisy, graph, pooled) -> [n_vertex, 3]`, jitted: every per-mesh
    pool given (`DMDNet(pooled=...)`)."""
    return _patch_predictor(_model_config(config))


@lru_cache(maxsize=8)
def _patch_predictor(config: ModelConfig):
    from dmd_jax.model import DMDNet

    model = DMDNet(config)

    @jax.jit
    def predict(params, noisy, graph, pooled):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True, pooled=pooled)
        return out

    return predict


@lru_cache(maxsize=8)
def pool_predictor(config: ModelConfig, names: tuple[str, ...]):
    """`pools(params, noisy, graph, pooled) -> {name: pool}`, jitted: the forward pass up
    to the pools `names` (earlier stages' pools given).

    Only the pools are returned, so XLA drops everything that does not feed them (the
    denoiser, the vertex update).
    """
    from dmd_jax.model import DMDNet

    model = DMDNet(config)

    @jax.jit
    def pools(params, noisy, graph, pooled):
        _, state = model.apply(
            {"params": params},
            noisy,
            graph,
            deterministic=True,
            pooled=pooled,
            mutable=["intermediates"],
        )
        found = dict(_find_sown(state["intermediates"]))
        return {name: found[name][0] for name in names}  # row 0: the patch's graph

    return pools


def _find_sown(tree):
    """`(name, value)` of every value `Module.sow` recorded, at any depth."""
    for key, value in tree.items():
        if isinstance(value, tuple):
            yield key, value[-1]
        else:
            yield from _find_sown(value)
