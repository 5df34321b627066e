"""Fitting the rules of a `DenoisePolicy` for trained weights on the validation split.

Two rules of `dmd_jax.policy.DenoisePolicy` are numbers fitted for one set of trained
weights; both are measured on the validation split of the real training meshes
(`dmd_jax.protocol.validation_files`), never on the test meshes:

* **the pass tolerance** (`fit_pass_tolerance`): `denoise` runs a second network pass
  while the last one moved the vertices by more than `pass_tolerance` (frame units,
  mean edges). How far the first pass moves a mesh tells how noisy it was; a second pass
  helps after heavy noise and hurts after light noise. `pass_rows` measures, per mesh and
  benchmark-noise level (`PASS_LEVELS`, the crops and seeds of `dmd_jax.protocol`), the
  normal error after one and two passes and the first pass's move; the tolerance is the
  one whose rule (a second pass exactly where the first moved more than it) gives the
  lowest mean error over the benchmark levels. Third passes are not simulated.
* **the pre-smoothing rule** (`fit_presmooth`): `round((roughness − start) /
  per_step)` Laplacian steps before the network (`dmd_jax.presmooth`). `presmooth_rows`
  measures, per mesh and noise condition (`PRESMOOTH_CONDITIONS`: the benchmark noise
  along the normals up to 0.5 edges, per coordinate up to the heaviest level of the
  paper's Table II), the noisy roughness and the error after 0-20 steps; the rule is
  the `(start, per_step)` of a grid with the lowest mean error over the conditions,
  each weighted equally, among the rules that leave every clean validation mesh alone.

`calibrate` runs both (the pass tolerance first, then the pre-smoothing with it) and
returns the new policy; `benchmarks/quality/calibrate.py` (`make calibrate`) writes the
reports and, with `--out`, the weights file carrying it. The measuring functions take
the denoiser as an argument (default `dmd_jax.inference.denoise`), so the fits can be
checked on tiny synthetic data without a network.

Host side: NumPy at import; JAX is loaded by the denoiser and the noise.
"""

from __future__ import annotations

import csv
import warnings
import zlib
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from dmd_jax import protocol

# Benchmark-noise levels the pass rule is measured at (mean edges along the normals).
PASS_LEVELS = (0.05, 0.1, 0.2, 0.3, 0.5)
TOLERANCES = tuple(float(t) for t in np.round(np.arange(0.04, 0.401, 0.01), 2))
PASS_HEADER = ("mesh", "faces", "level", "seed", "one_pass", "two_passes", "move1", "move2")
# The pass cap a fitted tolerance runs under when the weights' policy had one pass.
DEFAULT_MAX_PASSES = 8

# Pre-smoothing crops are smaller than the benchmark's (21 denoise calls per mesh and
# condition make this fit's cost; the roughness does not depend on the size).
PRESMOOTH_MAX_FACES = 6_000
# (direction, Gaussian σ in mean edges): the benchmark's noise along the normals, and
# per-coordinate noise up to the heaviest level of the paper's Table II (Block, Fandisk).
PRESMOOTH_CONDITIONS = (
    ("normal", 0.1),
    ("normal", 0.2),
    ("normal", 0.3),
    ("normal", 0.5),
    ("isotropic", 0.3),
    ("isotropic", 0.6),
    ("isotropic", 1.0),
    ("isotropic", 2.0),
    ("isotropic", 3.0),
)
STARTS = tuple(float(s) for s in range(10, 81))
PER_STEPS = tuple(float(p) for p in np.round(np.arange(1.0, 10.01, 0.5), 1))
# Columns before the per-step errors: 0-20 steps follow (`steps_0` ... `steps_20`).
PRESMOOTH_HEADER = ("mesh", "faces", "condition", "seed", "roughness", "laplacian")

# A denoiser as `inference.denoise`: (vertices, faces, bundle, **keywords) -> vertices.
Denoiser = Callable[..., np.ndarray]


class Case(NamedTuple):
    """One validation mesh, cropped as the protocol crops it."""

    name: str  # file name (seeds its noise)
    clean: np.ndarray  # [n_vertex, 3] float64
    faces: np.ndarray  # [n_face, 3] int


class Calibration(NamedTuple):
    """What `calibrate` measured and fitted."""

    policy: object  # DenoisePolicy with the fitted rules
    pass_rows: list[list]  # PASS_HEADER rows
    presmooth_rows: list[list]  # PRESMOOTH_HEADER + steps_0..steps_20 rows
    clean_roughness: dict[str, float]  # mesh name -> roughness of the clean crop
    presmooth_errors: dict[str, float]  # condition -> mean error under the fitted rule


def _default_denoiser() -> Denoiser:
    from dmd_jax.inference import denoise

    return denoise


def _normal_error(out, clean, faces) -> float:
    from dmd_jax.metrics import mesh_metrics

    return float(mesh_metrics(np.asarray(out, np.float64), clean, faces)["normal_deg"])


def validation_cases(val_dir=None, max_faces: int = protocol.MAX_FACES) -> list[Case]:
    """The validation meshes of `val_dir` (default `protocol.validation_dir()`), each
    cropped to at most `max_faces` faces (`protocol.crop`), in float64."""
    return _cases(protocol.validation_files(val_dir), max_faces)


def _cases(paths, max_faces: int) -> list[Case]:
    """The meshes of `paths`, each cropped to at most `max_faces` faces, in float64."""
    from dmd_jax.io import load_mesh

    cases = []
    for path in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "polygons triangulated" and the like
            clean, faces = load_mesh(path)
        clean, faces = protocol.crop(np.asarray(clean, np.float64), faces, max_faces)
        cases.append(Case(path.name, np.asarray(clean, np.float64), faces))
    return cases


# --------------------------------------------------------------------------------------
# The pass tolerance
# --------------------------------------------------------------------------------------


def pass_rows(
    cases: Sequence[Case],
    bundle,
    levels: Sequence[float] = PASS_LEVELS,
    *,
    denoise: Denoiser | None = None,
    echo: Callable[[str], None] | None = None,
) -> list[list]:
    """Per case and level: the errors after one and two passes and each pass's move.

    Args:
      cases: from `validation_cases`.
      bundle: the weights (`ModelBundle`), passed on to `denoise`.
      levels: benchmark-noise σ in mean edges (seeds `protocol.noise_seed`).
      denoise: the denoiser (default `dmd_jax.inference.denoise`), called with
        `iterations=1`.
      echo: progress output, one line per row.

    Returns:
      Rows of `PASS_HEADER`: errors in degrees, moves in mean edges of the pass's input.
    """
    from dmd_jax.mesh import mean_edge_length

    denoise = denoise or _default_denoiser()
    rows = []
    for name, clean, faces in cases:
        for level in levels:
            seed = protocol.noise_seed(name, level)
            noisy = protocol.benchmark_noise(clean, faces, level, seed)
            once = np.asarray(denoise(noisy, faces, bundle, iterations=1), np.float64)
            twice = np.asarray(denoise(once, faces, bundle, iterations=1), np.float64)
            err = [_normal_error(x, clean, faces) for x in (once, twice)]
            moves = [
                float(np.linalg.norm(b - a, axis=1).mean() / mean_edge_length(a, faces))
                for a, b in ((noisy, once), (once, twice))
            ]
            rows.append([name, len(faces), float(level), seed, *err, *moves])
            if echo:
                echo(
                    f"{name} σ = {level}: one pass {err[0]:.2f}°, two {err[1]:.2f}°, "
                    f"first pass moved {moves[0]:.3f} edges"
                )
    return rows


def simulate_passes(rows: Sequence[Sequence], tolerance: float, level: float) -> float:
    """The mean error at `level` if the second pass ran where `move1 > tolerance`."""
    errs = [r[5] if r[6] > tolerance else r[4] for r in rows if r[2] == level]
    return float(np.mean(errs))


def fit_pass_tolerance(
    rows: Sequence[Sequence],
    tolerances: Sequence[float] = TOLERANCES,
    levels: Sequence[float] = protocol.NOISE_LEVELS,
) -> float:
    """The tolerance with the lowest mean of `simulate_passes` over `levels` (the
    smallest on ties).

    Raises:
      ValueError: `rows` hold none of `levels`.
    """
    if not any(r[2] in levels for r in rows):
        raise ValueError(f"no measurement at the levels {tuple(levels)}")
    scores = [np.mean([simulate_passes(rows, t, lv) for lv in levels]) for t in tolerances]
    return float(tolerances[int(np.argmin(scores))])


# --------------------------------------------------------------------------------------
# The pre-smoothing rule
# --------------------------------------------------------------------------------------


def condition_name(direction: str, level: float) -> str:
    """A noise condition's name in the rows and reports, e.g. `"normal 0.2"`."""
    return f"{direction} {level:g}"


def presmooth_rows(
    cases: Sequence[Case],
    bundle,
    conditions: Sequence[tuple[str, float]] = PRESMOOTH_CONDITIONS,
    *,
    denoise: Denoiser | None = None,
    echo: Callable[[str], None] | None = None,
) -> tuple[list[list], dict[str, float]]:
    """Per case and condition: the noisy roughness and the error after 0-20 steps.

    The noise is `protocol.benchmark_noise` in the condition's direction, seeded by a
    CRC32 of `"<file>|<condition>"`; each count of Laplacian steps
    (`presmooth.laplacian_steps`) is followed by `denoise(..., presmooth=0)` (the
    weights' pass rule, no pre-smoothing of its own).

    Returns:
      `(rows, clean_roughness)`: rows of `PRESMOOTH_HEADER` then the 21 errors, and the
      roughness of every clean case (a rule must leave those alone).
    """
    from dmd_jax import baselines
    from dmd_jax.presmooth import MAX_STEPS, laplacian_steps, roughness

    denoise = denoise or _default_denoiser()
    rows, clean_roughness = [], {}
    for name, clean, faces in cases:
        clean_roughness[name] = float(roughness(clean, faces))
        for direction, level in conditions:
            cond = condition_name(direction, level)
            seed = zlib.crc32(f"{name}|{cond}".encode())
            noisy = protocol.benchmark_noise(clean, faces, level, seed, direction)
            errs, x = [], noisy
            for k in range(MAX_STEPS + 1):
                if k:
                    x = laplacian_steps(x, faces, 1)
                errs.append(_normal_error(denoise(x, faces, bundle, presmooth=0), clean, faces))
            lap = _normal_error(baselines.run_baseline("laplacian", noisy, faces), clean, faces)
            rough = float(roughness(noisy, faces))
            rows.append([name, len(faces), cond, seed, rough, lap, *errs])
            if echo:
                echo(
                    f"{name} {cond}: roughness {rough:.1f}°, no steps {errs[0]:.2f}°, best "
                    f"{min(errs):.2f}° after {int(np.argmin(errs))}, Laplacian {lap:.2f}°"
                )
    return rows, clean_roughness


def presmooth_errors(
    rows: Sequence[Sequence],
    start: float,
    per_step: float,
    conditions: Sequence[tuple[str, float]] = PRESMOOTH_CONDITIONS,
) -> dict[str, float]:
    """The mean error per condition when every mesh gets the rule's steps."""
    from dmd_jax.presmooth import steps_for

    out = {}
    for direction, level in conditions:
        cond = condition_name(direction, level)
        errs = [r[6 + steps_for(r[4], start, per_step)] for r in rows if r[2] == cond]
        out[cond] = float(np.mean(errs))
    return out


def fit_presmooth(
    rows: Sequence[Sequence],
    clean_roughness: dict[str, float],
    starts: Sequence[float] = STARTS,
    per_steps: Sequence[float] = PER_STEPS,
    conditions: Sequence[tuple[str, float]] = PRESMOOTH_CONDITIONS,
) -> tuple[float, float, dict[str, float]]:
    """`(start, per_step, errors per condition)` of the best rule on the grid that gives
    no step to any clean mesh (the first of equals, starts then steps ascending).

    Raises:
      ValueError: every rule of the grid would smooth a clean mesh.
    """
    from dmd_jax.presmooth import steps_for

    best = None
    for start in starts:
        for per_step in per_steps:
            if any(steps_for(r, start, per_step) for r in clean_roughness.values()):
                continue  # would smooth a clean validation mesh
            errs = presmooth_errors(rows, start, per_step, conditions)
            score = float(np.mean(list(errs.values())))
            if best is None or score < best[0] - 1e-9:
                best = (score, float(start), float(per_step), errs)
    if best is None:
        raise ValueError("every rule of the grid pre-smooths a clean validation mesh")
    return best[1], best[2], best[3]


def read_presmooth_csv(path) -> tuple[list[list], dict[str, float]]:
    """`presmooth_rows`' output back from the CSV `benchmarks/quality/calibrate.py`
    writes (clean meshes are rows of condition `clean`), to refit without measuring."""
    rows, clean = [], {}
    with open(path, newline="") as fh:
        for rec in csv.reader(fh):
            if rec[0] == "mesh":
                continue
            if rec[2] == "clean":
                clean[rec[0]] = float(rec[4])
                continue
            rows.append([rec[0], int(rec[1]), rec[2], int(rec[3])] + [float(x) for x in rec[4:]])
    return rows, clean


def read_pass_csv(path) -> list[list]:
    """`pass_rows`' output back from its CSV, to refit without measuring."""
    with open(path, newline="") as fh:
        return [
            [r[0], int(r[1]), float(r[2]), int(r[3]), *(float(x) for x in r[4:])]
            for r in csv.reader(fh)
            if r[0] != "mesh"
        ]


# --------------------------------------------------------------------------------------
# Both
# --------------------------------------------------------------------------------------


def fitted_policy(policy, *, pass_tolerance=None, presmooth=None):
    """`policy` with a fitted pass tolerance and/or pre-smoothing rule.

    Args:
      policy: the weights' current `DenoisePolicy`.
      pass_tolerance: the fitted tolerance, or None to keep the policy's; a tolerance
        needs more than one pass to choose from, so a one-pass policy gets
        `DEFAULT_MAX_PASSES`.
      presmooth: `(start, per_step)`, or None to keep the policy's.
    """
    out = policy
    if pass_tolerance is not None:
        passes = policy.max_passes if policy.max_passes > 1 else DEFAULT_MAX_PASSES
        out = out.replace(pass_tolerance=float(pass_tolerance), max_passes=passes)
    if presmooth is not None:
        out = out.replace(
            presmooth_start=float(presmooth[0]), presmooth_per_step=float(presmooth[1])
        )
    return out


def calibrate(
    bundle,
    val_dir=None,
    *,
    denoise: Denoiser | None = None,
    pass_cases: Sequence[Case] | None = None,
    presmooth_cases: Sequence[Case] | None = None,
    echo: Callable[[str], None] | None = None,
    fit_passes: bool | None = None,
) -> Calibration:
    """Fits the pass tolerance, then the pre-smoothing rule under it.

    Args:
      bundle: the weights (`checkpoints.ModelBundle`); its policy is the starting point.
      val_dir: the real training meshes (default `protocol.validation_dir()`).
      denoise: the denoiser (default `dmd_jax.inference.denoise`).
      pass_cases, presmooth_cases: the cases to measure (default: the validation split,
        cropped to `protocol.MAX_FACES` and `PRESMOOTH_MAX_FACES` faces).
      echo: progress output.
      fit_passes: whether to fit the pass tolerance. None: only for a network trained
        one pass at a time (`TrainConfig.passes == 1`); a network trained as a cascade
        keeps the passes of its policy (`policy.trained_policy`), and no pass rows are
        measured.

    Returns:
      A `Calibration`; its `policy` carries the fitted rules.
    """
    if fit_passes is None:
        fit_passes = bundle.config is None or bundle.config.train.passes == 1
    if presmooth_cases is None:
        presmooth_cases = validation_cases(val_dir, PRESMOOTH_MAX_FACES)
    p_rows, policy = [], bundle.policy
    if fit_passes:
        if pass_cases is None:
            pass_cases = validation_cases(val_dir)
        p_rows = pass_rows(pass_cases, bundle, denoise=denoise, echo=echo)
        policy = fitted_policy(policy, pass_tolerance=fit_pass_tolerance(p_rows))
    # The pre-smoothing is measured with the pass rule in force.
    bundle = bundle._replace(policy=policy)
    s_rows, clean = presmooth_rows(presmooth_cases, bundle, denoise=denoise, echo=echo)
    start, per_step, errs = fit_presmooth(s_rows, clean)
    policy = fitted_policy(policy, presmooth=(start, per_step))
    return Calibration(policy, p_rows, s_rows, clean, errs)


# --------------------------------------------------------------------------------------
# The learned pre-smoothing choice
# --------------------------------------------------------------------------------------

# The condition kind of `LEARN_CONDITIONS` for Gaussian noise per coordinate
# (`protocol.benchmark_noise(..., direction="isotropic")`, in mean edges).
ISOTROPIC = "isotropic"
# What the learned choice is fitted on: the *training* split of the real meshes (the
# validation split stays for choosing and reporting), crops of at most this many faces,
# these conditions (`protocol.NoiseCondition`; None: the clean mesh, which must get no
# steps), and the counts the choice picks from (those of
# `benchmarks/quality/policy_headroom.py`, whose validation rows then score it).
LEARN_MAX_FACES = 8_000
LEARN_CONDITIONS = (
    *(protocol.NoiseCondition(protocol.NOISE_KIND, s) for s in (0.05, 0.1, 0.2, 0.3, 0.45, 0.6)),
    protocol.NoiseCondition("impulse", 0.3),
    protocol.NoiseCondition("impulse", 0.6),
    None,
    # Gaussian noise per coordinate (the paper's Table II kind: a tangential part too),
    # `ISOTROPIC`-kind entries (added 2026-12-03: without them the choice left Table II's
    # Lion, 0.3 edges per coordinate, to the network alone).
    *(protocol.NoiseCondition(ISOTROPIC, s) for s in (0.3, 0.6, 1.0)),
)
LEARN_GRID = (0, 1, 2, 3, 4, 6, 8, 11)
# The network-free routes (`routes.run_route`: range σ, passes) the choice may also take.
LEARN_ROUTES = ((0.2, 60), (0.35, 60))
# The training noise draws differ from the benchmark's of the same mesh and condition.
LEARN_SEED_OFFSET = 7
# Neighbour counts tried, chosen by cross-validation over whole training meshes.
LEARN_NEIGHBOURS = (5, 10, 20, 40)
LEARN_FOLDS = 5
LEARN_DECIMALS = 4


def learn_header(grid: Sequence[int] = LEARN_GRID) -> tuple[str, ...]:
    """The columns of `learn_rows`: the case, its features, the rule's steps, the errors."""
    from dmd_jax.presmooth import FEATURE_NAMES

    return (
        "mesh",
        "noise",
        "level",
        "seed",
        *FEATURE_NAMES,
        "rule_steps",
        *(f"error_{k}" for k in grid),
    )


def training_cases(train_dir=None, max_faces: int = LEARN_MAX_FACES) -> list[Case]:
    """The training-split meshes of `train_dir` (default `protocol.validation_dir()`, the
    folder both splits live in), cropped as `validation_cases` crops."""
    from dmd_jax.data.real import mesh_files

    folder = protocol.validation_dir() if train_dir is None else train_dir
    return _cases(mesh_files(folder, "train"), max_faces)


def learn_draw(name: str, clean, faces, cond) -> tuple[str, float, int, np.ndarray]:
    """`(kind, level, seed, noisy)` of one training case under one of `LEARN_CONDITIONS`
    (None: the clean mesh); the seeds differ from the benchmark's by `LEARN_SEED_OFFSET`."""
    if cond is None:
        return "clean", 0.0, 0, clean
    kind, level = cond.kind, float(cond.level)
    if kind == ISOTROPIC:
        seed = zlib.crc32(f"{name}|{kind}|{level:g}".encode()) + LEARN_SEED_OFFSET
        return kind, level, seed, protocol.benchmark_noise(clean, faces, level, seed, "isotropic")
    seed = protocol.condition_seed(name, cond) + LEARN_SEED_OFFSET
    return kind, level, seed, protocol.condition_noise(clean, faces, cond, seed)


def route_errors(noisy, clean, faces, routes) -> list[float]:
    """The normal error of each network-free route (`routes.field_route`; `(sigma_r,
    passes)` pairs) on one noisy mesh, run in its mean-edge frame as `denoise` runs it."""
    from dmd_jax.routes import run_route

    return [_normal_error(run_route(noisy, faces, s, p), clean, faces) for s, p in routes]


def learn_rows(
    cases: Sequence[Case],
    bundle,
    conditions=LEARN_CONDITIONS,
    grid: Sequence[int] = LEARN_GRID,
    *,
    denoise: Denoiser | None = None,
    echo: Callable[[str], None] | None = None,
) -> list[list]:
    """Per case and condition: the noisy mesh's features, the steps the weights' own
    rule gives it and the normal error after each count of `grid` (`learn_header`).

    Each count runs `denoise(..., presmooth=k)` (the weights' pass rule after it).
    """
    from dmd_jax.presmooth import noise_features

    denoise = denoise or _default_denoiser()
    rows = []
    for name, clean, faces in cases:
        for cond in conditions:
            kind, level, seed, noisy = learn_draw(name, clean, faces, cond)
            _, info = denoise(noisy, faces, bundle, return_info=True)
            errs = [
                _normal_error(denoise(noisy, faces, bundle, presmooth=k), clean, faces)
                for k in grid
            ]
            rows.append(
                [
                    name,
                    kind,
                    level,
                    seed,
                    *noise_features(noisy, faces),
                    info.presmooth_steps,
                    *errs,
                ]
            )
            if echo:
                echo(
                    f"{name} {kind} {level:g}: best {min(errs):.2f}° after "
                    f"{grid[int(np.argmin(errs))]} steps, rule {info.presmooth_steps}"
                )
    return rows


def read_learn_csv(path, grid: Sequence[int] = LEARN_GRID) -> list[list]:
    """`learn_rows`' output back from its CSV (numbers parsed)."""
    header = learn_header(grid)
    return [
        [
            r["mesh"],
            r["noise"],
            float(r["level"]),
            int(r["seed"]),
            *(float(r[h]) for h in header[4 : -len(grid) - 1]),
            int(r["rule_steps"]),
            *(float(r[h]) for h in header[-len(grid) :]),
        ]
        for r in _csv_records(path, header)
    ]


def _csv_records(path, header: tuple[str, ...]) -> list[dict]:
    """The records of a CSV whose columns must be `header`, as dicts of strings.

    Raises:
      ValueError: other columns.
    """
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != header:
            raise ValueError(f"{path}: expected the columns {list(header)}")
        return list(reader)


def _split_rows(rows: Sequence[Sequence], grid: Sequence[int]):
    n = len(grid)
    features = np.array([r[4 : -n - 1] for r in rows], np.float64)
    errors = np.array([r[-n:] for r in rows], np.float64)
    return features, errors


class LearnedPresmooth(NamedTuple):
    """A fitted learned pre-smoothing choice: the `DenoisePolicy` fields it sets."""

    grid: tuple[int, ...]
    center: tuple[float, ...]
    scale: tuple[float, ...]
    examples: tuple[float, ...]
    regrets: tuple[float, ...]
    neighbours: int
    cv_regret: dict[int, float]  # neighbours -> cross-validated geometric-mean regret
    routes: tuple[tuple[float, int], ...] = ()  # network-free routes, after the counts

    def policy_fields(self) -> dict:
        return {
            "presmooth_grid": self.grid,
            "presmooth_center": self.center,
            "presmooth_scale": self.scale,
            "presmooth_examples": self.examples,
            "presmooth_regrets": self.regrets,
            "presmooth_neighbours": self.neighbours,
            "route_sigmas": tuple(float(s) for s, _ in self.routes),
            "route_passes": tuple(int(p) for _, p in self.routes),
        }

    def choose_options(self, features) -> np.ndarray:
        """`[n]` chosen option indices (the grid's counts, then the routes) for
        `[n, n_features]` features."""
        return _choose(
            len(self.grid) + len(self.routes),
            self.center,
            self.scale,
            self.examples,
            self.regrets,
            self.neighbours,
            features,
        )

    def choose(self, features) -> np.ndarray:
        """`[n]` chosen counts for `[n, n_features]` features (a fit without routes)."""
        if self.routes:
            raise ValueError("a fit with routes chooses options: use choose_options")
        return np.asarray(self.grid)[self.choose_options(features)]


def _choose(n_options, center, scale, examples, regrets, neighbours, features) -> np.ndarray:
    from dmd_jax.presmooth import learned_option

    return np.array(
        [
            learned_option(f, n_options, center, scale, examples, regrets, neighbours)
            for f in features
        ],
        int,
    )


def _standardise(features):
    center = features.mean(axis=0)
    scale = features.std(axis=0)
    return center, np.where(scale > 1e-9, scale, 1.0)


def regret_of(errors: np.ndarray, chosen_index: np.ndarray) -> float:
    """Geometric mean over cases of the chosen count's error over the best count's."""
    picked = errors[np.arange(len(errors)), chosen_index]
    return float(np.exp(np.mean(np.log(picked / errors.min(axis=1)))))


def fit_learned_presmooth(
    rows: Sequence[Sequence],
    grid: Sequence[int] = LEARN_GRID,
    *,
    neighbours: Sequence[int] = LEARN_NEIGHBOURS,
    folds: int = LEARN_FOLDS,
    routes: Sequence[tuple[float, int]] = (),
    route_errors=None,
) -> LearnedPresmooth:
    """Fits the learned choice on `learn_rows` (the training split).

    Every row becomes an example: its standardised features and the regret of each
    option (each count of `grid`, then each route), `log(error / best error of the
    case)` (`presmooth.learned_option`). The number of neighbours is the one of
    `neighbours` with the lowest regret of the choice in `folds`-fold cross-validation
    that holds out whole meshes (a mesh's conditions are never split between the
    examples and the cases scored).

    Args:
      rows: `learn_rows`.
      grid: the counts of the rows' error columns.
      neighbours, folds: the neighbour counts tried and the cross-validation folds.
      routes: network-free routes (`(sigma_r, passes)`, `routes.run_route`) the choice
        may also take.
      route_errors: `[len(rows), len(routes)]` their errors on the same cases, in the
        same order (`route_errors` of each case's `learn_draw`).

    Raises:
      ValueError: fewer meshes than folds, fewer rows than a neighbour count, route
        errors of the wrong shape, or an error that is not positive and finite.
    """
    grid = tuple(int(k) for k in grid)
    routes = tuple((float(s), int(p)) for s, p in routes)
    features, errors = _split_rows(rows, grid)
    if routes:
        extra = np.asarray(route_errors, np.float64)
        if extra.shape != (len(rows), len(routes)):
            raise ValueError(
                f"route_errors must have shape {(len(rows), len(routes))}, got {extra.shape}"
            )
        errors = np.concatenate([errors, extra], axis=1)
    table = _fit_nearest(features, errors, [r[0] for r in rows], neighbours, folds)
    return LearnedPresmooth(grid, *table, routes)


class _NearestTable(NamedTuple):
    center: tuple[float, ...]
    scale: tuple[float, ...]
    examples: tuple[float, ...]
    regrets: tuple[float, ...]
    neighbours: int
    cv_regret: dict[int, float]


def _fit_nearest(features, errors, meshes, neighbours, folds) -> _NearestTable:
    """A nearest-neighbour choice among the columns of `errors` `[n_case, n_option]`
    from `features` `[n_case, n_feature]`, its neighbour count chosen among `neighbours`
    by `folds`-fold cross-validation holding out whole meshes (`meshes`: each case's)."""
    if not (np.all(np.isfinite(errors)) and np.all(errors > 0)):
        raise ValueError("the errors must be positive and finite")
    names = sorted(set(meshes))
    if len(names) < folds:
        raise ValueError(f"{len(names)} meshes: cross-validation needs at least {folds}")
    regrets = np.log(errors / errors.min(axis=1, keepdims=True))
    fold_of = {m: i % folds for i, m in enumerate(names)}
    fold = np.array([fold_of[m] for m in meshes])
    cv = {}
    for k in neighbours:
        if k > int((fold != 0).sum()):
            raise ValueError(f"{len(meshes)} rows are too few for {k} neighbours")
        chosen = np.zeros(len(meshes), int)
        for f in range(folds):
            train, test = fold != f, fold == f
            center, scale = _standardise(features[train])
            chosen[test] = _choose(
                errors.shape[1],
                center,
                scale,
                ((features[train] - center) / scale).ravel(),
                regrets[train].ravel(),
                k,
                features[test],
            )
        cv[int(k)] = regret_of(errors, chosen)
    best = min(cv, key=cv.get)
    center, scale = _standardise(features)

    def stored(x):
        # Four decimals of standardised features and of log ratios keep the weights
        # file small; 1e-4 of a standard deviation is far below the features' own noise.
        return tuple(round(float(v), LEARN_DECIMALS) for v in np.ravel(x))

    return _NearestTable(
        tuple(map(float, center)),
        tuple(map(float, scale)),
        stored((features - center) / scale),
        stored(regrets),
        best,
        cv,
    )


# The review (`dmd_jax.review`): fitted on the same training cases as the learned choice,
# those where the choice runs the network.
REVIEW_ROUTE = 0  # the route of `LEARN_ROUTES` whose result the review compares
# The cascades the review may take (a route's field and vertex update on the network's
# result): the lighter fields and counts of the cascade study (docs/history.md,
# 2026-12-05 evening), measured beside the routes.
REVIEW_CASCADES = ((0.2, 4), (0.2, 16), (0.2, 60), (0.35, 16), (0.35, 60))


def review_header(
    routes: Sequence[tuple[float, int]] = LEARN_ROUTES,
    cascades: Sequence[tuple[float, int]] = REVIEW_CASCADES,
) -> tuple[str, ...]:
    """The columns of `review_rows`: the case, the noisy mesh's features (for study: the
    review does not read them), the output features, the network's error, each route's
    and each cascade's."""
    from dmd_jax.presmooth import FEATURE_NAMES
    from dmd_jax.review import OUTPUT_FEATURE_NAMES

    return (
        "mesh",
        "noise",
        "level",
        "seed",
        *FEATURE_NAMES,
        *OUTPUT_FEATURE_NAMES,
        "error_network",
        *(f"error_route_{s:g}_{p}" for s, p in routes),
        *(f"error_cascade_{s:g}_{p}" for s, p in cascades),
    )


def review_rows(
    cases: Sequence[Case],
    bundle,
    conditions=LEARN_CONDITIONS,
    *,
    draw: Callable | None = None,
    review_route: int = REVIEW_ROUTE,
    cascades: Sequence[tuple[float, int]] = REVIEW_CASCADES,
    denoise: Denoiser | None = None,
    echo: Callable[[str], None] | None = None,
) -> list[list]:
    """Per case and condition where the weights' policy runs the network (its learned
    choice takes no route): what the review reads and each option's normal error
    (`review_header`).

    Args:
      cases: the crops.
      bundle: weights whose policy has the learned choice and routes (its review, if
        any, is switched off here).
      conditions: noise conditions (None: the clean mesh).
      draw: `(name, clean, faces, cond) -> (kind, level, seed, noisy)`; default
        `learn_draw` (the training draws).
      review_route: the route whose result the features compare.
      cascades: `(sigma_r, passes)` of the cascades measured (`routes.run_route` on the
        network's result).
      denoise, echo: the denoiser and a progress printer.
    """
    from dmd_jax.presmooth import noise_features
    from dmd_jax.review import review_features
    from dmd_jax.routes import run_route

    policy = bundle.policy.without_review()
    routes = list(zip(policy.route_sigmas, policy.route_passes, strict=True))
    if not routes:
        raise ValueError("the weights' policy has no routes to review against")
    bundle = bundle._replace(policy=policy)
    denoise = denoise or _default_denoiser()
    draw = draw or learn_draw
    sigma, passes = routes[review_route]
    rows = []
    for name, clean, faces in cases:
        for cond in conditions:
            kind, level, seed, noisy = draw(name, clean, faces, cond)
            out, info = denoise(noisy, faces, bundle, return_info=True)
            if info.path == "route":
                continue
            errors = [_normal_error(out, clean, faces)] + [
                _normal_error(run_route(start, faces, s, p), clean, faces)
                for start, pairs in ((noisy, routes), (out, cascades))
                for s, p in pairs
            ]
            rows.append(
                [
                    name,
                    kind,
                    level,
                    seed,
                    *noise_features(noisy, faces),
                    *review_features(noisy, out, faces, sigma, passes),
                    *errors,
                ]
            )
            if echo:
                echo(f"{name} {kind} {level:g}: " + " ".join(f"{e:.2f}" for e in errors))
    return rows


def read_review_csv(
    path,
    routes: Sequence[tuple[float, int]] = LEARN_ROUTES,
    cascades: Sequence[tuple[float, int]] = REVIEW_CASCADES,
) -> list[list]:
    """`review_rows`' output back from its CSV (numbers parsed)."""
    header = review_header(routes, cascades)
    return [
        [r["mesh"], r["noise"], float(r["level"]), int(r["seed"])]
        + [float(r[h]) for h in header[4:]]
        for r in _csv_records(path, header)
    ]


def review_arrays(rows: Sequence[Sequence], n_options: int):
    """`(features, errors)` `[n, len(review.OUTPUT_FEATURE_NAMES)]`, `[n, n_options]` of
    `review_rows`: what the review reads, and each option's error (the network, the
    routes, the cascades)."""
    from dmd_jax.presmooth import FEATURE_NAMES

    n = n_options
    return (
        np.array([r[4 + len(FEATURE_NAMES) : -n] for r in rows], np.float64),
        np.array([r[-n:] for r in rows], np.float64),
    )


class LearnedReview(NamedTuple):
    """A fitted review: the `DenoisePolicy` fields it sets."""

    route: int
    center: tuple[float, ...]
    scale: tuple[float, ...]
    examples: tuple[float, ...]
    regrets: tuple[float, ...]
    neighbours: int
    cv_regret: dict[int, float]  # neighbours -> cross-validated geometric-mean regret
    cascades: tuple[tuple[float, int], ...] = ()  # the cascades of the second choice
    cascade_regrets: tuple[float, ...] = ()
    cascade_neighbours: int = 0
    cascade_cv_regret: dict[int, float] | None = None  # as cv_regret, for the second

    def policy_fields(self) -> dict:
        return {
            "review_route": self.route,
            "review_center": self.center,
            "review_scale": self.scale,
            "review_examples": self.examples,
            "review_regrets": self.regrets,
            "review_neighbours": self.neighbours,
            "cascade_sigmas": tuple(s for s, _ in self.cascades),
            "cascade_passes": tuple(p for _, p in self.cascades),
            "cascade_regrets": self.cascade_regrets,
            "cascade_neighbours": self.cascade_neighbours,
        }

    def choose_options(self, features) -> np.ndarray:
        """`[n]` chosen options for `[n, n_features]` features, as `review.review_choice`
        chooses them: 0 the network's result, `1 + i` route `i`, `1 + n_route + j`
        cascade `j`."""
        n_route = len(self.regrets) * len(self.center) // len(self.examples) - 1
        table = (self.center, self.scale, self.examples)
        chosen = _choose(1 + n_route, *table, self.regrets, self.neighbours, features)
        if not self.cascades:
            return chosen
        cascade = _choose(
            1 + len(self.cascades), *table, self.cascade_regrets, self.cascade_neighbours, features
        )
        return np.where((chosen == 0) & (cascade > 0), n_route + cascade, chosen)


def fit_review(
    rows: Sequence[Sequence],
    n_routes: int,
    cascades: Sequence[tuple[float, int]] = REVIEW_CASCADES,
    *,
    offered: Sequence[tuple[float, int]] | None = None,
    route: int = REVIEW_ROUTE,
    neighbours: Sequence[int] = LEARN_NEIGHBOURS,
    folds: int = LEARN_FOLDS,
) -> LearnedReview:
    """Fits the review on `review_rows` of the training split, as
    `fit_learned_presmooth` fits the choice: its first choice over the network's result
    and each route's, its second over the network's result and each offered cascade's,
    both from the same features and examples, each with its neighbour count chosen by
    cross-validation over whole meshes.

    Args:
      rows: `review_rows` measured with `n_routes` routes and `cascades`.
      n_routes: the routes of the rows (all are offered).
      cascades: the cascades of the rows' error columns.
      offered: the cascades the review may take, a subset of `cascades` (default: all;
        `()`: none, the first choice only).
      route, neighbours, folds: the compared route, the neighbour counts tried and the
        cross-validation folds.

    Raises:
      ValueError: an offered cascade the rows do not measure, or as `_fit_nearest`.
    """
    cascades = [(float(s), int(p)) for s, p in cascades]
    offered = cascades if offered is None else [(float(s), int(p)) for s, p in offered]
    missing = [c for c in offered if c not in cascades]
    if missing:
        raise ValueError(f"cascades {missing} are not among the measured {cascades}")
    features, errors = review_arrays(rows, 1 + n_routes + len(cascades))
    meshes = [r[0] for r in rows]
    first = _fit_nearest(features, errors[:, : 1 + n_routes], meshes, neighbours, folds)
    if not offered:
        return LearnedReview(route, *first)
    columns = [0, *(1 + n_routes + cascades.index(c) for c in offered)]
    second = _fit_nearest(features, errors[:, columns], meshes, neighbours, folds)
    return LearnedReview(
        route, *first, tuple(offered), second.regrets, second.neighbours, second.cv_regret
    )
