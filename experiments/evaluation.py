"""What every run of a sweep is scored on: the noisy test meshes (`sweep_scores`, one
noise key `EVAL_SEED` for every row and seed), a trained checkpoint's scores, the
reference rows (classic denoisers, the untrained model; `ensure_references`), and the
noise and rotation studies' evaluations. Used by the jobs of `experiments.runner`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from experiments import studies as st
from experiments.planning import _read_json, _write_json

# The key of every evaluation's noise (and of the rotation test's rotations), the same
# for every row and seed: all models are scored on the same noisy test meshes, so seed
# spreads are the training's and differences pair mesh by mesh. (12345 is what
# `dmd_jax.train.train` uses at seed 0.)
EVAL_SEED = 12345
# Classic denoisers scored on every sweep's test meshes (reference rows of the tables):
# Taubin is the bar for the base model, BNF the strongest classic filter on our
# real meshes (benchmarks/results/sota_lite.md).
CLASSIC_REFERENCES = ("taubin", "bnf")
REFERENCES_FILE = "references.json"


def _mean_dicts(rows: Sequence[dict]) -> dict:
    if not rows:
        return {}
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def sweep_scores(cfg, eval_sets, score: Callable) -> tuple[dict, dict]:
    """Scores something on the noisy test meshes every row of a sweep is scored on.

    The meshes are `evaluation_batches` of each split with `EVAL_SEED` and `cfg`'s
    noise, rotation and encoding: the same for every row, seed and reference.

    Args:
      cfg: an `ExperimentConfig` (its noise, rotation and encoding).
      eval_sets: `{"test_intra": [MeshExample], "test_inter": [...]}`.
      score: `score(batches) -> [metrics dict per mesh]`.

    Returns:
      `(means, per_mesh)`: `<split>/<metric>` means and lists (one value per test mesh).
    """
    from dmd_jax.pipeline import evaluation_batches

    means, per_mesh = {}, {}
    for name, examples in eval_sets.items():
        if not examples:
            continue
        batches = evaluation_batches(
            examples,
            seed=EVAL_SEED,
            noise=cfg.noise,
            rotate=cfg.train.rotate,
            encoding=cfg.model.encoding,
        )
        for k, values in _columns_of(score(batches)).items():
            per_mesh[f"{name}/{k}"] = values
            means[f"{name}/{k}"] = float(np.mean(values))
    return means, per_mesh


def _columns_of(rows: Sequence[dict]) -> dict[str, list[float]]:
    return {k: [float(r[k]) for r in rows] for k in rows[0]} if rows else {}


def evaluate_checkpoint(cfg, checkpoint_dir, eval_sets) -> tuple[dict, dict]:
    """The test metrics of a saved checkpoint, with the sweep's evaluation noise.

    Returns:
      `(means, per_mesh)`: `<split>/<metric>` means and lists (one value per test mesh),
      as `multiseed.train_seeds` reports them.
    """
    from dmd_jax.checkpoints import load_params
    from experiments.multiseed import eval_trainer, evaluate_per_mesh

    params, _ = load_params(checkpoint_dir)
    trainer = eval_trainer(cfg)  # the predictor every run of this model shares
    return sweep_scores(cfg, eval_sets, lambda b: evaluate_per_mesh(trainer, params, b))


def classic_references(cfg, eval_sets, methods: Sequence[str] = CLASSIC_REFERENCES) -> dict:
    """Classic denoisers on the sweep's noisy test meshes, as reference rows of the tables.

    The meshes are the ones every training-study row is scored on (`sweep_scores`), so
    a study's rows can be read against, e.g., Taubin smoothing, not only against the
    noisy input.

    Args:
      cfg: the sweep's base `ExperimentConfig`.
      eval_sets: `{"test_intra": [MeshExample], "test_inter": [...]}`.
      methods: `dmd_jax.api.denoise_with` method names, run at their defaults.

    Returns:
      `{method: {"<split>/<metric>": mean, ..., "per_mesh": {"<split>/<metric>": [...]}}}`.
    """
    from dmd_jax.api import denoise_with
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.pipeline import unpadded_mesh

    def scorer(method):
        def score(batches):
            rows = []
            for batch, _ in batches:
                noisy, clean, faces = unpadded_mesh(batch)
                rows.append(mesh_metrics(denoise_with(method, noisy, faces), clean, faces))
            return rows

        return score

    out = {}
    for method in methods:
        means, per_mesh = sweep_scores(cfg, eval_sets, scorer(method))
        out[method] = {**means, "per_mesh": per_mesh}
    return out


def untrained_reference(cfg, eval_sets) -> dict:
    """The base config's network at initialisation, on the sweep's noisy test meshes.

    With the normal-first head an untrained network is no identity: its zero-initialised
    head averages the candidate normals (the noisy one and the bilateral pre-filtered
    ones) and the vertex update follows them. This row shows what the fixed parts of the
    model give before any training, i.e. what training itself buys. Empty for the
    offset head (untrained, it returns the noisy input).

    Returns:
      `{"<split>/<metric>": mean, ..., "per_mesh": {...}}` like `classic_references`.
    """
    import jax

    from dmd_jax.model import init_params
    from experiments.multiseed import eval_trainer, evaluate_per_mesh

    if cfg.model.head != "normal":
        return {}
    params = jax.jit(lambda key: init_params(cfg.model, key))(jax.random.PRNGKey(cfg.train.seed))
    trainer = eval_trainer(cfg)

    def score(batches):
        rows = evaluate_per_mesh(trainer, params, batches)
        return [{k: v for k, v in r.items() if not k.startswith("noisy_")} for r in rows]

    means, per_mesh = sweep_scores(cfg, eval_sets, score)
    return {**means, "per_mesh": per_mesh}


def ensure_references(out_dir, cfg, eval_sets) -> dict:
    """`classic_references` and `untrained_reference` (key `"untrained"`) of a sweep,
    each computed once and kept in `out_dir`."""
    path = Path(out_dir) / REFERENCES_FILE
    refs = _read_json(path) if path.is_file() else {}
    missing = [m for m in CLASSIC_REFERENCES if m not in refs]
    if missing:
        refs.update(classic_references(cfg, eval_sets, missing))
    if "untrained" not in refs:
        untrained = untrained_reference(cfg, eval_sets)
        if untrained:
            refs["untrained"] = untrained
    _write_json(path, refs)
    return refs


def noise_evaluation(bundle, examples, kind: str, level: float, *, seed: int = EVAL_SEED):
    """The noise table's row `(kind, level)`: mean metrics of the denoised meshes and of
    the noisy input ("reference") against the clean meshes.

    Noise is added in the canonical frame of the clean mesh (level = a length in the unit
    cube, the paper's convention) with a key that depends only on the row and the mesh,
    so every model sees the same noisy meshes.
    """
    import jax

    from dmd_jax.inference import denoise
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.noise import add_noise_jax

    row = [(k, lv) for k, lv, _ in st.NOISE_ROWS].index((kind, level))
    key = jax.random.fold_in(jax.random.PRNGKey(seed), row)
    den, ref = [], []
    for i, ex in enumerate(examples):
        clean = np.asarray(ex.vertices, np.float64)
        noisy = np.asarray(
            add_noise_jax(jax.random.fold_in(key, i), clean, ex.faces, kind, level), np.float64
        )
        out = denoise(noisy, ex.faces, bundle)
        den.append(mesh_metrics(out, clean, ex.faces))
        ref.append(mesh_metrics(noisy, clean, ex.faces))
    d, r = _mean_dicts(den), _mean_dicts(ref)
    return {
        **{f"denoised/{k}": v for k, v in d.items()},
        **{f"reference/{k}": v for k, v in r.items()},
        "n_meshes": len(examples),
        "per_mesh": {
            **{f"denoised/{k}": [x[k] for x in den] for k in d},
            **{f"reference/{k}": [x[k] for x in ref] for k in r},
        },
    }


def rotation_evaluation(bundle, examples, *, gamma: int = st.RE_GAMMA, seed: int = EVAL_SEED):
    """The rotation-equivariance test of the paper's appendix E.

    For each test mesh `G_i` (the clean mesh with mixed training noise, in its canonical
    frame: centred, longest side 1) and `γ` random rotations `R_ij`, compares
    `G^RD = R_ij(D(G_i))` with `G^DR = D(R_ij(G_i))` by the vertex, normal and chamfer
    losses, averaged over `γ |S|` pairs (eqs. RE_test_vertex/normal/chamfer). The losses
    are taken as they stand in that frame (no re-normalisation), as the paper's formulas
    read; `vertex_per_coord` is the vertex loss divided by 3, the convention of the
    paper's tables. Also returns the denoising error of `D(G_i)` against the clean mesh
    (`denoised/...`), because a network that changes nothing is trivially equivariant.
    """
    import jax

    from dmd_jax import losses
    from dmd_jax.inference import denoise
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.pipeline import corrupt, random_rotation

    noise = bundle.config.noise
    base = jax.random.PRNGKey(seed)
    pairs, quality, per_mesh = [], [], []
    for i, ex in enumerate(examples):
        k_noise, k_rot = jax.random.split(jax.random.fold_in(base, i))
        noisy, clean, _ = corrupt(k_noise, ex.vertices, ex.faces, rotate=False, noise=noise)
        d = denoise(noisy, ex.faces, bundle)
        quality.append(mesh_metrics(d, clean, ex.faces))
        first = len(pairs)
        for j in range(gamma):
            r = random_rotation(jax.random.fold_in(k_rot, j))
            rd = d @ r.T
            dr = denoise(noisy @ r.T, ex.faces, bundle)
            v = float(losses.vertex_loss(rd, dr))
            pairs.append(
                {
                    "vertex": v,
                    "vertex_per_coord": v / 3.0,
                    "normal_deg": float(losses.normal_loss(rd, dr, ex.faces, degrees=True)),
                    "chamfer": float(losses.chamfer_distance(rd, dr)),
                }
            )
        # Per mesh, its γ rotations averaged: the unit the bootstrap resamples.
        per_mesh.append(
            {
                **{f"re/{k}": v for k, v in _mean_dicts(pairs[first:]).items()},
                **{f"denoised/{k}": v for k, v in quality[-1].items()},
            }
        )
    return {
        **{f"re/{k}": v for k, v in _mean_dicts(pairs).items()},
        **{f"denoised/{k}": v for k, v in _mean_dicts(quality).items()},
        "n_meshes": len(examples),
        "gamma": gamma,
        "per_mesh": {k: [m[k] for m in per_mesh] for k in (per_mesh[0] if per_mesh else {})},
    }
