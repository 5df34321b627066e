"""CNR's training: per-stage samples, the Adam fit of each regressor, the whole cascade
(`train_cnr`) and the `dmd-jax train-cnr` command (`train_main`)."""

from __future__ import annotations

import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from dmd_jax.baselines._common import float_dtype
from dmd_jax.baselines.cascaded_regression.config import CNRConfig
from dmd_jax.baselines.cascaded_regression.features import (
    MeshArrays,
    face_features_jit,
    pad_rows,
    prepare_mesh,
    to_jax,
)
from dmd_jax.baselines.cascaded_regression.model import (
    CNRRegressor,
    CNRWeights,
    cnr,
    save_cnr_weights,
    stage_jit,
)
from dmd_jax.geometry import face_normals
from dmd_jax.graph import bucket_size

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
    desc, base, frames = face_features_jit(x, arr, cfg)
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
                arrays_of[i] = (to_jax(arr, dt), vp)
            arr, vp = arrays_of[i]
            xp = jnp.asarray(pad_rows(x, vp), dt)
            if stage > 0:
                xp, _ = stage_jit(stage_params[-1], xp, arr, cfg)
                copies[j] = (i, np.asarray(xp[: x.shape[0]], np.float64), clean)
            n_face = f.shape[0]
            idx = rng.choice(n_face, min(n_face, faces_per_mesh), replace=False)
            cp = jnp.asarray(pad_rows(clean, vp), dt)
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
