"""The short Python path: noise with an integer seed, and every denoiser through one call.

These are exported at the package root (`dmd_jax.add_noise`, `dmd_jax.denoise_with`),
so an experiment needs no submodule import::

    import dmd_jax

    clean, faces = dmd_jax.load_mesh("part.obj")
    noisy = dmd_jax.add_noise(0, clean, faces, "gaussian", 0.2, units="edge")
    rows = {m: dmd_jax.mesh_metrics(dmd_jax.denoise_with(m, noisy, faces), clean, faces)
            for m in ("dmd", "taubin", "bnf")}
    print(dmd_jax.metrics_table(rows, label="method"))
"""

from __future__ import annotations

import numpy as np

# Every method `denoise_with` accepts: DMD-Net, then `dmd_jax.baselines` (classic
# filters, then the learned CNR). The CLI's `--method` takes the same names.
METHODS = ("dmd", "laplacian", "taubin", "bmd", "nifp", "fefp", "bnf", "gnf", "l0", "cnr")


def _float_dtype(vertices) -> np.dtype:
    """float32 stays float32; every other input (float64, float16, integers) -> float64."""
    dtype = np.asarray(vertices).dtype
    return np.dtype(np.float32) if dtype == np.float32 else np.dtype(np.float64)


def add_noise(
    seed,
    vertices,
    faces,
    kind: str,
    level: float,
    *,
    units: str = "canonical",
    impulse_p: float = 0.15,
    impulse_q: float = 0.15,
    impulse_mode: str = "coordinate",
    direction: str = "isotropic",
    view=None,
) -> np.ndarray:
    """`dmd_jax.noise.add_noise_jax` for NumPy users: an integer seed, NumPy out, dtype kept.

    Args:
      seed: an `int` (as `dmd-jax add-noise --seed`) or a `jax.random` key.
      vertices: `[n_vertex, 3]` positions, in any frame.
      faces: `[n_face, 3]` vertex indices (used by `units="edge"`).
      kind: `gaussian`, `uniform`, `gamma`, `impulse` or `scanner` (`dmd_jax.noise`).
      level: σ for Gaussian, the rms for scanner, the amplitude for the other kinds, in
        `units`.
      units: `"canonical"` (fraction of the longest bounding-box side) or `"edge"`
        (× mean edge length).
      impulse_p, impulse_q, impulse_mode: see `dmd_jax.noise.add_noise_jax`.
      direction: `"isotropic"` (per coordinate) or `"normal"` (one draw per vertex along
        its vertex normal: the mesh-denoising benchmark protocol). The scanner kind moves
        along its view and takes the default.
      view: `kind="scanner"` only: the direction the sensor looks along, `[3]`; None
        draws it from the seed.

    Returns:
      `[n_vertex, 3]` NumPy array: float32 for float32 input, float64 otherwise (the
      unit draws are float32 from `jax.random`, so a seed gives the same noise whether or
      not JAX's float64 mode is on, and the same as `dmd-jax add-noise --seed`).
    """

    import jax.numpy as jnp

    from dmd_jax import noise
    from dmd_jax.mesh import validate_mesh, validate_vertices

    # Every argument is checked before any draw, as `denoise` checks its own.
    key = noise.seed_key(seed)
    noise.check_kind(kind)
    level = noise.check_level(level)
    noise.check_units(units)
    noise.check_direction(direction)
    noise.check_impulse(impulse_p, impulse_q, impulse_mode)
    dtype = _float_dtype(vertices)
    if faces is None:
        v = validate_vertices(vertices)
    else:
        v, faces = validate_mesh(vertices, faces)
    if kind == "scanner":
        if direction != "isotropic":
            raise ValueError(
                f"kind='scanner' moves vertices along its view, not direction={direction!r}"
            )
        return noise.scanner_noise(key, v, faces, level, units=units, view=view).astype(dtype)
    if view is not None:
        raise ValueError(f"view is the scanner kind's; kind {kind!r} takes none")
    along_normal = direction == "normal"
    if along_normal and faces is None:
        raise ValueError("direction='normal' needs the faces of the mesh")
    # noise.add_noise_jax's unit draws (float32) and noise unit, combined in float64.
    x = noise.unit_noise(
        key,
        (v.shape[0], 1) if along_normal else v.shape,
        kind,
        dtype=jnp.float32,
        impulse_p=impulse_p,
        impulse_q=impulse_q,
        impulse_mode=impulse_mode,
    )
    unit = float(noise.noise_unit_length(v, faces, units))
    x = np.asarray(x, np.float64)
    if along_normal:
        x = x * noise.vertex_normals_np(v, faces)
    return (v + level * unit * x).astype(dtype)


def denoise_with(
    method: str, vertices, faces=None, *, weights=None, iterations: int | None = None, **params
) -> np.ndarray:
    """Denoises with DMD-Net or any baseline of `dmd_jax.baselines`, one call for all.

    Args:
      method: `"dmd"` (the network) or a name of `METHODS` (`taubin`, `bnf`, `cnr`, ...).
      vertices: `[n_vertex, 3]` noisy positions, in any frame, or a mesh object with
        `.vertices` and `.faces` (a `trimesh.Trimesh`) standing for both.
      faces: `[n_face, 3]` vertex indices.
      weights: DMD-Net or CNR weights: None for the bundled ones, a weights file, a
        checkpoint directory (DMD-Net), or a loaded `ModelBundle`. Classic filters have
        none, and refuse it.
      iterations: passes of the denoiser, each starting from the last one's output;
        None (default): one for a classic filter, the model's own policy for DMD-Net
        (`dmd_jax.inference.denoise`).
      **params: parameters of a baseline (`dmd_jax.baselines.DEFAULTS[method]`), or
        keywords of `dmd_jax.inference.denoise` for DMD-Net (`aggregation`, `policy`,
        `presmooth`, `relax`, `max_memory`, `return_info`, ...).

    Returns:
      `[n_vertex, 3]` NumPy array in the input frame and vertex order: float32 for
      float32 input, float64 otherwise.

    Raises:
      ValueError: unknown method or parameter, weights for a classic filter, bad mesh.
    """
    if faces is None and hasattr(vertices, "vertices") and hasattr(vertices, "faces"):
        vertices, faces = vertices.vertices, vertices.faces  # a trimesh.Trimesh
    if faces is None:
        raise TypeError(
            "denoise_with needs faces: pass denoise_with(method, vertices, faces) or a mesh "
            "object with .vertices and .faces (e.g. a trimesh.Trimesh)"
        )
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of: {', '.join(METHODS)}")
    if iterations is not None and (
        isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1
    ):
        raise ValueError(f"iterations must be a positive integer or None, got {iterations!r}")
    dtype = _float_dtype(vertices)
    if method == "dmd":
        from dmd_jax.checkpoints import ModelBundle, load_model
        from dmd_jax.inference import denoise

        bundle = weights if isinstance(weights, ModelBundle) else load_model(weights)
        out = denoise(vertices, faces, bundle, iterations=iterations, **params)
        if params.get("return_info"):
            out, info = out
            return np.asarray(out).astype(dtype, copy=False), info
        return np.asarray(out).astype(dtype, copy=False)
    from dmd_jax import baselines

    if weights is not None:
        if method not in baselines.LEARNED:
            raise ValueError(f"{method!r} is a classic filter and takes no weights")
        params = {**params, "weights": weights}
    if iterations is not None and iterations > baselines.MAX_PASSES:
        raise ValueError(f"iterations must be at most {baselines.MAX_PASSES}, got {iterations!r}")
    out = vertices
    for _ in range(1 if iterations is None else int(iterations)):
        out = baselines.run_baseline(method, out, faces, **params)
    return np.asarray(out).astype(dtype, copy=False)
