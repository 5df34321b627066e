"""The denoising policy: the rules `denoise` applies around a trained network.

A `ModelConfig` says what the network is (its layers, its inputs, the parameters it
has). A `DenoisePolicy` says how `denoise` uses it: how many network passes to run, how
much to pre-smooth noise heavier than any the network was trained on, how much
tangential relaxation to apply after. Five numbers, chosen for one set of trained
weights, travel in the weights file's own `policy` section (`dmd_jax.checkpoints`,
format version 2): changing a rule is an edit of the weights file (`dmd-jax
export-weights --pass-tolerance ... --presmooth ...`), never of code. What the network
should decide per mesh it learns in training; the policy holds no fitted tables (the
selectors fitted around the network were removed, issue 54: `docs/history.md`).

The pass loop (`run_passes`) and the pre-smoothing plan (`presmooth_plan`) live here
too, so every path of `denoise` (whole mesh, patch by patch) runs the same rules.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

import dmd_jax.config.frozen as frozen
from dmd_jax.config import _check, _check_finite, _check_positive_int, _ConfigMixin, _static

# Bounds on what a weights file or a caller may ask for: a weights file is untrusted
# input, and each pass or step costs a whole network run or a sweep over the mesh.
MAX_PASSES_LIMIT = 64
MAX_RELAX_STEPS = 1000
# A roughness rule reads degrees between face normals: 0-180.
_MAX_DEGREES = 180.0
# The `policy` fields of weights files written before issue 54: the fitted selectors
# (learned pre-smoothing kNN, network-free routes, review, cascades). Such files still
# load: `stored_policy` drops these fields with one warning naming them.
RETIRED_FIELDS = (
    "presmooth_grid",
    "presmooth_center",
    "presmooth_scale",
    "presmooth_examples",
    "presmooth_regrets",
    "presmooth_neighbours",
    "route_sigmas",
    "route_passes",
    "review_route",
    "review_center",
    "review_scale",
    "review_examples",
    "review_regrets",
    "review_neighbours",
    "cascade_sigmas",
    "cascade_passes",
    "cascade_regrets",
    "cascade_neighbours",
)


class RetiredPolicyWarning(UserWarning):
    """A weights file carried policy fields this version no longer runs (`RETIRED_FIELDS`)."""


@frozen.dataclass
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
        (`dmd_jax.presmooth`). `presmooth_start` 0: no pre-smoothing. A documented
        rule, not a fitted table: the bundled network was trained on noise up to one
        mean edge, and the rule starts where the roughness of heavier noise begins.
      relax_steps: steps of feature-preserving tangential relaxation after the network
        (`dmd_jax.relax.relax_tangential`); 0 leaves the result as the network made it.
      controller: whether `denoise` lets the learned smoothing controller stored with
        the weights (`dmd_jax.controller`) choose pre-smoothing, passes and vertex update
        when the caller fixes none of them, instead of the two rules above.
    """

    max_passes: int = _static(1)
    pass_tolerance: float = _static(0.0)
    presmooth_start: float = _static(0.0)
    presmooth_per_step: float = _static(5.0)
    relax_steps: int = _static(0)
    controller: bool = _static(False)

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
            isinstance(self.controller, bool),
            f"controller must be true or false, got {self.controller!r}",
        )
        _check(
            self.relax_steps <= MAX_RELAX_STEPS,
            f"relax_steps must be at most {MAX_RELAX_STEPS}, got {self.relax_steps}",
        )

    @property
    def presmooths(self) -> bool:
        """Whether `denoise` runs the pre-smoothing rule."""
        return self.presmooth_start > 0

    def describe(self, sep: str = " ") -> str:
        """The fields on one line, `name{sep}value` (what `dmd-jax info` and the reports
        print)."""
        return ", ".join(f"{key}{sep}{value}" for key, value in self.to_dict().items())

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


def stored_policy(stored, source="the weights file") -> DenoisePolicy:
    """The policy of a weights file's `policy` section, its retired fields dropped.

    Files written before issue 54 carry the fitted selectors' fields (`RETIRED_FIELDS`:
    about 43,000 numbers of nearest-neighbour tables). They keep loading, with the
    network, the pass rule and the pre-smoothing rule they hold; the selectors are not
    run, and one `RetiredPolicyWarning` names the fields dropped. Any other unknown
    field is an error, as before.

    Args:
      stored: the section's JSON dict.
      source: names the file in the warning.

    Raises:
      ValueError: not a dict, an unknown field, or a value out of its bounds.
    """
    import warnings

    if not isinstance(stored, dict):
        raise ValueError(f"the policy must be a JSON object, got {type(stored).__name__}")
    retired = [name for name in RETIRED_FIELDS if name in stored]
    if retired:
        warnings.warn(
            f"{source}: dropped the retired policy fields {', '.join(retired)} (fitted "
            "selectors this dmd_jax no longer runs, issue 54); the network runs with "
            "the file's pass and pre-smoothing rules. Re-export the weights (dmd-jax "
            "export-weights) to drop them from the file.",
            RetiredPolicyWarning,
            stacklevel=3,
        )
        stored = {k: v for k, v in stored.items() if k not in RETIRED_FIELDS}
    return DenoisePolicy.from_dict(stored)


# The pass cap of format-1 weights with a pass tolerance (on the validation split no mesh
# needed a third pass; fixed pass counts kept improving up to 8 on the paper's Table II
# levels, experiments/results/sota/sota.md).
LEGACY_AUTO_MAX_PASSES = 8


class PresmoothPlan(NamedTuple):
    """The Laplacian steps run before the network and the roughness that chose them
    (None when the caller fixed the steps or the rule is off)."""

    steps: int
    roughness: float | None


# `denoise(..., presmooth=PRESMOOTH_RULE)`: the policy's rule, as with no `presmooth`
# (kept for callers of the releases where it picked the rule over a learned choice).
PRESMOOTH_RULE = "rule"


def presmooth_plan(
    policy: DenoisePolicy,
    vertices: np.ndarray,
    faces: np.ndarray,
    steps: int | str | None,
    free: np.ndarray | None = None,
    *,
    normals: np.ndarray | None = None,
) -> PresmoothPlan:
    """How many pre-smoothing steps to run: `steps` if given, else the policy's rule
    (`steps=PRESMOOTH_RULE` or None).

    Args:
      policy: the policy.
      vertices: `[n_vertex, 3]` noisy positions (any frame: the roughness is scale free).
      faces: `[n_face, 3]` faces.
      steps: a caller's fixed step count, `PRESMOOTH_RULE`, or None.
      free: `[n_vertex]` bool, the vertices that may move (`presmooth.roughness`), or
        None for all.
      normals: `[n_face, 3]` the faces' unit normals (`mesh.face_normals_np` of
        `vertices`), if already known.
    """
    from dmd_jax import presmooth

    if isinstance(steps, str) and steps == PRESMOOTH_RULE:
        steps = None
    if steps is not None:
        return PresmoothPlan(check_count("presmooth", steps, most=presmooth.MAX_STEPS), None)
    if not policy.presmooths:
        return PresmoothPlan(0, None)
    rough = presmooth.roughness(vertices, faces, free=free, normals=normals)
    steps = presmooth.steps_for(rough, policy.presmooth_start, policy.presmooth_per_step)
    if (
        steps
        and presmooth.bend_share(vertices, faces, free=free, normals=normals)
        < presmooth.MIN_BEND_SHARE
    ):
        steps = 0  # a coarse convex solid's dihedrals, not noise: nothing to pre-smooth
    return PresmoothPlan(steps, rough)


def run_passes(
    one_pass: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    policy: DenoisePolicy,
    held: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """Applies `one_pass` (positions -> positions, frame units) as the policy says.

    Up to `policy.max_passes` times, stopping after a pass whose mean vertex move is at
    most `policy.pass_tolerance` (tolerance 0: every one of them). Vertices of `held`
    (`[n_vertex]` bool, `consistency.exact_vertices`) are put back where they were after
    every pass, before the move is measured.

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
        if held is not None:
            out[held] = x[held]
        moved = float(np.linalg.norm(out - x, axis=1).mean()) if len(out) else 0.0
        x, done = out, done + 1
    return x, done
