"""Experiment configuration: frozen pytree dataclasses, presets and structure variants.

Every config is a frozen pytree dataclass (`dmd_jax.config.frozen`: what
`flax.struct.dataclass` makes, without importing Flax), so it is immutable, hashable
and a pytree.
Every field is static metadata (`pytree_node=False`): configs decide shapes, code paths
and which loss terms are computed at all (`dmd_jax.losses` needs static weights), so a
config has no leaves and can be a static argument of `jax.jit`.

Configs serialise to plain JSON (`to_dict` / `from_dict`, `to_json` / `from_json`);
`from_dict` is strict: unknown keys and values of the wrong type raise `ValueError`;
missing keys take their defaults. Checkpoints and bundled weights carry their config.

Presets (`preset(name)`):

* `paper`: the paper's width 512, FGT-8, feature extractor of 2 two-stream networks,
  denoiser depth 2. Our reading of the architecture has 12,881,416 parameters
  (`dmd_jax.model.param_count(preset("paper").model)`, with `jax.eval_shape`): feature
  extractor 3,683,845, transformer 4,990,464, denoiser 4,207,107. The paper says
  "around 30 million" but gives no per-layer sizes (its figure is the only source and
  is not in the text), so the gap must lie in what the text leaves out: hidden fully
  connected layers in the heads and the transformer, the widths inside the densely
  connected aggregators, wider projections. We do not invent layers to reach 30 M.
* `small`: the first stage of the bundled weights' recipe, sized for a 2-core CPU: width 32, FGT-8,
  the resolution-free `"local"` encoding with Taubin-smoothed candidates and the
  normal-first head (`dmd_jax.encoding`, `docs/design-decisions.md`), edge-unit noise
  mostly along normals with clean draws, losses in edge units. (Before 2026-11-30
  `small` was width 48 on absolute bounding-box coordinates; those weights still load,
  their config travels with them.) The bundled file's own config is that of the last
  of two fine-tunes on top of it (`scripts/train_bundled.sh`, `docs/bundled-model.md`):
  120 pre-filter passes instead of 60, heavier normal losses, benchmark-weighted noise
  and their own schedule; `dmd-jax info --weights bundled` prints it.
* `test`: the `small` recipe at width 8 and 40 steps: a run on a tiny dataset in under
  a minute on 2 cores (`dmd-jax train --preset test`), and the model of unit tests.

Layout: `sections` holds the dataclasses and their validation, `codec` the JSON codec
they share (`_ConfigMixin`), `presets` the presets and structure variants. Every name is
re-exported here, so `from dmd_jax.config import X` is the one import a caller needs.
"""

# The private helpers a config-like class outside this package builds on
# (`dmd_jax.policy.DenoisePolicy`) are re-exported explicitly (`X as X`).
from dmd_jax.config.codec import _ConfigMixin as _ConfigMixin
from dmd_jax.config.presets import (
    CAPPED_CANONICAL_LEVELS,
    PRESETS,
    VARIANTS,
    preset,
    variant_config,
)
from dmd_jax.config.sections import (
    DATA_SOURCES,
    DTYPES,
    FEATURE_CURVATURES,
    FILTER_SIGMA_RANGE,
    HEADS,
    LEGACY_POLICY_FIELDS,
    MAX_FILTERS,
    MAX_HEAD_INIT_SCALE,
    MAX_TRAIN_PASSES,
    MODEL_COUNT_LIMITS,
    SCHEDULES,
    SCHEMES,
    VARIANT_NAMES,
    DataConfig,
    ExperimentConfig,
    LossConfig,
    ModelConfig,
    NoiseConfig,
    TrainConfig,
)
from dmd_jax.config.sections import _check as _check
from dmd_jax.config.sections import _check_finite as _check_finite
from dmd_jax.config.sections import _check_positive_int as _check_positive_int
from dmd_jax.config.sections import _static as _static

__all__ = [
    "CAPPED_CANONICAL_LEVELS",
    "DATA_SOURCES",
    "DTYPES",
    "FEATURE_CURVATURES",
    "FILTER_SIGMA_RANGE",
    "HEADS",
    "LEGACY_POLICY_FIELDS",
    "MAX_FILTERS",
    "MAX_HEAD_INIT_SCALE",
    "MAX_TRAIN_PASSES",
    "MODEL_COUNT_LIMITS",
    "PRESETS",
    "SCHEDULES",
    "SCHEMES",
    "VARIANTS",
    "VARIANT_NAMES",
    "DataConfig",
    "ExperimentConfig",
    "LossConfig",
    "ModelConfig",
    "NoiseConfig",
    "TrainConfig",
    "preset",
    "variant_config",
]
