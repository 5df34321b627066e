"""The denoising policy: the rules `denoise` applies around a trained network.

A `ModelConfig` says what the network is (its layers, its inputs, the parameters it
has). A `DenoisePolicy` says how `denoise` uses it: how much to pre-smooth a noisy mesh
before the network (or whether to take a network-free route past it), how many network
passes to run, how much tangential relaxation to apply after. Its numbers are fitted for
one set of trained weights (`dmd_jax.calibrate`), and travel in the weights file's own
`policy` section (`dmd_jax.checkpoints`, format version 2): changing a rule is an edit of
the weights file (`dmd-jax export-weights --pass-tolerance ... --presmooth ...`), never
of code.

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
# Network-free routes (`dmd_jax.routes`): each pass is a sweep over the mesh.
MAX_ROUTES = 8
MAX_ROUTE_PASSES = 500
MIN_ROUTE_SIGMA, MAX_ROUTE_SIGMA = 0.01, 10.0
# A roughness rule reads degrees between face normals: 0-180.
_MAX_DEGREES = 180.0


def _check_fields_of_runs(name: str, sigmas, passes) -> None:
    """`{name}_sigmas` and `{name}_passes` pair up, at most `MAX_ROUTES`, each a range
    sigma in `[MIN_ROUTE_SIGMA, MAX_ROUTE_SIGMA]` and a whole pass count in `[1,
    MAX_ROUTE_PASSES]` (a weights file is untrusted: every run is bounded)."""
    _check(
        len(passes) == len(sigmas) and len(sigmas) <= MAX_ROUTES,
        f"{name}_sigmas and {name}_passes must pair up, at most {MAX_ROUTES}, got "
        f"{len(sigmas)} and {len(passes)}",
    )
    for sigma, count in zip(sigmas, passes, strict=True):
        _check(
            isinstance(sigma, float | int)
            and math.isfinite(sigma)
            and MIN_ROUTE_SIGMA <= sigma <= MAX_ROUTE_SIGMA,
            f"{name}_sigmas must be range sigmas from {MIN_ROUTE_SIGMA} to "
            f"{MAX_ROUTE_SIGMA}, got {sigma!r}",
        )
        _check(
            isinstance(count, int) and 1 <= count <= MAX_ROUTE_PASSES,
            f"{name}_passes must be whole numbers from 1 to {MAX_ROUTE_PASSES}, got {count!r}",
        )


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
      presmooth_grid, presmooth_center, presmooth_scale, presmooth_examples,
        presmooth_regrets, presmooth_neighbours: the learned pre-smoothing choice, in
        place of the roughness rule when `presmooth_grid` is set (the rule's numbers
        stay: `denoise(..., presmooth="rule")` runs them): `presmooth.learned_steps` reads
        the noisy mesh's `presmooth.noise_features` and runs the count of
        `presmooth_grid` of least mean regret (log error over the best count's) over the
        `presmooth_neighbours` nearest training examples; where that is the grid's
        largest count and the rule asks for more (noise heavier than any training
        example), the rule's count. Fitted for one set of weights
        on the training split of `shared/meshes/train`
        (`benchmarks/quality/presmooth_learn.py`); empty: off.
      relax_steps: steps of feature-preserving tangential relaxation after the network
        (`dmd_jax.relax.relax_tangential`); 0 leaves the result as the network made it.
      route_sigmas, route_passes: network-free routes the learned choice may take in
        place of the network (`dmd_jax.routes.run_route`: one of the network's own
        candidate normal fields alone, range σ `route_sigmas[i]` after
        `route_passes[i]` passes, then the head's vertex update). Their regrets follow
        the grid's in each row of `presmooth_regrets`. Empty: the choice picks only
        pre-smoothing counts for the network.
      review_route, review_center, review_scale, review_examples, review_regrets,
        review_neighbours: the review after the network (`dmd_jax.review`), on when
        `review_examples` is set: where the network ran whole on a mesh after the
        learned choice, the `review.output_features` of the network's result beside
        route `review_route`'s (an index into `route_sigmas`) choose, by least mean
        regret over the `review_neighbours` nearest training examples, between keeping
        the network's result (the first regret of each row of `review_regrets`) and
        each route. Needs the learned choice and its routes.
      cascade_sigmas, cascade_passes, cascade_regrets, cascade_neighbours: the
        review's second choice, where it keeps the network's result: keep it, or run a
        cascade on it, a route's candidate field and vertex update (`routes.run_route`,
        range σ `cascade_sigmas[i]` after `cascade_passes[i]` passes) on the network's
        *result* rather than the noisy mesh (a second stage). The same features and
        training examples as the review (`review_examples`), with their own regrets
        (`1 + len(cascade_sigmas)` per example: the network's result, then each
        cascade) and neighbour count. Empty: no cascade.
    """

    max_passes: int = _static(1)
    pass_tolerance: float = _static(0.0)
    presmooth_start: float = _static(0.0)
    presmooth_per_step: float = _static(5.0)
    relax_steps: int = _static(0)
    presmooth_grid: tuple[int, ...] = _static(())
    presmooth_center: tuple[float, ...] = _static(())
    presmooth_scale: tuple[float, ...] = _static(())
    presmooth_examples: tuple[float, ...] = _static(())
    presmooth_regrets: tuple[float, ...] = _static(())
    presmooth_neighbours: int = _static(0)
    route_sigmas: tuple[float, ...] = _static(())
    route_passes: tuple[int, ...] = _static(())
    review_route: int = _static(0)
    review_center: tuple[float, ...] = _static(())
    review_scale: tuple[float, ...] = _static(())
    review_examples: tuple[float, ...] = _static(())
    review_regrets: tuple[float, ...] = _static(())
    review_neighbours: int = _static(0)
    cascade_sigmas: tuple[float, ...] = _static(())
    cascade_passes: tuple[int, ...] = _static(())
    cascade_regrets: tuple[float, ...] = _static(())
    cascade_neighbours: int = _static(0)

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

        self._check_learned_presmoothing()
        self._check_review()

    def _check_learned_presmoothing(self) -> None:
        # A weights file is untrusted: sizes and values are checked before any is used.
        from dmd_jax import presmooth

        grid, n_features = self.presmooth_grid, len(presmooth.FEATURE_NAMES)
        n_route = len(self.route_sigmas)
        _check_fields_of_runs("route", self.route_sigmas, self.route_passes)
        fields = (
            self.presmooth_center,
            self.presmooth_scale,
            self.presmooth_examples,
            self.presmooth_regrets,
        )
        if not grid and not any(fields) and not self.presmooth_neighbours:
            _check(not n_route, "routes need a learned choice (presmooth_grid) to pick them")
            return
        _check(
            0 < len(grid) <= presmooth.MAX_STEPS + 1
            and all(isinstance(k, int) and 0 <= k <= presmooth.MAX_STEPS for k in grid)
            and list(grid) == sorted(set(grid)),
            f"presmooth_grid must be ascending distinct step counts from 0 to "
            f"{presmooth.MAX_STEPS}, got {grid!r}",
        )
        self._check_nearest_table(
            "presmooth", n_features, len(grid) + n_route, f"{len(grid)} counts, {n_route} routes"
        )

    def _check_nearest_table(self, prefix: str, n_features: int, n_options: int, options: str):
        """The checks of one nearest-neighbour table, the fields `{prefix}_center`,
        `_scale`, `_examples`, `_regrets`, `_neighbours` (`options` names the regret
        columns in the messages)."""
        from dmd_jax.presmooth import MAX_EXAMPLES

        examples = getattr(self, f"{prefix}_examples")
        neighbours = getattr(self, f"{prefix}_neighbours")
        n_example = len(examples) // n_features
        _check(
            0 < n_example <= MAX_EXAMPLES,
            f"{prefix}_examples must hold 1 to {MAX_EXAMPLES} examples of "
            f"{n_features} features, got {len(examples)} numbers",
        )
        want = {
            f"{prefix}_center": n_features,
            f"{prefix}_scale": n_features,
            f"{prefix}_examples": n_example * n_features,
            f"{prefix}_regrets": n_example * n_options,
        }
        for name, size in want.items():
            values = getattr(self, name)
            _check(
                len(values) == size and all(math.isfinite(x) for x in values),
                f"{name} must hold {size} finite numbers ({n_example} examples, "
                f"{options}), got {len(values)}",
            )
        _check(
            all(x > 0 for x in getattr(self, f"{prefix}_scale")),
            f"{prefix}_scale must be positive",
        )
        _check_positive_int(f"{prefix}_neighbours", neighbours)
        _check(
            neighbours <= n_example,
            f"{prefix}_neighbours must be at most the {n_example} examples, got {neighbours}",
        )

    def _check_review(self) -> None:
        from dmd_jax import review

        _check_fields_of_runs("cascade", self.cascade_sigmas, self.cascade_passes)
        n_cascade = len(self.cascade_sigmas)
        fields = (self.review_center, self.review_scale, self.review_examples, self.review_regrets)
        if not any(fields) and not self.review_neighbours:
            _check(
                self.review_route == 0,
                f"review_route needs a review (review_examples), got {self.review_route!r}",
            )
            _check(
                not (n_cascade or self.cascade_regrets or self.cascade_neighbours),
                "cascades need a review (review_examples) to take them",
            )
            return
        n_route = len(self.route_sigmas)
        _check(
            self.learns_presmoothing and n_route > 0,
            "a review needs the learned choice and its routes (presmooth_grid, route_sigmas)",
        )
        _check(
            isinstance(self.review_route, int) and 0 <= self.review_route < n_route,
            f"review_route must index one of the {n_route} routes, got {self.review_route!r}",
        )
        self._check_nearest_table(
            "review",
            len(review.OUTPUT_FEATURE_NAMES),
            1 + n_route,
            f"the network and {n_route} routes",
        )
        if not (n_cascade or self.cascade_regrets or self.cascade_neighbours):
            return
        n_example = len(self.review_examples) // len(review.OUTPUT_FEATURE_NAMES)
        size = n_example * (1 + n_cascade)
        _check(
            n_cascade > 0
            and len(self.cascade_regrets) == size
            and all(math.isfinite(x) for x in self.cascade_regrets),
            f"cascade_regrets must hold {size} finite numbers ({n_example} examples, the "
            f"network and {n_cascade} cascades), got {len(self.cascade_regrets)}",
        )
        _check_positive_int("cascade_neighbours", self.cascade_neighbours)
        _check(
            self.cascade_neighbours <= n_example,
            f"cascade_neighbours must be at most the {n_example} examples, "
            f"got {self.cascade_neighbours}",
        )

    @property
    def reviews(self) -> bool:
        """Whether `denoise` reviews the network's result (`dmd_jax.review`)."""
        return bool(self.review_examples)

    def without_review(self) -> DenoisePolicy:
        """This policy with no review after the network."""
        return self.replace(
            review_route=0,
            review_center=(),
            review_scale=(),
            review_examples=(),
            review_regrets=(),
            review_neighbours=0,
            cascade_sigmas=(),
            cascade_passes=(),
            cascade_regrets=(),
            cascade_neighbours=0,
        )

    @property
    def presmooths(self) -> bool:
        """Whether `denoise` chooses pre-smoothing steps (the rule or the learned choice)."""
        return self.presmooth_start > 0 or self.learns_presmoothing

    def describe(self, sep: str = " ") -> str:
        """The fields on one line, `name{sep}value`, a learned choice's tables as their
        size (what `dmd-jax info` and the reports print)."""
        from dmd_jax.presmooth import FEATURE_NAMES
        from dmd_jax.review import OUTPUT_FEATURE_NAMES

        tables = ("center", "scale", "regrets")
        items = []
        for key, value in self.to_dict().items():
            if key in {f"{p}_{t}" for p in ("presmooth", "review", "cascade") for t in tables}:
                continue
            if key == "presmooth_examples":
                n = len(value) // len(FEATURE_NAMES)
                value = f"{n} training examples" if value else "none"
            if key == "review_examples":
                n = len(value) // len(OUTPUT_FEATURE_NAMES)
                value = f"{n} training examples" if value else "none"
            items.append(f"{key}{sep}{value}")
        return ", ".join(items)

    def with_presmooth_rule(self) -> DenoisePolicy:
        """This policy with its roughness rule in place of the learned choice (and no
        review, which needs the choice's routes)."""
        return self.without_review().replace(
            presmooth_grid=(),
            presmooth_center=(),
            presmooth_scale=(),
            presmooth_examples=(),
            presmooth_regrets=(),
            presmooth_neighbours=0,
            route_sigmas=(),
            route_passes=(),
        )

    def route_label(self, index: int) -> str:
        """How reports name route `index`: `"field σ0.2 ×60"`."""
        return f"field σ{self.route_sigmas[index]:g} ×{self.route_passes[index]}"

    def cascade_label(self, index: int) -> str:
        """How reports name cascade `index`: `"cascade σ0.2 ×16"`."""
        return f"cascade σ{self.cascade_sigmas[index]:g} ×{self.cascade_passes[index]}"

    @property
    def learns_presmoothing(self) -> bool:
        """Whether the learned choice, not the roughness rule, picks the steps."""
        return bool(self.presmooth_grid)

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
    """The Laplacian steps run before the network, the roughness that chose them
    (None when the caller fixed the steps or the rule is off), and the route the learned
    choice took in place of the network (an index into `DenoisePolicy.route_sigmas`;
    None: the network runs)."""

    steps: int
    roughness: float | None
    route: int | None = None


# `denoise(..., presmooth=PRESMOOTH_RULE)`: the roughness rule, not the learned choice.
PRESMOOTH_RULE = "rule"


def presmooth_plan(
    policy: DenoisePolicy, vertices: np.ndarray, faces: np.ndarray, steps: int | str | None
) -> PresmoothPlan:
    """How many pre-smoothing steps to run: `steps` if given, else the policy's choice
    (learned, or its roughness rule; `steps=PRESMOOTH_RULE`: the rule). Only the learned
    choice, with no `steps` given, may take a network-free route instead (`route`).

    Args:
      policy: the policy.
      vertices: `[n_vertex, 3]` noisy positions (any frame: the roughness is scale free).
      faces: `[n_face, 3]` faces.
      steps: a caller's fixed step count, `PRESMOOTH_RULE`, or None.
    """
    from dmd_jax import presmooth

    if isinstance(steps, str) and steps == PRESMOOTH_RULE:
        policy, steps = policy.with_presmooth_rule(), None
    if steps is not None:
        return PresmoothPlan(check_count("presmooth", steps, most=presmooth.MAX_STEPS), None)
    if not policy.presmooths:
        return PresmoothPlan(0, None)
    if policy.learns_presmoothing:
        features = presmooth.noise_features(vertices, faces)
        grid = policy.presmooth_grid
        option = presmooth.learned_option(
            features,
            len(grid) + len(policy.route_sigmas),
            policy.presmooth_center,
            policy.presmooth_scale,
            policy.presmooth_examples,
            policy.presmooth_regrets,
            policy.presmooth_neighbours,
        )
        # The median angle the features read (of a mesh's first faces, for a large one).
        rough = float(np.exp(features[1]) - 0.5)
        if option >= len(grid):
            return PresmoothPlan(0, rough, option - len(grid))
        steps = grid[option]
        # The choice at its largest count, and the rule asking for more (the paper's
        # per-coordinate noise of several edges, beyond every training example): a
        # nearest-neighbour choice cannot extrapolate past its grid; the rule can.
        if steps == max(policy.presmooth_grid):
            rule = presmooth.steps_for(rough, policy.presmooth_start, policy.presmooth_per_step)
            steps = max(steps, rule)
        return PresmoothPlan(steps, rough)
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
