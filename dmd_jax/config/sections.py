"""The config dataclasses: `ModelConfig`, `LossConfig`, `TrainConfig`, `NoiseConfig`,
`DataConfig` and the `ExperimentConfig` that nests them, with their validation.

Every field is static metadata (`_static`, `pytree_node=False`), so a config is a pytree
with no leaves and can be a static argument of `jax.jit`. Each class checks its fields
in `__post_init__` (a bad value raises `ValueError` naming the field); the JSON codec is
`dmd_jax.config.codec`, the presets `dmd_jax.config.presets`.
"""

from __future__ import annotations

import math
from typing import Any

import dmd_jax.config.frozen as frozen
from dmd_jax.config.codec import _ConfigMixin
from dmd_jax.constants import (
    ENCODINGS,
    FILTER_RANGE_SIGMAS,
    NOISE_KINDS,
    PAPER_NOISE_KINDS,
    local_dims,
)

VARIANT_NAMES = ("fgt8", "fgt3", "wo_t", "mt", "do_2s", "do_1s", "fgt_1s")
SCHEMES = ("joint", "alter", "two_phase", "u_fe")
SCHEDULES = ("constant", "cosine")
# Network passes a training step may unroll (`TrainConfig.passes`): each costs a forward
# and backward pass of the whole batch.
MAX_TRAIN_PASSES = 8
DTYPES = ("float32", "float64")
HEADS = ("offset", "normal")
# How the normal-first head moves the vertices onto its normals (`ModelConfig.vertex_update`).
VERTEX_UPDATES = ("jacobi", "solve")
# How the feature extractor's curvature targets are expressed: the paper's raw values, or
# asinh(κ), which keeps the heavy tail of κ at sharp edges (1e3–1e5 in the canonical
# frame) from swamping the loss while staying monotone and exact near zero.
FEATURE_CURVATURES = ("raw", "asinh")
DATA_SOURCES = ("procedural", "folder")


def _static(default: Any):
    """A structural (non-pytree) field: part of the treedef, never traced."""
    return frozen.field(pytree_node=False, default=default)


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _check_choice(name: str, value: Any, choices: tuple) -> None:
    _check(value in choices, f"{name} must be one of {choices}, got {value!r}")


def _check_positive_int(name: str, value: Any, *, minimum: int = 1) -> None:
    _check(
        isinstance(value, int) and not isinstance(value, bool) and value >= minimum,
        f"{name} must be an integer >= {minimum}, got {value!r}",
    )


def _check_path(name: str, value: Any) -> None:
    """None, or a non-empty string (a file or folder named in a config)."""
    _check(
        value is None or (isinstance(value, str) and value != ""),
        f"{name} must be a path or null, got {value!r}",
    )


def _check_finite(name: str, value: Any, *, positive: bool = False) -> None:
    """A finite real number (not a bool), >= 0, or > 0 with `positive`."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    _check(
        ok and (value > 0 if positive else value >= 0),
        f"{name} must be a finite number {'> 0' if positive else '>= 0'}, got {value!r}",
    )


# --------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------


# ModelConfig fields of configs saved before 2026-12-02 that now live in
# `dmd_jax.policy.DenoisePolicy` (`policy.from_legacy_model_fields`).
LEGACY_POLICY_FIELDS = ("pass_tolerance", "presmooth_start", "presmooth_per_step")


# Upper bounds on every count a model config carries. A weights file is untrusted input
# and each of these multiplies the work of one denoise (`filter_iterations = 10**7` ran
# for ever): the bounds sit far above any trained model (the bundled one: width 32,
# 120 filter passes, 10 Taubin pairs, 10 vertex iterations; the paper's width 512).
MODEL_COUNT_LIMITS = {
    "width": 4096,
    "fe_two_streams": 16,
    "depth": 16,
    "transformer_width": 4096,
    "n_agg": 16,
    "dense_layers": 16,
    "mt_transforms": 16,
    "stn_width": 4096,
    "vertex_iterations": 1000,
    "vertex_max_iterations": 10000,
    "filter_iterations": 1000,
    "taubin_iterations": 1000,
}
# A bilateral filter's range σ acts on differences of unit normals (0 to 2): below 0.01
# every weight but a face's own underflows (1e-300 divided by zero), above 10 the
# filter is a plain average.
FILTER_SIGMA_RANGE = (0.01, 10.0)
MAX_FILTERS = 16
MAX_HEAD_INIT_SCALE = 100.0


@frozen.dataclass
class ModelConfig(_ConfigMixin):
    """DMD-Net structure. All fields are static (they decide shapes and code paths).

    Only what defines the network and its parameters: how `denoise` uses a trained
    network (pre-smoothing, passes, relaxation) is a `dmd_jax.policy.DenoisePolicy`,
    stored beside the config in a weights file. `vertex_iterations` and
    `filter_iterations` hold no parameters but are part of the function the network was
    trained as (training differentiates through them), so they stay here.

    Attributes:
      width: hidden width of every two-stream network (paper: 512) and the number of
        columns of the transformation `W_tf`.
      fe_two_streams: two-stream networks in the feature extractor (paper: 2).
      depth: two-stream networks in the denoiser (paper's depth ablation: best 2).
      transformer_width: hidden width inside the transformer; `None` means `width`.
      variant: structure ablation variant, one of `VARIANT_NAMES`: `fgt8` (the paper's
        model), `fgt3`, `wo_t`, `mt`, `do_2s`, `do_1s`, `fgt_1s`.
      n_agg: aggregators per stream in a two-stream network (paper: 3).
      dense_layers: densely connected aggregators in the transformer before its last AGG.
      mt_transforms: transformations in the cascade of the `mt` variant (>= 2): the
        first `mt_transforms - 1` are `8 x 8` (ReLU after each), the last `8 x width`.
      dropout: dropout rate after every ReLU (paper ablation: 0, 0.2, 0.35, 0.5).
      attention: GAT-style attention coefficients instead of the fixed GCN weights.
      stn: PointNet-style spatial transformer (3 x 3 per mesh) on the input coordinates.
      stn_width: hidden width of the STN's per-vertex MLP (the next layer is twice it).
      predict_offset: the denoiser predicts an offset added to the noisy positions
        (`True`) or the positions themselves.
      pdf_residual: add the primal stream's output to the fused PDF output (our choice;
        see `dmd_jax.model.TwoStream`).
      normalize_fe_normals: the feature extractor's normal part is unit length.
      head_init_scale: variance scale of the denoiser head's initial kernel; 0 (default)
        initialises it to zeros, so an untrained offset model is exactly the identity map
        (the residual stacks grow activations at init, measured rms ≈ 0.8 after the
        first two-stream network and ≈ 60 after the denoiser's last, for both the small
        and paper presets; a random head would start with offsets larger than the
        shape).
      dtype: parameter and computation dtype, `"float32"` or `"float64"`.
      encoding: how the network sees a mesh (`dmd_jax.encoding`): `"xyz"` (the paper's
        reading: bounding-box frame, absolute coordinates) or `"local"` (edge-unit
        frame, Laplacian coordinates, normals and pre-filtered normals, face normals on
        the dual stream).
      head: `"offset"` (the denoiser predicts a per-vertex offset, or positions when
        `predict_offset=False`) or `"normal"` (normal-first: the dual stream of the
        denoiser's last two-stream network predicts face normals, and
        `vertex_iterations` of Sun et al.'s normal-driven update move the noisy
        vertices onto them; trained end to end). `"normal"` needs `encoding="local"`.
      vertex_iterations: iterations of the normal-driven vertex update (`head="normal"`,
        `vertex_update="jacobi"`).
      vertex_update: how the normal-first head moves the vertices onto its normals:
        `"jacobi"` (default; every config saved before this field): `vertex_iterations`
        steps of Sun et al.'s update (`geometry.fit_vertices_to_normals`); `"solve"`:
        the regularised least-squares fit solved to `vertex_tolerance`
        (`vertex_update.solve_vertices_to_normals`, implicit differentiation).
      vertex_tolerance: `"solve"`: stop when the preconditioned residual has fallen by
        this factor.
      vertex_max_iterations: `"solve"`: at most this many conjugate-gradient iterations.
      vertex_normal_weight, vertex_tangent_weight: `"solve"`: the hold toward the start
        along the vertex normal and in the tangent plane (`μ_n`, `μ_t` of
        `dmd_jax.vertex_update`).
      filter_iterations: passes of the longest bilateral pre-filter run of the `"local"`
        encoding (fields are also kept after 2/15 and 1/2 of it:
        `encoding.snapshot_passes`).
      head_consistency: the normal-first head also sees, per candidate normal, how
        smooth it is over the face's neighbours and how far it is from the noisy normal
        (`encoding.candidate_consistency`), through its own zero-initialised Dense layer
        (so weights trained without it load with the same outputs).
      taubin_iterations: λ|μ pairs of Taubin smoothing whose results (kept after 3/10
        of them and after all) add candidate normals and vertex displacements to the
        `"local"` encoding (`encoding.taubin_snapshots`); 0 (default) adds none. Like
        `filter_iterations`, ignored by the `"xyz"` encoding (so a `small`-derived config
        can switch to `"xyz"` with one edit).
      filter_sigmas: the range σ of each bilateral pre-filter of the `"local"` encoding,
        one filter (and `len(encoding.FILTER_SNAPSHOTS)` candidates) each; the filters'
        passes are most of the encoding's cost (about 2.3 ms a pass at 100k faces on 2
        CPU cores), so fewer filters buy speed.
    """

    width: int = _static(64)
    fe_two_streams: int = _static(2)
    depth: int = _static(2)
    transformer_width: int | None = _static(None)
    variant: str = _static("fgt8")
    n_agg: int = _static(3)
    dense_layers: int = _static(3)
    mt_transforms: int = _static(2)
    dropout: float = _static(0.0)
    attention: bool = _static(False)
    stn: bool = _static(False)
    stn_width: int = _static(64)
    predict_offset: bool = _static(True)
    pdf_residual: bool = _static(True)
    normalize_fe_normals: bool = _static(True)
    head_init_scale: float = _static(0.0)
    dtype: str = _static("float32")
    encoding: str = _static("xyz")
    head: str = _static("offset")
    vertex_iterations: int = _static(10)
    vertex_update: str = _static("jacobi")
    vertex_tolerance: float = _static(1e-4)
    vertex_max_iterations: int = _static(200)
    vertex_normal_weight: float = _static(1e-3)
    vertex_tangent_weight: float = _static(0.03)
    filter_iterations: int = _static(60)
    head_consistency: bool = _static(False)
    taubin_iterations: int = _static(0)
    filter_sigmas: tuple[float, ...] = _static(FILTER_RANGE_SIGMAS)

    @classmethod
    def from_dict(cls, data: dict[str, Any]):
        """`_ConfigMixin.from_dict`, dropping the policy fields of configs saved before the
        policy had its own home (`LEGACY_POLICY_FIELDS`; every such config carries them,
        most at their defaults). A weights file's non-default values were moved to its
        policy by `dmd_jax.checkpoints` before this is called."""
        if isinstance(data, dict):
            data = {k: v for k, v in data.items() if k not in LEGACY_POLICY_FIELDS}
        return super().from_dict(data)

    def __post_init__(self):
        _check_positive_int("width", self.width)
        _check_positive_int("fe_two_streams", self.fe_two_streams)
        _check_positive_int("depth", self.depth)
        if self.transformer_width is not None:
            _check_positive_int("transformer_width", self.transformer_width)
        _check_choice("variant", self.variant, VARIANT_NAMES)
        _check_positive_int("n_agg", self.n_agg)
        _check_positive_int("dense_layers", self.dense_layers, minimum=0)
        _check_positive_int("mt_transforms", self.mt_transforms, minimum=2)
        _check(
            isinstance(self.dropout, int | float) and 0.0 <= self.dropout < 1.0,
            f"dropout must lie in [0, 1), got {self.dropout!r}",
        )
        _check_positive_int("stn_width", self.stn_width)
        _check(
            isinstance(self.head_init_scale, int | float) and self.head_init_scale >= 0,
            f"head_init_scale must be >= 0, got {self.head_init_scale!r}",
        )
        _check_choice("dtype", self.dtype, DTYPES)
        _check_choice("encoding", self.encoding, ENCODINGS)
        _check_choice("head", self.head, HEADS)
        _check(
            self.head == "offset" or self.encoding == "local",
            "head='normal' needs encoding='local' (it mixes the pre-filtered face normals)",
        )
        _check_positive_int("vertex_iterations", self.vertex_iterations)
        _check_choice("vertex_update", self.vertex_update, VERTEX_UPDATES)
        _check_positive_int("vertex_max_iterations", self.vertex_max_iterations)
        for name in ("vertex_tolerance", "vertex_normal_weight", "vertex_tangent_weight"):
            value = getattr(self, name)
            _check(
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
                and 0 < value <= 1,
                f"{name} must be a number in (0, 1], got {value!r}",
            )
        _check_positive_int("filter_iterations", self.filter_iterations)
        _check_positive_int("taubin_iterations", self.taubin_iterations, minimum=0)
        _check(
            len(self.filter_sigmas) > 0
            and all(isinstance(s, int | float) and s > 0 for s in self.filter_sigmas),
            f"filter_sigmas must be a non-empty tuple of positive numbers, "
            f"got {self.filter_sigmas!r}",
        )
        _check(
            not self.head_consistency or self.head == "normal",
            "head_consistency needs head='normal' (it describes the candidate normals)",
        )
        for name, most in MODEL_COUNT_LIMITS.items():
            value = getattr(self, name)
            _check(
                value is None or value <= most,
                f"{name} must be at most {most:,}, got {value!r} (a bound on the work one "
                "denoise may take)",
            )
        low, high = FILTER_SIGMA_RANGE
        _check(
            len(self.filter_sigmas) <= MAX_FILTERS
            and all(
                not isinstance(s, bool) and math.isfinite(s) and low <= s <= high
                for s in self.filter_sigmas
            ),
            f"filter_sigmas must be at most {MAX_FILTERS} numbers in [{low:g}, {high:g}] "
            f"(range σ of unit-normal differences), got {self.filter_sigmas!r}",
        )
        _check(
            math.isfinite(self.head_init_scale) and self.head_init_scale <= MAX_HEAD_INIT_SCALE,
            f"head_init_scale must be a finite number <= {MAX_HEAD_INIT_SCALE:g}, "
            f"got {self.head_init_scale!r}",
        )

    # Derived structure, one place for every variant's switches.
    @property
    def uses_feature_extractor(self) -> bool:
        return self.variant not in ("do_2s", "do_1s")

    @property
    def uses_transformer(self) -> bool:
        return self.variant in ("fgt8", "fgt3", "mt", "fgt_1s")

    @property
    def fe_two_stream(self) -> bool:
        return self.variant != "fgt_1s"

    @property
    def denoiser_two_stream(self) -> bool:
        return self.variant not in ("do_1s", "fgt_1s")

    @property
    def vertex_in_dim(self) -> int:
        """Columns of the primal input: 3 (xyz) or `encoding.local_dims(...)[0]` (local)."""
        if self.encoding == "xyz":
            return 3
        return local_dims(self.taubin_iterations, self.filter_sigmas)[0]

    @property
    def transform_in_dim(self) -> int:
        """Rows of `W_tf`: the primal input plus the 5 features (8 for the paper's
        `[xyz ‖ features]`), or the primal input alone (FGT-3)."""
        return self.vertex_in_dim + (0 if self.variant == "fgt3" else 5)

    @property
    def n_transforms(self) -> int:
        return self.mt_transforms if self.variant == "mt" else 1

    @property
    def hidden_transformer_width(self) -> int:
        return self.width if self.transformer_width is None else self.transformer_width


# --------------------------------------------------------------------------------------
# Loss, training, noise, data
# --------------------------------------------------------------------------------------


@frozen.dataclass
class LossConfig(_ConfigMixin):
    """Loss weights (the paper's final values) and curvature scales (all static).

    Attributes:
      vertex, normal, curvature, chamfer, feature: the weights λ_V, λ_N, λ_κ, λ_C, λ_FE.
      gamma_h, gamma_g: γ_H and γ_G of the curvature loss (paper appendix C).
      chamfer_block: rows per block of the blockwise chamfer distance.
      feature_curvature: `raw` (paper) or `asinh`: the feature extractor learns
        `asinh(κ_H)`, `asinh(κ_G)` instead of the raw curvatures.
      face_normal: weight of the normal-first head's own face-normal error (radians,
        `losses.predicted_normal_loss`); read only by models with `head="normal"`.
      crease_weight: how much a crease face (an edge of dihedral angle at least
        `constants.CREASE_ANGLE` on the clean mesh, `losses.crease_face_mask`) counts in
        the normal and face-normal terms against any other face: feature-balanced
        training for CAD parts, whose few crease faces a plain mean drowns in their
        flats. 1: every face alike (the terms' plain means).
    """

    vertex: float = _static(1.0)
    normal: float = _static(0.2)
    curvature: float = _static(0.01)
    chamfer: float = _static(0.05)
    feature: float = _static(1.0)
    gamma_h: float = _static(1e-6)
    gamma_g: float = _static(1.0)
    chamfer_block: int = _static(1024)
    feature_curvature: str = _static("raw")
    face_normal: float = _static(0.0)
    crease_weight: float = _static(1.0)

    def __post_init__(self):
        _check_choice("feature_curvature", self.feature_curvature, FEATURE_CURVATURES)
        _check(
            isinstance(self.crease_weight, int | float) and 0.0 < self.crease_weight < 1e3,
            f"crease_weight must be a number in (0, 1000), got {self.crease_weight!r}",
        )
        for name in ("vertex", "normal", "curvature", "chamfer", "feature", "face_normal"):
            value = getattr(self, name)
            _check(
                isinstance(value, int | float) and 0.0 <= value < float("inf"),
                f"loss weight {name} must be a finite number >= 0, got {value!r}",
            )
        _check(self.gamma_h > 0 and self.gamma_g > 0, "gamma_h and gamma_g must be > 0")
        _check_positive_int("chamfer_block", self.chamfer_block)

    @classmethod
    def all_ones(cls, **kwargs) -> LossConfig:
        """The weights the paper's ablation studies use: every λ = 1."""
        return cls(vertex=1.0, normal=1.0, curvature=1.0, chamfer=1.0, feature=1.0, **kwargs)


@frozen.dataclass
class TrainConfig(_ConfigMixin):
    """Optimiser, schedule and training scheme (all static).

    Attributes:
      lr, b1, b2, eps: Adam (paper: lr 1e-4, β1 0.9, β2 0.999).
      schedule: `constant`, or `cosine`: linear warm-up over `warmup_steps` (0: none),
        then cosine decay to `lr * min_lr_ratio` at `steps`.
      warmup_steps: linear warm-up steps of `cosine`.
      min_lr_ratio: final learning rate of `cosine` as a fraction of `lr`.
      grad_clip: global-norm gradient clipping; 0 turns it off (the paper is silent; we
        clip at 1 so one impulse-noise outlier batch cannot blow up Adam's moments).
      steps: optimiser steps.
      batch_size: meshes per step.
      scheme: `joint`, `alter`, `two_phase` or `u_fe` (paper's training scheme ablation).
      alter_period: steps per half-cycle of `alter` (paper: 1, odd/even iterations).
      two_phase_split: fraction of `steps` spent pre-training the feature extractor in
        `two_phase` (the paper says "several epochs").
      eval_every, ckpt_every, log_every: intervals in steps; 0 turns one off.
      ckpt_keep: checkpoints kept on disk.
      rotate: random rotation augmentation (the paper's route to rotation equivariance).
      seed: seed of parameter init, shuffling and noise.
      init_from: a checkpoint directory or weights file a fine-tune starts from
        (`train.init_params_from`: the same parameter shapes, or a grafted
        `head_consistency` input); the optimizer starts fresh. None: a fresh init. A run
        that resumes from its own checkpoint ignores it.
      passes: network passes unrolled per training mesh (a weight-shared cascade): pass
        `k + 1` starts from pass `k`'s output, with no gradient through that input, and
        every pass's output is scored against the clean mesh (the loss averages the
        passes' terms). So the network learns to denoise its own output too, and the
        pass count `denoise` runs is a trained setting (`DenoisePolicy.max_passes`),
        not a fitted threshold. Evaluation during training runs the same passes. At
        most `MAX_TRAIN_PASSES`.
      candidate_pool: noisy draws kept per training mesh whose `"local"` encoding inputs
        (the candidate normal fields, `encoding.LocalInputs`) are computed once, outside
        the step, instead of in every step (`pipeline.CandidatePool`); 0 (the default):
        every batch is drawn and encoded afresh (`pipeline.training_batch`). Batches
        stay a function of `(seed, step)`; each use of a draw gets its own rotation.
      candidate_uses: with a pool, how many times each cached draw is trained on (once
        per visit of its mesh, `candidate_pool` visits apart) before it is replaced by
        a fresh draw; the encoding's cost per step falls about this many times.
    """

    lr: float = _static(1e-4)
    b1: float = _static(0.9)
    b2: float = _static(0.999)
    eps: float = _static(1e-8)
    schedule: str = _static("constant")
    warmup_steps: int = _static(0)
    min_lr_ratio: float = _static(0.05)
    grad_clip: float = _static(1.0)
    steps: int = _static(10_000)
    batch_size: int = _static(4)
    scheme: str = _static("joint")
    alter_period: int = _static(1)
    two_phase_split: float = _static(0.5)
    eval_every: int = _static(1000)
    ckpt_every: int = _static(1000)
    ckpt_keep: int = _static(3)
    log_every: int = _static(100)
    rotate: bool = _static(True)
    seed: int = _static(0)
    init_from: str | None = _static(None)
    passes: int = _static(1)
    candidate_pool: int = _static(0)
    candidate_uses: int = _static(4)

    @property
    def learning_rate(self) -> float:
        """Alias of `lr`."""
        return self.lr

    @property
    def two_phase_fe_steps(self) -> int:
        """Steps of the feature-extractor pre-training phase of `two_phase`."""
        return max(1, min(self.steps - 1, round(self.steps * self.two_phase_split)))

    def __post_init__(self):
        _check(self.lr > 0, f"lr must be > 0, got {self.lr}")
        _check(0 <= self.b1 < 1 and 0 <= self.b2 < 1, "b1 and b2 must lie in [0, 1)")
        _check(self.eps > 0, f"eps must be > 0, got {self.eps}")
        _check_choice("schedule", self.schedule, SCHEDULES)
        _check_positive_int("warmup_steps", self.warmup_steps, minimum=0)
        _check(0.0 <= self.min_lr_ratio <= 1.0, "min_lr_ratio must lie in [0, 1]")
        _check(self.grad_clip >= 0, f"grad_clip must be >= 0, got {self.grad_clip}")
        _check_positive_int("steps", self.steps)
        _check_positive_int("batch_size", self.batch_size)
        _check_choice("scheme", self.scheme, SCHEMES)
        _check_positive_int("alter_period", self.alter_period)
        _check(0.0 < self.two_phase_split < 1.0, "two_phase_split must lie in (0, 1)")
        for name in ("eval_every", "ckpt_every", "log_every"):
            _check_positive_int(name, getattr(self, name), minimum=0)
        _check_positive_int("ckpt_keep", self.ckpt_keep)
        _check_positive_int("seed", self.seed, minimum=0)
        _check_path("init_from", self.init_from)
        _check_positive_int("passes", self.passes)
        _check_positive_int("candidate_pool", self.candidate_pool, minimum=0)
        _check_positive_int("candidate_uses", self.candidate_uses)
        _check(
            self.passes <= MAX_TRAIN_PASSES,
            f"passes must be at most {MAX_TRAIN_PASSES}, got {self.passes}",
        )


@frozen.dataclass
class NoiseConfig(_ConfigMixin):
    """What the mixed-noise sampler draws during training (all static).

    Attributes:
      kinds: noise types drawn uniformly per mesh.
      canonical_levels: `((kind, (level, ...)), ...)` levels in the canonical frame;
        `None` takes the paper's five levels per type from `dmd_jax.noise`.
      edge_levels: levels relative to the mean edge length; `None` takes the defaults of
        `dmd_jax.noise`.
      p_edge: probability that a mesh gets an edge-relative level instead of a
        canonical-frame one.
      p_normal: probability that an edge-relative draw is along the vertex normals (the
        benchmark protocol) instead of per coordinate.
      p_clean: probability of a clean input (level 0).
      p_scanner: probability that a mesh gets the scanner kind (`noise.ScannerModel`:
        depth-sensor noise along a drawn view) instead of a draw from `kinds`.
      scanner_levels: the scanner kind's levels in mean edge lengths; `None` takes
        `noise.SCANNER_LEVELS`.
    """

    kinds: tuple[str, ...] = _static(PAPER_NOISE_KINDS)
    canonical_levels: tuple[tuple[str, tuple[float, ...]], ...] | None = _static(None)
    edge_levels: tuple[float, ...] | None = _static(None)
    p_edge: float = _static(0.5)
    p_normal: float = _static(0.0)
    p_clean: float = _static(0.0)
    p_scanner: float = _static(0.0)
    scanner_levels: tuple[float, ...] | None = _static(None)

    def __post_init__(self):
        _check(len(self.kinds) > 0, "noise kinds must not be empty")
        for kind in self.kinds:
            _check_choice("noise kind", kind, NOISE_KINDS)
        if self.canonical_levels is not None:
            for kind, levels in self.canonical_levels:
                _check_choice("noise kind", kind, NOISE_KINDS)
                _check(len(levels) > 0 and all(x > 0 for x in levels), "levels must be > 0")
        if self.edge_levels is not None:
            _check(all(x > 0 for x in self.edge_levels), "edge levels must be > 0")
        if self.scanner_levels is not None:
            _check(
                len(self.scanner_levels) > 0 and all(x > 0 for x in self.scanner_levels),
                "scanner levels must be > 0",
            )
        for name in ("p_edge", "p_normal", "p_clean", "p_scanner"):
            value = getattr(self, name)
            _check(0.0 <= value <= 1.0, f"{name} must lie in [0, 1], got {value}")


@frozen.dataclass
class DataConfig(_ConfigMixin):
    """Where the training meshes come from, how they are split, what is evaluated.

    The first group records how a dataset was made (the ablation runs fill it in); the
    rest is what `train.train_and_evaluate` reads to assemble a run's training and
    evaluation sets (`dmd_jax.data.training_sets`). All static.

    Attributes:
      source: `procedural` (the built-in shape categories) or `folder` (category/*.obj).
      root: the folder for `source="folder"`.
      categories: categories to use; `None` means all.
      test_inter_categories: categories held out entirely (the paper's test-inter).
      instances_per_category: procedural shapes generated per category.
      target_vertices: vertex count procedural shapes are remeshed to.
      test_fraction: fraction of each training category's instances kept for test-intra.
      seed: seed of the generator and of the split.
      dataset_dir: a dataset directory written by `dmd-jax make-dataset`
        (`data.load_dataset`): training uses its `train` split, evaluation the first
        meshes of its test splits. None: no dataset (`train_and_evaluate` needs one).
      eval_meshes_per_split: meshes of each test split (`test_intra`, `test_inter`)
        evaluated during training, the first of each split; 0: none. (8 of each: a
        third of the `test` preset's one-minute run is evaluation.)
      real_root: a folder of real meshes (e.g. `shared/meshes/train`), or None. Its
        training split (`data.real`) is added to the training set as connected patches;
        its fixed validation split is evaluated as `val`, picks the best checkpoint, and
        every evaluation set then uses the benchmark noise
        (`protocol.benchmark_noise_config()`) instead of the training noise. The
        patches are drawn with `train.seed`.
      real_patch_faces: faces of a training patch at most (a smaller mesh stays whole).
      real_faces_per_patch: a training mesh of `F` faces gives
        `F // real_faces_per_patch + 1` patches, at most `real_patches_per_mesh`.
      real_patches_per_mesh: training patches per real mesh at most.
      real_val_patch_faces: faces of a validation patch at most.
      real_val_patches_per_mesh: validation patches per real mesh at most.
      real_coarse_faces: face counts each real training mesh is also decimated to, whole
        (`data.real.coarse_copies`: coarse tessellations, whose clean faces meet at large
        angles); `()`: none.
      stress_copies: copies of each generated stress shape (`data.stress`: pyramid,
        cube, cone, fan disc, ...) added to the training set (each copy gets its own
        rotation and noise per step); 0: none.
      scan_views: simulated scans (`dmd_jax.scan.simulate_scan`) of every training mesh
        added to the training set, each a range-image triangulation with its view, so the
        pipeline gives it scanner noise along that view; 0: none.
      scan_resolution: pixels on the longer side of those scans' depth maps.
    """

    source: str = _static("procedural")
    root: str | None = _static(None)
    categories: tuple[str, ...] | None = _static(None)
    test_inter_categories: tuple[str, ...] = _static(())
    instances_per_category: int = _static(40)
    target_vertices: int = _static(2000)
    test_fraction: float = _static(0.2)
    seed: int = _static(0)
    dataset_dir: str | None = _static(None)
    eval_meshes_per_split: int = _static(8)
    real_root: str | None = _static(None)
    real_patch_faces: int = _static(6000)
    real_faces_per_patch: int = _static(12000)
    real_patches_per_mesh: int = _static(8)
    real_val_patch_faces: int = _static(4000)
    real_val_patches_per_mesh: int = _static(1)
    real_coarse_faces: tuple[int, ...] = _static(())
    stress_copies: int = _static(0)
    scan_views: int = _static(0)
    scan_resolution: int = _static(64)

    def __post_init__(self):
        _check_choice("data source", self.source, DATA_SOURCES)
        _check(
            self.source != "folder" or self.root is not None,
            "data source 'folder' needs a root directory",
        )
        _check_positive_int("instances_per_category", self.instances_per_category)
        _check_positive_int("target_vertices", self.target_vertices, minimum=4)
        _check(0.0 <= self.test_fraction < 1.0, "test_fraction must lie in [0, 1)")
        _check_positive_int("seed", self.seed, minimum=0)
        _check_path("dataset_dir", self.dataset_dir)
        _check_positive_int("eval_meshes_per_split", self.eval_meshes_per_split, minimum=0)
        _check_path("real_root", self.real_root)
        for name in (
            "real_patch_faces",
            "real_faces_per_patch",
            "real_patches_per_mesh",
            "real_val_patch_faces",
            "real_val_patches_per_mesh",
        ):
            _check_positive_int(name, getattr(self, name))
        for n in self.real_coarse_faces:
            _check_positive_int("real_coarse_faces", n, minimum=4)
        # Bounded: each copy or view is a training mesh held in memory.
        _check_positive_int("stress_copies", self.stress_copies, minimum=0)
        _check(self.stress_copies <= 64, "stress_copies must be at most 64")
        _check_positive_int("scan_views", self.scan_views, minimum=0)
        _check(self.scan_views <= 16, "scan_views must be at most 16")
        _check_positive_int("scan_resolution", self.scan_resolution, minimum=8)
        _check(self.scan_resolution <= 512, "scan_resolution must be at most 512")


@frozen.dataclass
class ExperimentConfig(_ConfigMixin):
    """Everything one run needs; what checkpoints and bundled weights carry."""

    name: str = _static("default")
    model: ModelConfig = ModelConfig()
    loss: LossConfig = LossConfig()
    train: TrainConfig = TrainConfig()
    noise: NoiseConfig = NoiseConfig()
    data: DataConfig = DataConfig()
