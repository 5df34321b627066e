"""dmd_jax: DMD-Net mesh denoising in JAX and Flax, with sparse segment-sum graph ops.

The promised entry point::

    import dmd_jax

    bundle = dmd_jax.load_pretrained()  # or load_weights(path), load_model(path)
    clean = dmd_jax.denoise(vertices, faces, bundle)

The names below are imported on first use (module `__getattr__`), so `import dmd_jax`
loads neither JAX nor Flax; `__all__` lists them.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# Public name -> the module that defines it (the one place it lives).
_EXPORTS = {
    "denoise": "dmd_jax.inference",
    "ModelBundle": "dmd_jax.checkpoints",
    "load_model": "dmd_jax.checkpoints",
    "load_pretrained": "dmd_jax.checkpoints",
    "load_weights": "dmd_jax.checkpoints",
    "save_weights": "dmd_jax.checkpoints",
    "DMDNet": "dmd_jax.model",
    "ExperimentConfig": "dmd_jax.config",
    "ModelConfig": "dmd_jax.config",
    "LossConfig": "dmd_jax.config",
    "TrainConfig": "dmd_jax.config",
    "NoiseConfig": "dmd_jax.config",
    "PRESETS": "dmd_jax.config",
    "preset": "dmd_jax.config",
    "MeshGraph": "dmd_jax.graph",
    "build_mesh_graph": "dmd_jax.graph",
    "load_mesh": "dmd_jax.io",
    "save_mesh": "dmd_jax.io",
    # The short path of the README: noise with an int seed, any denoiser, the metrics.
    "add_noise": "dmd_jax.api",
    "simulate_scan": "dmd_jax.scan",
    "denoise_with": "dmd_jax.api",
    "mesh_metrics": "dmd_jax.metrics",
    "metrics_table": "dmd_jax.metrics",
    "render_meshes": "dmd_jax.render",
    "comparison_html": "dmd_jax.viewer",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str):
    """Imports a public name's module on first access and caches the name here."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'dmd_jax' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
