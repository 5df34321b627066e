"""Presets (`preset(name)`: `paper`, `small`, `test`, `gpu`) and the paper's structure
variants (`VARIANTS`, `variant_config`). What each preset is and why is in the docstring
of `dmd_jax.config` and of each builder below."""

from __future__ import annotations

from typing import Any

from dmd_jax.config.sections import (
    VARIANT_NAMES,
    DataConfig,
    ExperimentConfig,
    LossConfig,
    ModelConfig,
    NoiseConfig,
    TrainConfig,
)

# The paper's canonical-frame levels with the heaviest cut, so a draw stays within about
# one mean edge on the 1k-6k-vertex training meshes and patches (model-audit, item B).
CAPPED_CANONICAL_LEVELS = (
    ("gaussian", (0.005, 0.01, 0.02)),
    ("uniform", (0.01, 0.02, 0.035)),
    ("gamma", (0.005, 0.01, 0.015)),
    ("impulse", (0.01, 0.02, 0.05)),
)


def _paper() -> ExperimentConfig:
    return ExperimentConfig(
        name="paper",
        model=ModelConfig(width=512, fe_two_streams=2, depth=2, variant="fgt8"),
        loss=LossConfig(),
        train=TrainConfig(steps=200_000, batch_size=4),
    )


def _small() -> ExperimentConfig:
    # The first stage of the bundled weights' recipe (docs/bundled-model.md): resolution-free
    # inputs, normal-first head, edge-unit noise mostly along normals with clean draws.
    return ExperimentConfig(
        name="small",
        model=ModelConfig(
            width=32,
            fe_two_streams=2,
            depth=2,
            variant="fgt8",
            stn_width=32,
            encoding="local",
            head="normal",
            taubin_iterations=10,
        ),
        loss=LossConfig(
            vertex=1.0,
            normal=1.0,
            curvature=0.0,
            chamfer=0.0,
            feature=0.02,
            feature_curvature="asinh",
            face_normal=1.0,
        ),
        train=TrainConfig(
            # 6,000 steps: on the same data a 3,000-step run reached 11.7° on the
            # validation patches and a 6,000-step run 11.1° (docs/history.md).
            steps=6000,
            batch_size=2,
            lr=1e-3,
            schedule="cosine",
            warmup_steps=100,
            eval_every=500,
            ckpt_every=100,
        ),
        noise=NoiseConfig(
            canonical_levels=CAPPED_CANONICAL_LEVELS,
            edge_levels=(0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5),
            p_edge=0.85,
            p_normal=0.6,
            p_clean=0.1,
        ),
        data=DataConfig(target_vertices=2000),
    )


def _test() -> ExperimentConfig:
    # The small recipe (encoding, head, losses, noise, schedule) at width 8 and 40
    # steps: `dmd-jax train --preset test` on a `--per-category 2` dataset trains
    # in under a minute on 2 cores and beats its noisy input (tests/test_cli.py). Unit
    # tests build on it too, so it stays the smallest model that is still the recipe.
    small = _small()
    return small.replace(
        name="test",
        model=small.model.replace(width=8, stn_width=8),
        loss=small.loss.replace(chamfer_block=256),
        train=small.train.replace(
            steps=40,
            batch_size=1,
            warmup_steps=5,
            eval_every=0,
            ckpt_every=0,
            log_every=5,
        ),
        data=DataConfig(instances_per_category=2, target_vertices=200),
    )


def _gpu() -> ExperimentConfig:
    """The paper's architecture at width 128: the `gpu` ablation sweep, about an hour.

    `python -m experiments run --preset gpu` (`make ablate-gpu`) trains every study with
    3 seeds (side by side, one program per row): 31 distinct rows, 27 at `steps` and the
    4 depth rows at 10/3 of it (the paper's 200 against 60 epochs), i.e. 27 x 1,200 +
    4 x 4,000 = 48,400 row steps of batch 4.

    Step cost, measured with `python -m experiments.device_bench --size full` on this
    repository's 2 shared CPU cores (load 5-9, 2026-12-02; CPU seconds per step, which a
    loaded machine inflates less than wall time): `small` (width 32, batch 2, padded to
    5,120 vertices) 0.47 s, `paper` (width 512, batch 4, 10,240 vertices) 17.2 s. Per
    padded vertex, t(W) = a + b W^2 through both: a = 8.5e-5 s, b = 6.1e-9 s, so width
    128 costs 1.85e-4 s per vertex; a batch of 4 meshes of 900-1,000 vertices pads to
    4,096, so one seed's step is 0.76 s and a row's (3 seeds) 2.3 s of CPU.

    GPU assumption: one H100/H200-class GPU runs these f32 gather/scatter and width-128
    matmul kernels 50x faster than the 2 cores, with a floor of 10 ms a step (a few
    hundred fused kernels and the host's batch): a row step takes max(2.3 / 50, 0.01)
    = 46 ms, so the 48,400 row steps take 37 min. Compilation: 17 distinct train-step
    programs and 15 models (init and predictor) for the 31 rows, once rows share
    programs (`train.step_program_key`), at an assumed 40 s and 20 s each, 16 min of
    CPU, about half of it hidden behind the other worker's training (2 workers on one
    GPU). Data (228 meshes on 16 cores), calibration, references and the noise and
    rotation evaluations: about 6 min. Total: about 37 + 8 + 6 = 51 min. `device_bench` on the
    GPU measures the two assumptions (steps/s of `small` and `paper`); rescale `steps`
    by its ratio to them if they are off.

    The learning rate is the cpu preset's (5e-4, cosine, 50 warm-up steps): the paper's
    constant 1e-4 is tuned for 150,000 steps, not 1,200.
    """
    return ExperimentConfig(
        name="gpu",
        model=ModelConfig(width=128, fe_two_streams=2, depth=2, variant="fgt8"),
        loss=LossConfig(feature_curvature="asinh"),
        train=TrainConfig(
            steps=1200,
            batch_size=4,
            lr=5e-4,
            schedule="cosine",
            warmup_steps=50,
            eval_every=0,
            ckpt_every=200,
            ckpt_keep=1,
            log_every=20,
        ),
        data=DataConfig(target_vertices=1000),
    )


PRESETS = {"paper": _paper, "small": _small, "test": _test, "gpu": _gpu}


def preset(name: str) -> ExperimentConfig:
    """The named preset (`paper`, `small`, `test` or `gpu`) as an `ExperimentConfig`."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]()


# The paper's structure ablation (appendix D): display name -> ModelConfig edits.
VARIANTS: dict[str, dict[str, Any]] = {
    "FGT-8": {"variant": "fgt8"},
    "FGT-3": {"variant": "fgt3"},
    "W/O T": {"variant": "wo_t"},
    "MT": {"variant": "mt"},
    "DO-2S": {"variant": "do_2s"},
    "DO-1S": {"variant": "do_1s"},
    "FGT-1S": {"variant": "fgt_1s"},
}


def variant_config(model: ModelConfig, name: str) -> ModelConfig:
    """`model` with the structure-ablation edits of `name` (a key of `VARIANTS`, or a
    variant id such as `"fgt3"`)."""
    if name in VARIANTS:
        return model.with_edits(VARIANTS[name])
    if name in VARIANT_NAMES:
        return model.with_edits({"variant": name})
    raise ValueError(
        f"unknown variant {name!r}; choose one of {list(VARIANTS)} or {list(VARIANT_NAMES)}"
    )
