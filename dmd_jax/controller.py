"""The learned smoothing controller: how much to smooth, chosen per mesh.

The amount of smoothing decides more of the result than anything else measured: a
light-noise scan of fine detail wants none, a depth-camera scan twenty Laplacian steps
and eight network passes. The controller reads the scale-free statistics of a noisy
mesh (`controller_features`) and scores every option of the search grid of
`data.smoothing_set`: none (the mesh as given), Laplacian pre-smoothing alone, or
pre-smoothing followed by 1-8 network passes with the Jacobi or the converged vertex
update. It is a small MLP trained on generated examples to minimise the expected
relative regret of its choice: `sum_o softmax(s)_o (E_o − E_best) / (E_best + ε)`,
where `E_o` is option `o`'s mean face-normal error on the example.

What it is apart from how it is used: `ControllerParams` (arrays and the option list,
stored as a section of the weights file), `scores`, `choose`, `fit`, `evaluate`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# Relative regret's floor (degrees): on a clean mesh the best error is 0, and a choice
# that changes it by 0.1° is not infinitely worse.
REGRET_FLOOR_DEG = 0.5


class Option(NamedTuple):
    """One amount of smoothing: Laplacian steps, then `passes` network passes with
    `update` (None when `passes` is 0)."""

    presmooth: int
    update: str | None
    passes: int

    @property
    def label(self) -> str:
        """`p8` (pre-smoothing alone; `p0` is none), `p8_solve_4`: the reports' name."""
        if not self.passes:
            return f"p{self.presmooth}"
        return f"p{self.presmooth}_{self.update}_{self.passes}"


def options(presmooth_grid, updates, max_passes: int) -> list[Option]:
    """Every option of a search grid, "none" (`Option(0, None, 0)`) first."""
    out = [Option(p, None, 0) for p in presmooth_grid]
    out += [
        Option(p, u, k) for p in presmooth_grid for u in updates for k in range(1, max_passes + 1)
    ]
    return out


def option_errors(errors: np.ndarray, presmooth_grid, updates, max_passes: int) -> np.ndarray:
    """`[n, n_option]`: the search table `[n, P, U, K + 1]` laid out as `options(...)`."""
    cols = [errors[:, p, 0, 0] for p in range(len(presmooth_grid))]
    cols += [
        errors[:, p, u, k]
        for p in range(len(presmooth_grid))
        for u in range(len(updates))
        for k in range(1, max_passes + 1)
    ]
    return np.stack(cols, axis=1)


# How the statistics are read before standardisation. "log1p": `log(1 + max(x, 0))`,
# which evens out the heavy tails of the roughness angles and displacements (a scan's
# 60° against a fine mesh's 2°) that a standardised MLP otherwise spends its width on:
# on the generated validation split 1.117-1.119 of the oracle against 1.167-1.182 raw
# (width 32, four seeds; benchmarks/results/controller.md). "identity": as computed
# (controllers stored before the field existed).
TRANSFORMS = ("identity", "log1p")


def transform(feats: np.ndarray, kind: str) -> np.ndarray:
    """`feats [..., F]` as the controller reads them (`TRANSFORMS`)."""
    x = np.asarray(feats, np.float64)
    if kind == "log1p":
        return np.log1p(np.maximum(x, 0.0))
    if kind == "identity":
        return x
    raise ValueError(f"unknown statistics transform {kind!r} (one of {TRANSFORMS})")


class ControllerParams(NamedTuple):
    """A trained controller: feature standardisation, the MLP, the options it scores."""

    mean: np.ndarray  # [F]
    scale: np.ndarray  # [F]
    w1: np.ndarray  # [F, H]
    b1: np.ndarray  # [H]
    w2: np.ndarray  # [H, O]
    b2: np.ndarray  # [O]
    options: tuple  # O Options
    transform: str = "identity"  # TRANSFORMS: applied to the statistics before `mean`

    def to_dict(self) -> dict:
        """Plain arrays and lists (a weights file's `controller` section)."""
        arrays = {
            k: np.asarray(getattr(self, k), np.float32)
            for k in ("mean", "scale", "w1", "b1", "w2", "b2")
        }
        return {
            **arrays,
            "options": [[o.presmooth, o.update or "", o.passes] for o in self.options],
            "transform": self.transform,
        }

    def to_json(self) -> dict:
        """`to_dict` with lists for arrays (a JSON section)."""
        return {
            k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in self.to_dict().items()
        }

    @classmethod
    def from_dict(cls, d: dict) -> ControllerParams:
        """The inverse of `to_dict`, checking shapes.

        Raises:
          ValueError: a missing field or inconsistent shapes.
        """
        try:
            arrays = {
                k: np.asarray(d[k], np.float64) for k in ("mean", "scale", "w1", "b1", "w2", "b2")
            }
            opts = tuple(Option(int(p), str(u) or None, int(k)) for p, u, k in d["options"])
            kind = str(d.get("transform", "identity"))
            if kind not in TRANSFORMS:
                raise ValueError(f"unknown transform {kind!r}")
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"the controller section is malformed ({err})") from None
        f, h = arrays["w1"].shape
        if (
            arrays["mean"].shape != (f,)
            or arrays["scale"].shape != (f,)
            or arrays["b1"].shape != (h,)
            or arrays["w2"].shape != (h, len(opts))
            or arrays["b2"].shape != (len(opts),)
        ):
            raise ValueError("the controller section's arrays have inconsistent shapes")
        if not all(np.all(np.isfinite(a)) for a in arrays.values()):
            raise ValueError("the controller section holds non-finite numbers")
        return cls(**arrays, options=opts, transform=kind)


def scores(params: ControllerParams, feats: np.ndarray) -> np.ndarray:
    """`[..., O]` scores (higher: better) of `[..., F]` statistics."""
    x = (transform(feats, params.transform) - params.mean) / params.scale
    h = np.maximum(x @ params.w1 + params.b1, 0.0)
    return h @ params.w2 + params.b2


def crop_scores(params: ControllerParams, feats: np.ndarray, crop_mask=None) -> np.ndarray:
    """`[n, O]` scores of meshes read in crops: `[n, C, F]` statistics (`crop_mask`
    `[n, C]`: which are real; None: all), each mesh's mean over its crops (`decide`)."""
    s = scores(params, feats)
    if crop_mask is None:
        return s.mean(axis=1)
    m = np.asarray(crop_mask, np.float64)[..., None]
    return (s * m).sum(axis=1) / m.sum(axis=1)


def choose(params: ControllerParams, feats: np.ndarray) -> Option:
    """The option the controller picks for one mesh's statistics `[F]`."""
    return params.options[int(np.argmax(scores(params, feats)))]


def relative_regret(errors: np.ndarray) -> np.ndarray:
    """`[n, O]`: `(E_o − E_best) / (E_best + REGRET_FLOOR_DEG)` per example."""
    best = errors.min(axis=1, keepdims=True)
    return (errors - best) / (best + REGRET_FLOOR_DEG)


def fit(
    feats: np.ndarray,
    errors: np.ndarray,
    opts: list[Option],
    *,
    hidden: int = 32,
    l2: float = 1e-3,
    steps: int = 3000,
    lr: float = 3e-3,
    seed: int = 0,
    kind: str = "log1p",
    objective: str = "softmax",
    crop_mask: np.ndarray | None = None,
) -> ControllerParams:
    """Trains a controller on examples (full batch, Adam): reproducible for a seed.

    Args:
      feats: `[n, F]` statistics, or `[n, C, F]`: each example read in up to `C` crops
        (`controller_features.crops`), its scores the mean over its crops, as `decide`
        reads a large mesh (a whole mesh's best option is then learned from the crops
        the controller will see of it).
      errors: `[n, O]` every option's error (`option_errors`).
      opts: the `O` options.
      hidden: the MLP's width.
      l2: weight decay on both layers' weights.
      steps, lr: Adam's steps and learning rate.
      seed: the initialisation's seed.
      kind: how the statistics are read (`TRANSFORMS`).
      objective: "softmax": minimise the expected relative regret of a softmax over the
        scores (the scores are a policy); "regret": regress each option's relative
        regret (squared error), the scores its negation, so the choice is the option of
        least predicted mean regret (safer where the examples disagree: an option that is
        best on some neighbours and 2× worse on others predicts a high mean).
      crop_mask: `[n, C]` bool, which crops of `[n, C, F]` statistics are real (each
        example has at least one); None: all.

    Raises:
      ValueError: an unknown objective, or statistics, errors and mask of inconsistent
        shapes.
    """
    if objective not in ("softmax", "regret"):
        raise ValueError(f"unknown objective {objective!r}")
    import jax
    import jax.numpy as jnp
    import optax

    feats = np.asarray(feats, np.float64)
    if feats.ndim == 2:
        feats = feats[:, None, :]
    if feats.ndim != 3 or len(feats) != len(errors):
        raise ValueError(f"statistics {feats.shape} for errors {np.shape(errors)}")
    mask = np.ones(feats.shape[:2], bool) if crop_mask is None else np.asarray(crop_mask, bool)
    if mask.shape != feats.shape[:2] or not mask.any(axis=1).all():
        raise ValueError(f"crop mask {mask.shape} for statistics {feats.shape}, or an empty row")
    feats = transform(feats, kind)
    rows = feats[mask]  # every real crop counts once in the standardisation
    mean = rows.mean(axis=0)
    scale = np.where(rows.std(axis=0) > 1e-9, rows.std(axis=0), 1.0)
    x = jnp.asarray(np.where(mask[..., None], (feats - mean) / scale, 0.0), jnp.float32)
    w = jnp.asarray(mask / mask.sum(axis=1, keepdims=True), jnp.float32)  # [n, C]
    regret = jnp.asarray(relative_regret(np.asarray(errors, np.float64)), jnp.float32)
    n_feat, n_opt = x.shape[2], regret.shape[1]
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    params = {
        "w1": jax.random.normal(k1, (n_feat, hidden)) * np.sqrt(2.0 / n_feat),
        "b1": jnp.zeros(hidden),
        "w2": jax.random.normal(k2, (hidden, n_opt)) * 0.01,
        "b2": jnp.zeros(n_opt),
    }

    def loss(p):
        h = jax.nn.relu(x @ p["w1"] + p["b1"])
        s = jnp.einsum("nc,nco->no", w, h @ p["w2"] + p["b2"])  # mean over real crops
        decay = jnp.sum(p["w1"] ** 2) + jnp.sum(p["w2"] ** 2)
        if objective == "regret":
            return jnp.mean((s + jnp.log1p(regret)) ** 2) + l2 * decay
        prob = jax.nn.softmax(s, axis=-1)
        return jnp.mean(jnp.sum(prob * regret, axis=-1)) + l2 * decay

    tx = optax.adam(lr)
    state = tx.init(params)

    @jax.jit
    def step(p, s):
        g = jax.grad(loss)(p)
        u, s = tx.update(g, s, p)
        return optax.apply_updates(p, u), s

    for _ in range(steps):
        params, state = step(params, state)
    p = jax.device_get(params)
    return ControllerParams(
        mean=mean,
        scale=scale,
        w1=np.asarray(p["w1"], np.float64),
        b1=np.asarray(p["b1"], np.float64),
        w2=np.asarray(p["w2"], np.float64),
        b2=np.asarray(p["b2"], np.float64),
        options=tuple(opts),
        transform=kind,
    )


def geomean(x) -> float:
    """The geometric mean of positive numbers."""
    x = np.asarray(x, np.float64)
    return float(np.exp(np.mean(np.log(x))))


def evaluate(chosen: np.ndarray, errors: np.ndarray, default: np.ndarray) -> dict:
    """How good a choice per example is, against the per-example oracle and today's default.

    Args:
      chosen: `[n]` option index per example.
      errors: `[n, O]`.
      default: `[n]` the default call's error.

    Returns:
      `to_oracle` (geometric mean of chosen / best error, each floored at
      `REGRET_FLOOR_DEG`), `to_default` (chosen / default, same floor), `worst_to_oracle`,
      `capture`: the share of the oracle's gain over the default (in log geometric mean)
      that the choice realises.
    """
    e = errors[np.arange(len(chosen)), chosen] + REGRET_FLOOR_DEG
    best = errors.min(axis=1) + REGRET_FLOOR_DEG
    base = np.asarray(default) + REGRET_FLOOR_DEG
    gain = np.log(geomean(base)) - np.log(geomean(best))
    got = np.log(geomean(base)) - np.log(geomean(e))
    return {
        "to_oracle": geomean(e / best),
        "worst_to_oracle": float(np.max(e / best)),
        "to_default": geomean(e / base),
        "capture": float(got / gain) if gain > 0 else float("nan"),
    }


class Decision(NamedTuple):
    """What the controller chose for one mesh, and from what."""

    option: Option
    features: dict  # name -> value, the statistics it read

    def describe(self) -> str:
        """One line for `DenoiseInfo` (what it chose and the main statistics behind it)."""
        o = self.option
        what = (
            "none (the mesh as given)"
            if o.passes == 0 and o.presmooth == 0
            else f"{o.presmooth} pre-smoothing steps"
            + (f", {o.passes} passes ({o.update} update)" if o.passes else ", no network pass")
        )
        f = self.features
        return (
            f"controller: {what}; from roughness {f['rough_q50']:.1f}° (median), "
            f"distance to the neighbours' planes {f['plane_rms']:.3f} edges, tangential "
            f"{f['tangent_rms']:.2f} edges, edge spread {f['edge_spread']:.2f}, anisotropy "
            f"{f['disp_anisotropy']:.2f}, roughness kept after 16 steps "
            f"{f['rough_ratio_16']:.2f}"
        )


def decide(params: ControllerParams, vertices, faces) -> Decision:
    """The controller's choice for one mesh (every vertex referenced): read whole when it
    is small, else in crops (`controller_features.crops`), the scores averaged.

    Args:
      params: the trained controller.
      vertices: `[n_vertex, 3]` noisy positions, any frame.
      faces: `[n_face, 3]`.
    """
    from dmd_jax.controller_features import FEATURE_NAMES, crops, features

    feats = np.array([features(v, f) for v, f in crops(vertices, faces)])
    if params.mean.shape[0] != feats.shape[1]:
        raise ValueError(
            f"the controller reads {params.mean.shape[0]} statistics, this dmd_jax computes "
            f"{feats.shape[1]}: retrain it (scripts/train_controller.py)"
        )
    # A large mesh is read crop by crop: the option best on average over its crops.
    best = int(np.argmax(crop_scores(params, feats[None])[0]))
    mean = feats.mean(axis=0)
    return Decision(params.options[best], dict(zip(FEATURE_NAMES, mean.tolist(), strict=True)))
