"""The paper's ablation studies as sweeps of frozen configs, and the presets they run at.

A *study* is a list of rows; a *run* is one row at one seed. Every run is an
`ExperimentConfig` derived from one base config with `with_edits`:

* the seven training studies of the paper's appendix D (training scheme, dropout, graph
  attention, structure, loss, depth, STN) take their rows from `experiments.ablations.ABLATIONS`
  unchanged (`ablation_config`);
* `noise` evaluates one trained model (the base config, i.e. the final loss weights) on
  the paper's noise table: four kinds times three levels, against the noisy input as
  reference;
* `rotation` is the rotation-equivariance test of appendix E (γ = 5 random rotations
  per test mesh) for models trained with and without rotation augmentation and STN.

Every run has a deterministic id, `<readable row name>-<hash>`, the hash being the
SHA-256 of the config JSON (its `name` left out, so a row that appears in several studies
with the same settings, such as FGT-8 = Joint = `Dr=0.0`, has the same training hash and is
trained once) plus the evaluation it gets. Seeds are part of the config (`train.seed`).

Presets (`PRESETS`):

* `test`: the smoke sweep. Width 8, two steps per run, one mesh size (one padding bucket),
  one test mesh per split, XLA backend optimisation level 0.
* `cpu`: the `small` recipe at width 32, 1,000 steps of batch 2 on 80 training meshes of
  322-383 vertices (one padding bucket), 3 seeds per row trained together
  (`experiments.multiseed`), evaluated on every test mesh (16 test-intra, 18
  test-inter); sized for `make ablate` in <= 3 h on two free cores.
* `cpu-quick`: `make ablate-quick`, a first look: `cpu` at 300 steps, four studies
  (encoding, head, attention, STN), 3 seeds, the first 8 test meshes of each split.
* `cpu-offset`: the second base recipe, where the network does the denoising: `cpu` with
  the direct-offset head (an identity map before training, no pre-filtered candidates
  to average), 3,000 steps at lr 1e-3, 5 seeds per row; a sweep of several sessions
  (resumable).
* `paper`: the paper's width and epochs (60 epochs of 10⁴ meshes at batch 4 = 150,000
  steps; 200 epochs = 500,000 for the depth study) on the procedural dataset at 40 shapes
  per category; for GPUs.

Two settings of every preset depart from the paper's literal values, for reasons measured
on our data (see `experiments/results/README.md`): the curvature-loss scales γ_H, γ_G are
re-chosen for the dataset (the paper chose its own "based on distribution of objects in
our dataset"; here they are computed, see `experiments.runner.calibrate_curvature`), and
the feature extractor learns `asinh` of the curvatures (`LossConfig.feature_curvature`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from dmd_jax.config import ExperimentConfig, preset
from dmd_jax.data.dataset import DEFAULT_TEST_INTER
from experiments.ablations import ABLATIONS, ablation_config

# --------------------------------------------------------------------------------------
# Studies
# --------------------------------------------------------------------------------------

TRAIN = "train"
NOISE = "noise"
ROTATION = "rotation"


class Study(NamedTuple):
    """One study: its directory name, title, kind, the paper's table and its rows.

    Attributes:
      key: directory and CLI name.
      title: table title.
      kind: `train` (one model per row, evaluated on test-intra and test-inter), `noise`
        (one model, one row per noise setting) or `rotation` (one model per row, the
        rotation-equivariance test).
      paper_table: the `\\label` of the paper's table.
      rows: row names, in the paper's order.
      reference: the row the paper chose (every other row is compared against it).
    """

    key: str
    title: str
    kind: str
    paper_table: str
    rows: tuple[str, ...]
    reference: str | None


# The paper's noise table (section 4): kind, level in the canonical frame, display name.
NOISE_ROWS: tuple[tuple[str, float, str], ...] = (
    ("gamma", 0.03, "0.03·Γ(2,2)"),
    ("gamma", 0.04, "0.04·Γ(2,2)"),
    ("gamma", 0.05, "0.05·Γ(2,2)"),
    ("gaussian", 0.025, "N(0,0.025)"),
    ("gaussian", 0.05, "N(0,0.05)"),
    ("gaussian", 0.1, "N(0,0.1)"),
    ("impulse", 0.05, "0.05·δ(0.15,0.15)"),
    ("impulse", 0.1, "0.1·δ(0.15,0.15)"),
    ("impulse", 0.2, "0.2·δ(0.15,0.15)"),
    ("uniform", 0.05, "0.05·U(−1,1)"),
    ("uniform", 0.1, "0.1·U(−1,1)"),
    ("uniform", 0.2, "0.2·U(−1,1)"),
)
NOISE_MODEL_ROW = "DMD-Net"

# The rotation-equivariance test (appendix E): the paper's two models plus the two
# without rotation augmentation, which show what the augmentation buys. All use the base
# config's (final) loss weights, as the paper's final model does.
ROTATION_ROWS: dict[str, dict[str, Any]] = {
    "Rotation Augmentation": {"train": {"rotate": True}, "model": {"stn": False}},
    "Rotation Augmentation + STN": {"train": {"rotate": True}, "model": {"stn": True}},
    "No Augmentation": {"train": {"rotate": False}, "model": {"stn": False}},
    "No Augmentation + STN": {"train": {"rotate": False}, "model": {"stn": True}},
}
RE_GAMMA = 5  # random rotations per test mesh (paper: γ = 5)

STUDIES: tuple[Study, ...] = (
    Study(
        "scheme",
        "Training scheme",
        TRAIN,
        "table:training_strategy",
        tuple(ABLATIONS["scheme"]),
        "Joint",
    ),
    Study("dropout", "Dropout rate", TRAIN, "table:dropout", tuple(ABLATIONS["dropout"]), "Dr=0.0"),
    Study(
        "attention",
        "Graph attention",
        TRAIN,
        "table:attention",
        tuple(ABLATIONS["attention"]),
        "Without Attention",
    ),
    Study(
        "structure",
        "Network structure",
        TRAIN,
        "table:structure_ablation",
        tuple(ABLATIONS["structure"]),
        "FGT-8",
    ),
    Study("loss", "Loss", TRAIN, "table:loss_ablation", tuple(ABLATIONS["loss"]), "With All"),
    Study("depth", "Depth", TRAIN, "table:depth_ablation", tuple(ABLATIONS["depth"]), "DMD-Net 2"),
    Study("stn", "Spatial transformer", TRAIN, "table:STN", tuple(ABLATIONS["stn"]), "Without STN"),
    # Not in the paper (no paper table): the resolution-free encoding and the output head.
    Study(
        "encoding",
        "Input encoding",
        TRAIN,
        "",
        tuple(ABLATIONS["encoding"]),
        "xyz (paper)",
    ),
    Study("head", "Output head", TRAIN, "", tuple(ABLATIONS["head"]), "offset"),
    Study(
        "noise",
        "Noise evaluation",
        NOISE,
        "table:Noise_Evaluation",
        tuple(name for _, _, name in NOISE_ROWS),
        None,
    ),
    Study(
        "rotation",
        "Rotation-equivariance test",
        ROTATION,
        "table:REq",
        tuple(ROTATION_ROWS),
        "Rotation Augmentation",
    ),
)
STUDY_KEYS = tuple(s.key for s in STUDIES)


def get_study(key: str) -> Study:
    """The study called `key` (one of `STUDY_KEYS`)."""
    for study in STUDIES:
        if study.key == key:
            return study
    raise ValueError(f"unknown study {key!r}; choose from {', '.join(STUDY_KEYS)}")


# --------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class AblatePreset:
    """Where and how big a sweep runs.

    Attributes:
      name: preset name; the dataset cache is `data/ablate-<name>` and the results
        `experiments/results/<name>` unless told otherwise.
      base: the `dmd_jax.config` preset the base config starts from.
      edits: `with_edits` applied to it (width, steps, schedule, ...).
      study_edits: extra edits per study key, applied after the row's edits.
      categories: procedural categories of the dataset (`None`: all).
      test_inter: categories held out whole (the paper's test-inter).
      per_category: shapes generated per category.
      min_vertices, max_vertices: vertex range of every mesh.
      intra_fraction: share of each category in test-intra.
      data_seed: dataset seed.
      eval_meshes: test meshes used per split (`None`: all); also the meshes of the
        noise and rotation studies (test-intra and test-inter together, as the paper).
      seeds: training seeds; every row runs once per seed.
      calibrate_curvature: compute γ_H, γ_G from the training set (see module doc).
      xla_opt_level: `--xla_backend_optimization_level` for the worker processes
        (`None`: XLA's default). Level 0 compiles about 35 % faster on CPU and runs
        slower, the right trade for runs of a few steps.
      jax_cache: keep compiled programs in JAX's persistent compilation cache
        (`$ABLATE_JAX_CACHE`, default `~/.cache/dmd_jax/xla-ablate`), so a rerun or a
        resumed run skips most of the compile time.
      workers: rows trained in parallel (processes); a row's seeds train together in
        one process (`experiments.multiseed`).
      seeds_together: how many of a row's seeds share one vmapped program (`None`: all);
        the rest of the row's seeds follow in the same process, one group after the
        other, on the same compiled program. At 5 seeds on two busy cores one seed at a
        time costs 25 % less CPU per step than all five vmapped
        (docs/ablations.md, measured by the retired `experiments/seed_speedup.py`).
      dataset: the dataset cache's name, `data/ablate-<dataset>` (default: `name`);
        presets that share one dataset name it alike and generate it once.
      studies: the studies `run` does by default (`None`: every study).
      dataset_workers: processes generating the dataset (`None`: every core).
      description: one line for the results README.
    """

    name: str
    base: str
    edits: Mapping[str, Any]
    study_edits: Mapping[str, Mapping[str, Any]]
    categories: tuple[str, ...] | None
    test_inter: tuple[str, ...]
    per_category: int
    min_vertices: int
    max_vertices: int
    intra_fraction: float = 0.2
    data_seed: int = 0
    eval_meshes: int | None = None
    seeds: tuple[int, ...] = (0,)
    calibrate_curvature: bool = True
    xla_opt_level: int | None = None
    jax_cache: bool = True
    workers: int = 1
    seeds_together: int | None = None
    dataset: str | None = None
    studies: tuple[str, ...] | None = None
    dataset_workers: int | None = 1
    description: str = ""

    @property
    def dataset_name(self) -> str:
        """The dataset cache's name (`data/ablate-<dataset_name>`)."""
        return self.dataset or self.name

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AblatePreset:
        """Inverse of `to_dict` (lists back to tuples)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"AblatePreset: unknown key(s) {unknown}")
        out = dict(data)
        for key in ("categories", "test_inter", "seeds", "studies"):
            if out.get(key) is not None:
                out[key] = tuple(out[key])
        return cls(**out)

    def with_changes(self, **changes) -> AblatePreset:
        return dataclasses.replace(self, **changes)

    def with_seeds(self, seeds: Sequence[int] | None) -> AblatePreset:
        """This preset planned over its own seeds and `seeds` too (`run --seeds`, which
        chooses what trains now, never what the tables are made of)."""
        if not seeds:
            return self
        return self.with_changes(seeds=tuple(sorted({*self.seeds, *map(int, seeds)})))

    def data_edits(self) -> dict[str, Any]:
        """The `DataConfig` edits that record this preset's dataset in every config."""
        return {
            "data": {
                "source": "procedural",
                "categories": self.categories,
                "test_inter_categories": self.test_inter,
                "instances_per_category": self.per_category,
                "target_vertices": (self.min_vertices + self.max_vertices) // 2,
                "test_fraction": self.intra_fraction,
                "seed": self.data_seed,
            }
        }


_SMOKE_TRAIN = {
    "steps": 2,
    "batch_size": 1,
    "eval_every": 0,
    "ckpt_every": 0,
    "ckpt_keep": 1,
    "log_every": 1,
}

# The cpu preset's schedule; its step count is sized for `make ablate` in <= 3 h on two
# free cores (docs/ablations.md: how the estimate was made).
_CPU_TRAIN = {
    "steps": 1000,
    "batch_size": 2,
    "lr": 5e-4,
    "schedule": "cosine",
    "warmup_steps": 50,
    "eval_every": 0,
    "ckpt_every": 100,
    "ckpt_keep": 1,
    "log_every": 10,
}
# `make ablate-quick`: the two studies the paper lacks and two of its own, 6 distinct
# trainings, at fewer steps (<= 20 min on two free cores).
_QUICK_STEPS = 300
_QUICK_STUDIES = ("encoding", "head", "attention", "stn")
# The cpu-offset preset: the offset head needs 3x the cpu preset's steps to beat Taubin.
_OFFSET_STEPS = 3000

_CPU = AblatePreset(
    name="cpu",
    base="small",
    edits={
        "name": "ablate-cpu",
        # The recipe the recorded rows were trained with; the head study has a row
        # with the bundled model's Taubin candidates.
        "model": {"width": 32, "stn_width": 16, "taubin_iterations": 0},
        "loss": {"feature_curvature": "asinh"},
        "train": _CPU_TRAIN,
    },
    study_edits={},
    categories=None,
    test_inter=DEFAULT_TEST_INTER,
    per_category=6,
    # Two meshes of 322-383 vertices pad to the 768 bucket, one to 384: one compiled
    # train step and one predictor per config (the seeds of a row share both).
    min_vertices=322,
    max_vertices=383,
    eval_meshes=None,
    seeds=(0, 1, 2),
    workers=2,
    dataset_workers=2,
    description=(
        f"CPU sweep: width 32, {_CPU_TRAIN['steps']} steps of batch 2 (lr 5e-4, cosine), "
        "3 seeds per row trained together, 80 training meshes of 322-383 vertices, all "
        "34 test meshes"
    ),
)

PRESETS: dict[str, AblatePreset] = {
    "test": AblatePreset(
        name="test",
        base="test",
        edits={
            "name": "ablate-test",
            # One aggregator per stream and per dense block, not 3: no study varies them,
            # and each compiles into every program (25 % less compile per model).
            "model": {"n_agg": 1, "dense_layers": 1},
            "loss": {"feature_curvature": "asinh"},
            "train": _SMOKE_TRAIN,
        },
        study_edits={},
        # One mesh size: every batch (batch size 1) and every test mesh pads to the same
        # 160-vertex bucket, so each config compiles one train step and one predictor.
        categories=("extrusion", "torus", "blob", "bottle"),
        test_inter=("bottle",),
        per_category=2,
        min_vertices=130,
        max_vertices=158,
        eval_meshes=1,
        xla_opt_level=0,
        workers=2,
        dataset_workers=1,
        description=(
            "smoke sweep: width 8, one aggregator per stream and dense block, 2 steps per "
            "run, 1 test mesh per split"
        ),
    ),
    "cpu": _CPU,
    "cpu-quick": _CPU.with_changes(
        name="cpu-quick",
        edits={**_CPU.edits, "train": {**_CPU_TRAIN, "steps": _QUICK_STEPS, "warmup_steps": 25}},
        # The first 8 meshes of each test split: 16 meshes x 3 seeds per interval.
        eval_meshes=8,
        dataset="cpu",  # the cpu preset's dataset and calibration, generated once
        studies=_QUICK_STUDIES,
        description=(
            f"first look: the cpu preset at {_QUICK_STEPS} steps, studies "
            f"{', '.join(_QUICK_STUDIES)}, 3 seeds per row, 8 test meshes per split"
        ),
    ),
    # The second base recipe (issue 32): the network carries the denoising. The cpu
    # preset's normal-first head averages fixed pre-filtered normals before any training
    # (its untrained base already removes 70 % of the error), so rows that change only
    # the network differ by tenths of a degree; here the direct-offset head starts as the
    # identity, so everything it removes is learnt. 3,000 steps at lr 1e-3: one seed of
    # its FGT-8 row scored 9.74 / 8.61 degrees (test-intra / test-inter) against
    # Taubin's 11.61 / 9.11; 2,000 steps at 1e-3 or 2e-3 gave 10.2 / 9.7, 1,000 steps at
    # 5e-4 (the cpu head study's offset row) 11.1 / 10.3 (docs/ablations.md).
    "cpu-offset": _CPU.with_changes(
        name="cpu-offset",
        edits={
            **_CPU.edits,
            "name": "ablate-cpu-offset",
            "model": {**_CPU.edits["model"], "head": "offset"},
            "train": {**_CPU_TRAIN, "steps": _OFFSET_STEPS, "lr": 1e-3},
        },
        seeds=(0, 1, 2, 3, 4),
        seeds_together=1,
        dataset="cpu",  # the cpu preset's dataset and calibration: the same test meshes
        description=(
            f"network-does-the-work sweep: the cpu preset with the direct-offset head, "
            f"{_OFFSET_STEPS} steps of batch 2 (lr 1e-3, cosine), 5 seeds per row one after "
            "the other, the cpu preset's meshes"
        ),
    ),
    # The whole sweep on one GPU in about an hour: the paper's architecture at width 128,
    # 1,200 steps (depth rows 4,000), 3 seeds; the sizing is in `dmd_jax.config.presets._gpu`.
    "gpu": AblatePreset(
        name="gpu",
        base="gpu",
        edits={"name": "ablate-gpu"},
        # The paper trains the depth variants for 200 epochs, the others for 60.
        study_edits={"depth": {"train": {"steps": 4000}}},
        categories=None,
        test_inter=DEFAULT_TEST_INTER,
        per_category=12,
        # Four meshes of 900-1,000 vertices pad to one 4,096-vertex bucket.
        min_vertices=900,
        max_vertices=1000,
        eval_meshes=None,
        seeds=(0, 1, 2),
        workers=2,
        dataset_workers=None,
        description=(
            "one GPU, about an hour: width 128, 1,200 steps of batch 4 (depth study "
            "4,000), 3 seeds per row trained together, 12 shapes per category of "
            "900-1,000 vertices"
        ),
    ),
    "paper": AblatePreset(
        name="paper",
        base="paper",
        edits={
            "name": "ablate-paper",
            "loss": {"feature_curvature": "asinh"},
            "train": {"steps": 150_000, "eval_every": 5000, "ckpt_every": 5000},
        },
        # The paper trains the depth variants for 200 epochs, the others for 60.
        study_edits={"depth": {"train": {"steps": 500_000}}},
        categories=None,
        test_inter=DEFAULT_TEST_INTER,
        per_category=40,
        min_vertices=1000,
        max_vertices=6000,
        eval_meshes=None,
        workers=1,
        dataset_workers=None,
        description="the paper's width (512) and epochs, procedural data at 40 per category",
    ),
}


def get_preset(name: str) -> AblatePreset:
    if name not in PRESETS:
        raise ValueError(f"unknown ablation preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]


# --------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------


class RunSpec(NamedTuple):
    """One run: a study row at a seed, the config it trains and the evaluation it gets."""

    study: str
    row: str
    seed: int
    config: ExperimentConfig
    evaluation: dict  # {"kind": "test" | "noise" | "rotation", ...}
    train_hash: str
    run_id: str


def slug(text: str) -> str:
    """A readable directory-name fragment: `"W/O T"` -> `"w_o_t"`, `"Dr=0.35"` -> `"dr_0.35"`."""
    text = text.replace("·", "x").replace("−", "-").replace("Γ", "gamma").replace("δ", "delta")
    text = text.replace("+", "plus")
    out = re.sub(r"[^a-z0-9.\-]+", "_", text.lower()).strip("_")
    return out or "run"


def _digest(payload: Any, length: int = 10) -> str:
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:length]


# Model switches added after results were recorded, at the value that leaves the model as
# it was: left out of the hashes, so finished runs keep their ids and are not retrained.
_LATER_MODEL_FIELDS = {
    "head_consistency": False,
    "taubin_iterations": 0,
    "filter_sigmas": [0.2, 0.35, 0.6],  # as `to_dict` writes the default tuple
    "pass_tolerance": 0.0,
    "presmooth_start": 0.0,
    "presmooth_per_step": 5.0,
    "vertex_update": "jacobi",
    "vertex_tolerance": 1e-4,
    "vertex_max_iterations": 200,
    "vertex_normal_weight": 1e-3,
    "vertex_tangent_weight": 0.03,
}


# Data and training settings added later (what `train.train_and_evaluate` reads), at the
# value that leaves a run as it was: left out of the hashes for the same reason.
_LATER_FIELDS = {
    "data": {
        "dataset_dir": None,
        "eval_meshes_per_split": 8,
        "real_root": None,
        "real_patch_faces": 6000,
        "real_faces_per_patch": 12000,
        "real_patches_per_mesh": 8,
        "real_val_patch_faces": 4000,
        "real_val_patches_per_mesh": 1,
        "real_coarse_faces": [],
        "stress_copies": 0,
        "scan_views": 0,
        "scan_resolution": 64,
    },
    "train": {"init_from": None, "candidate_pool": 0, "candidate_uses": 4},
    "loss": {"crease_weight": 1.0},
    "noise": {"p_scanner": 0.0, "scanner_levels": None},
}


# Fields added without a `_LATER_FIELDS` entry, so that runs recorded before them carry
# hashes without them: `train.passes` (2026-12-02), absent from every run of the cpu,
# cpu-quick and cpu-recipe sweeps and present in the cpu-offset sweep's. `plan` with a
# results directory finds such runs under their recorded ids (`recorded_hashes`).
_FIELDS_ADDED_UNHASHED = ({"train": {"passes": 1}},)


def _hashed(cfg: ExperimentConfig, drop: Mapping[str, Mapping[str, Any]] | None = None) -> dict:
    data = cfg.to_dict()
    data.pop("name", None)
    model = data["model"]
    for key, value in _LATER_MODEL_FIELDS.items():
        if model.get(key) == value:
            model.pop(key)
    for section, fields in _LATER_FIELDS.items():
        for key, value in fields.items():
            if data[section].get(key, value) == value:
                data[section].pop(key, None)
    for section, fields in (drop or {}).items():
        for key, value in fields.items():
            if data[section].get(key, value) == value:
                data[section].pop(key, None)
    return data


def _older_hashed(cfg: ExperimentConfig) -> list[dict]:
    """`_hashed` as it was before each field of `_FIELDS_ADDED_UNHASHED`, newest first."""
    out, drop = [], {}
    for fields in reversed(_FIELDS_ADDED_UNHASHED):
        for section, values in fields.items():
            drop[section] = {**drop.get(section, {}), **values}
        older = _hashed(cfg, drop)
        if older != _hashed(cfg) and older not in out:
            out.append(older)
    return out


def config_hash(cfg: ExperimentConfig) -> str:
    """Hash of a config's JSON without its `name`: equal settings, equal hash."""
    return _digest(_hashed(cfg))


def run_hash(cfg: ExperimentConfig, evaluation: Mapping[str, Any]) -> str:
    return _digest({"config": _hashed(cfg), "evaluation": dict(evaluation)})


def base_config(p: AblatePreset, gammas: Mapping[str, float] | None = None) -> ExperimentConfig:
    """The preset's base config: the `dmd_jax` preset, the edits, the dataset and γ."""
    cfg = preset(p.base).with_edits(dict(p.edits)).with_edits(p.data_edits())
    if gammas is not None:
        cfg = cfg.with_edits(
            {"loss": {"gamma_h": float(gammas["gamma_h"]), "gamma_g": float(gammas["gamma_g"])}}
        )
    return cfg


def _with_name(cfg: ExperimentConfig, base: ExperimentConfig, study: str, row: str):
    return cfg.with_edits({"name": f"{base.name}-{study}-{slug(row)}"})


def study_configs(p: AblatePreset, base: ExperimentConfig, study: str) -> list[tuple[str, Any]]:
    """`(row, config)` pairs of one study before seeds (the noise study: one config)."""
    s = get_study(study)
    extra = dict(p.study_edits.get(study, {}))
    if s.kind == TRAIN:
        out = [(row, ablation_config(base, study, row)) for row in s.rows]
    elif s.kind == NOISE:
        out = [(NOISE_MODEL_ROW, _with_name(base, base, study, "model"))]
    else:
        out = [
            (row, _with_name(base.with_edits(ROTATION_ROWS[row]), base, study, row))
            for row in s.rows
        ]
    out = [(row, cfg.with_edits(extra) if extra else cfg) for row, cfg in out]
    # DO-2S and DO-1S have no feature extractor, so the FE loss has nothing to act on:
    # its weight goes to 0 (ABLATIONS keeps λ_FE = 1 in every row, which the loss refuses
    # without extractor output).
    return [
        (
            row,
            cfg if cfg.model.uses_feature_extractor else cfg.with_edits({"loss": {"feature": 0.0}}),
        )
        for row, cfg in out
    ]


def _evaluation(p: AblatePreset, kind: str, **extra) -> dict[str, Any]:
    return {"kind": kind, "eval_meshes": p.eval_meshes, **extra}


def plan(
    p: AblatePreset,
    base: ExperimentConfig,
    studies: Sequence[str] | None = None,
    out_dir: Path | str | None = None,
) -> list[RunSpec]:
    """Every run of the chosen studies (default: all), in study, row, seed order.

    With `out_dir` (the sweep's results directory), a run recorded there before a field
    of `_FIELDS_ADDED_UNHASHED` existed keeps its recorded id and training hash
    (`recorded_hashes`), so a rerun finds it finished instead of retraining it.
    """
    keys = STUDY_KEYS if studies is None else tuple(studies)
    for key in keys:
        get_study(key)
    runs: list[RunSpec] = []
    for key in keys:
        s = get_study(key)
        for row, cfg in study_configs(p, base, key):
            for seed in p.seeds:
                c = cfg.with_edits({"train": {"seed": int(seed)}})
                if s.kind == NOISE:
                    evals = [
                        (name, _evaluation(p, "noise", noise_kind=kind, level=level))
                        for kind, level, name in NOISE_ROWS
                    ]
                elif s.kind == ROTATION:
                    evals = [(row, _evaluation(p, "rotation", gamma=RE_GAMMA))]
                else:
                    evals = [(row, _evaluation(p, "test"))]
                for name, ev in evals:
                    runs.append(RunSpec(key, name, int(seed), c, ev, *_ids(p, name, seed, c, ev)))
    return runs if out_dir is None else recorded_hashes(p, runs, Path(out_dir))


def _ids(p: AblatePreset, name: str, seed: int, c: ExperimentConfig, ev: dict, hashed=None):
    """`(train_hash, run_id)` of a run, from `hashed` (default: `_hashed(c)`)."""
    hashed = _hashed(c) if hashed is None else hashed
    h = _digest({"config": hashed, "evaluation": dict(ev)})
    rid = f"{slug(name)}-{h}" if len(p.seeds) == 1 else f"{slug(name)}-s{seed}-{h}"
    return _digest(hashed), rid


def recorded_hashes(p: AblatePreset, runs: Sequence[RunSpec], out_dir: Path) -> list[RunSpec]:
    """`runs` with the ids they were recorded under in `out_dir`.

    A training whose run directory exists only under an older hash (`_older_hashed`)
    takes that training hash for all its runs, and each run its older id where that
    directory exists, so the recorded checkpoints and metrics are found; every other
    run keeps today's ids.
    """
    older: dict[str, list[tuple[dict, str, str]]] = {}  # today's train hash -> its older ids
    for r in runs:
        if (out_dir / r.study / r.run_id).is_dir():
            continue
        for hashed in _older_hashed(r.config):
            train_hash, rid = _ids(p, r.row, r.seed, r.config, r.evaluation, hashed)
            if (out_dir / r.study / rid).is_dir():
                older.setdefault(r.train_hash, []).append((hashed, train_hash, rid))
                break
    if not older:
        return list(runs)
    out = []
    for r in runs:
        if r.train_hash not in older:
            out.append(r)
            continue
        hashed, train_hash, _ = older[r.train_hash][0]
        _, rid = _ids(p, r.row, r.seed, r.config, r.evaluation, hashed)
        if not (out_dir / r.study / rid).is_dir() and (out_dir / r.study / r.run_id).is_dir():
            rid = r.run_id
        out.append(r._replace(train_hash=train_hash, run_id=rid))
    return out


def training_homes(runs: Sequence[RunSpec]) -> dict[str, RunSpec]:
    """For each training hash, the first run that uses it: its directory holds the
    checkpoints, and every other run with that hash reuses the trained model."""
    homes: dict[str, RunSpec] = {}
    for r in runs:
        homes.setdefault(r.train_hash, r)
    return homes
