"""The denoising policy: the rules `denoise` applies around a trained network.

A `ModelConfig` says what the network is (its layers, its inputs, the parameters it
has). A `DenoisePolicy` says how `denoise` uses it: how much to pre-smooth a noisy mesh
before the network, how many network passes to run, how much tangential relaxation to
apply after. Its numbers are fitted on the validation split for one set of trained
weights (`dmd_jax.calibrate`), and travel in the weights file's own `policy` section
(`dmd_jax.checkpoints`, format version 2): changing a rule is an edit of the weights
file (`dmd-jax export-weights --pass-tolerance ... --presmooth ...`), never of code.

The pass loop (`run_passes`) and the pre-smoothing choice (`presmooth_plan`) live here
too, so every path of `denoise` (whole mesh, patch by patch) runs the same rules.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from flax import struct

from dmd_jax.config import _check, _check_finite, _check_positive_int, _ConfigMixin, _static

# Bounds on what a weights file or a caller may ask for: a weights file is untrusted
# input, and each pass or step costs a whole network run or a sweep over the mesh.
MAX_PASSES_LIMIT = 64
MAX_RELAX_STEPS = 1000
# A roughness rule reads degrees between face normals: 0-180.
_MAX_DEGREES = 180.0


@struct.dataclass
class DenoisePolicy(_ConfigMixin):
    """How `denoise` runs a trained network (all static, JSON like the configs).

    Attributes:
      max_passes: network passes, each starting from the last one's output; with
        `pass_tolerance` above 0, the most passes.
      pass_tolerance: stop after a pass that moved the vertices by at most this on
        average, in the units of the model's frame (mean edge lengths of the input for
        the `"local"` encoding). 0 runs every one of `max_passes`. The amount a pass
        moves the mesh tells how noisy it was: a second pass helps after heavy noise
        and hurts after light noise.
      presmooth_start, presmooth_per_step: the heavy-noise pre-smoothing rule:
        `round((roughness − presmooth_start) / presmooth_per_step)` uniform Laplacian
        steps, clipped to `presmooth.MAX_STEPS`, before the network, where the roughness
        is the noisy mesh's median angle (degrees) between edge-adjacent face normals
        (`dmd_jax.presmooth`). `presmooth_start` 0: no pre-smoothing.
      relax_steps: steps of feature-preserving tangential relaxation after the network
        (`dmd_jax.relax.relax_tangential`); 0 leaves the result as the network made it.
    """

    max_passes: int = _static(1)
    pass_tolerance: float = _static(0.0)
    presmooth_start: float = _static(0.0)
    presmooth_per_step: float = _static(5.0)
    relax_steps: int = _static(0)

    def __post_init__(self):
        _check_positive_int("max_passes", self.max_passes)
        _check(
            self.max_passes <= MAX_PASSES_LIMIT,
            f"max_passes must be at most {MAX_PASSES_LIMIT}, got {self.max_passes}",
        )
        _check_finite("pass_tolerance", self.pass_tolerance)
        _check_finite("presmooth_start", self.presmooth_start)
        _check_finite("presmooth_per_step", self.presmooth_per_step, positive=True)
        _check(
            self.presmooth_start <= _MAX_DEGREES,
            f"presmooth_start is a roughness in degrees (0-180), got {self.presmooth_start}",
        )
        _check(
            self.presmooth_per_step >= 1e-3,
            f"presmooth_per_step must be at least 0.001 degrees, got {self.presmooth_per_step}",
        )
        _check_positive_int("relax_steps", self.relax_steps, minimum=0)
        _check(
            self.relax_steps <= MAX_RELAX_STEPS,
            f"relax_steps must be at most {MAX_RELAX_STEPS}, got {self.relax_steps}",
        )

    @property
    def presmooths(self) -> bool:
        """Whether the pre-smoothing rule is on."""
        return self.presmooth_start > 0

    def overridden(
        self, *, iterations: int | None = None, relax: int | None = None
    ) -> DenoisePolicy:
        """This policy with a caller's fixed pass count or relaxation steps.

        Args:
          iterations: a fixed number of network passes (no tolerance), or None to keep
            the policy's pass rule.
          relax: relaxation steps, or None to keep the policy's.

        Raises:
          ValueError: a count that is not a whole number in range.
        """
        out = self
        if iterations is not None:
            check_count("iterations", iterations, minimum=1, most=MAX_PASSES_LIMIT)
            out = out.replace(max_passes=int(iterations), pass_tolerance=0.0)
        if relax is not None:
            check_count("relax", relax, most=MAX_RELAX_STEPS)
            out = out.replace(relax_steps=int(relax))
        return out


def trained_policy(config) -> DenoisePolicy:
    """The policy a network's training implies: the passes it was trained to run.

    A run with `TrainConfig.passes = k` scores the network after each of `k` passes, so
    `denoise` runs `k` (no tolerance, no pre-smoothing, no relaxation). It is the
    policy of a training checkpoint and of weights exported from one, until a fitted
    or edited policy replaces it (`dmd-jax export-weights`).

    Args:
      config: the run's `ExperimentConfig`.
    """
    return DenoisePolicy(max_passes=config.train.passes)


def check_count(name: str, value, *, minimum: int = 0, most: int) -> int:
    """`value` as an int if it is a whole number in `[minimum, most]` (a bool is not).

    Raises:
      ValueError: naming `name`, the value and the range.
    """
    if isinstance(value, bool | np.bool_):
        ok = False
    elif isinstance(value, int | np.integer):
        ok = minimum <= value <= most  # exact for integers of any size
    elif isinstance(value, float | np.floating):
        ok = math.isfinite(value) and value == int(value) and minimum <= value <= most
    else:
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a whole number from {minimum} to {most}, got {value!r}")
    return int(value)


def from_legacy_model_fields(model: dict) -> tuple[dict, DenoisePolicy]:
    """Splits a stored model config dict of weights format 1 into model and policy.

    Format-1 files (and configs saved before the policy had its own home) carry the rules
    as `ModelConfig` fields: `pass_tolerance` (0: one pass; above 0: up to 8 passes, the
    old `inference.AUTO_MAX_PASSES`), `presmooth_start`, `presmooth_per_step`.

    Returns:
      The model dict without those keys, and the policy they described.
    """
    model = dict(model)
    tolerance = model.pop("pass_tolerance", 0.0)
    start = model.pop("presmooth_start", 0.0)
    per_step = model.pop("presmooth_per_step", 5.0)
    policy = DenoisePolicy.from_dict(
        {
            "max_passes": LEGACY_AUTO_MAX_PASSES if tolerance > 0 else 1,
            "pass_tolerance": tolerance,
            "presmooth_start": start,
            "presmooth_per_step": per_step,
        }
    )
    return model, policy


# The pass cap of format-1 weights with a pass tolerance (on the validation split no mesh
# needed a third pass; fixed pass counts kept improving up to 8 on the paper's Table II
# levels, experiments/results/sota/sota.md).
LEGACY_AUTO_MAX_PASSES = 8


class PresmoothPlan(NamedTuple):
    """The Laplacian steps run before the network, and the roughness that chose them
    (None when the caller fixed the steps or the rule is off)."""

    steps: int
    roughness: float | None


def presmooth_plan(
    policy: DenoisePolicy, vertices: np.ndarray, faces: np.ndarray, steps: int | None
) -> PresmoothPlan:
    """How many pre-smoothing steps to run: `steps` if given, else the policy's rule.

    Args:
      policy: the policy.
      vertices: `[n_vertex, 3]` noisy positions (any frame: the roughness is scale free).
      faces: `[n_face, 3]` faces.
      steps: a caller's fixed step count, or None.
    """
    from dmd_jax import presmooth

    if steps is not None:
        return PresmoothPlan(check_count("presmooth", steps, most=presmooth.MAX_STEPS), None)
    if not policy.presmooths:
        return PresmoothPlan(0, None)
    rough = presmooth.roughness(vertices, faces)
    return PresmoothPlan(
        presmooth.steps_for(rough, policy.presmooth_start, policy.presmooth_per_step), rough
    )


def run_passes(
    one_pass: Callable[[np.ndarray], np.ndarray], x: np.ndarray, policy: DenoisePolicy
) -> tuple[np.ndarray, int]:
    """Applies `one_pass` (positions -> positions, frame units) as the policy says.

    Up to `policy.max_passes` times, stopping after a pass whose mean vertex move is at
    most `policy.pass_tolerance` (tolerance 0: every one of them).

    Returns:
      The positions and the number of passes run.

    Raises:
      ValueError: a pass produced non-finite positions.
    """
    tolerance = policy.pass_tolerance if policy.pass_tolerance > 0 else -1.0
    done, moved = 0, np.inf
    while done < policy.max_passes and moved > tolerance:
        out = one_pass(x)
        if not np.all(np.isfinite(out)):
            raise ValueError("the network produced non-finite vertices (broken weights?)")
        moved = float(np.linalg.norm(out - x, axis=1).mean()) if len(out) else 0.0
        x, done = out, done + 1
    return x, done
