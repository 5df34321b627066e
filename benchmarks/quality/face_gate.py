"""A per-face choice between the network's normals and the routes' (issue 29): measured.

The review (`dmd_jax.review`) chooses one option for the whole mesh: the network's
result, a route (a pre-filtered field alone, `dmd_jax.routes`) or a cascade. Even an
oracle over those options stays above 0.85 of the best other library method per shape on
the validation split (`review_learn.md`), so a per-mesh choice cannot reach issue 29's
target. A CAD part's flats are often cleaner in a route and its creases in the network's
result: choosing **per face** could beat every per-mesh choice. This script measures
whether a learned per-face gate does.

For every validation crop and `make sota-lite` condition (validation split only; the
test meshes are never read) it runs the bundled weights' network (review off), the
σ 0.2 and σ 0.35 routes on the noisy mesh and a cascade (σ 0.2, 16 passes) on the
network's result; per face it reads how far the four normal fields are apart, how rough
each is around the face (mean and largest angle to its edge neighbours) and how far each
moved from the noisy normal. A softmax gate over the four fields, fitted to least
expected per-face normal error (each mesh weighted alike), picks a field per face; the
vertex update of the normal-first head (`routes.fit_vertices`, from the network's
result) then follows the picked normals. The gate is scored leaving each mesh out of its
own fit (all of that mesh's conditions), against the shipped default (review on), the
network alone, the oracle over the four whole-mesh results, and the per-face oracle of
the normals (not a mesh: the least of four errors per face, so it also profits from
per-face noise in the errors).

```bash
python benchmarks/quality/face_gate.py            # ~4 min measuring, ~3 min fitting
python benchmarks/quality/face_gate.py --reuse    # refit from out/face_gate/
```
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    best_others,
    environment,
    markdown_table,
    per_shape_cell,
    write_report,
)
from dmd_jax import calibrate, protocol  # noqa: E402

FIELDS = ("net", "r02", "r035", "casc")
FIELD_NAMES = {
    "net": "network",
    "r02": "route σ 0.2 ×60",
    "r035": "route σ 0.35 ×60",
    "casc": "cascade σ 0.2 ×16",
}
CACHE = Path("out/face_gate")
# Faces per mesh and condition in the gate's fit (each mesh weighted alike).
FIT_FACES = 2000


def measure(cache: Path, reuse: bool) -> list[Path]:
    """One `.npz` per validation crop and condition: clean, noisy, default and fields."""
    from dmd_jax.inference import as_bundle, denoise
    from dmd_jax.routes import run_route

    cache.mkdir(parents=True, exist_ok=True)
    no_review = as_bundle(None, None).policy.without_review()
    paths = []
    t0 = time.time()
    for case in calibrate.validation_cases():
        for cond in protocol.QUALITY_CONDITIONS:
            seed = protocol.condition_seed(case.name, cond)
            path = cache / f"{case.name}__{cond.kind}_{cond.level:g}__{seed}.npz"
            paths.append(path)
            if reuse and path.exists():
                continue
            noisy = protocol.condition_noise(case.clean, case.faces, cond, seed)
            net = denoise(noisy, case.faces, policy=no_review)
            arrays = {
                "clean": case.clean,
                "faces": case.faces,
                "noisy": noisy,
                "default": denoise(noisy, case.faces),
                "net": net,
                "r02": run_route(noisy, case.faces, 0.2, 60),
                "r035": run_route(noisy, case.faces, 0.35, 60),
                "casc": run_route(net, case.faces, 0.2, 16),
            }
            tmp = path.with_suffix(".tmp.npz")
            np.savez_compressed(tmp, **arrays)
            tmp.replace(path)
            print(f"{path.name}: {time.time() - t0:.0f} s", flush=True)
    return paths


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def _roughness(n, a, b, n_face):
    """Per face: mean and largest angle to the faces sharing an edge with it."""
    t = _angle(n[a], n[b])
    count = np.bincount(a, minlength=n_face) + np.bincount(b, minlength=n_face)
    mean = (np.bincount(a, t, n_face) + np.bincount(b, t, n_face)) / np.maximum(count, 1)
    largest = np.zeros(n_face)
    np.maximum.at(largest, a, t)
    np.maximum.at(largest, b, t)
    return mean, largest


def load_case(path: Path) -> dict:
    """A measured case with its per-face fields, errors and gate features."""
    from dmd_jax.mesh import face_normals_np
    from dmd_jax.topology import face_adjacency

    d = dict(np.load(path))
    f = d["faces"]
    a, b = face_adjacency(f, d["clean"].shape[0])
    normals = {k: face_normals_np(d[k], f) for k in ("clean", "noisy", *FIELDS)}
    log = lambda t: np.log(t + 0.5)  # noqa: E731
    features = [log(_angle(normals["net"], normals[k])) for k in FIELDS[1:]]
    for k in FIELDS:
        features += [log(x) for x in _roughness(normals[k], a, b, f.shape[0])]
    features += [log(_angle(normals[k], normals["noisy"])) for k in FIELDS]
    name, cond, seed = path.name[: -len(".npz")].split("__")
    kind, level = cond.rsplit("_", 1)
    return {
        "key": (name, kind, float(level), int(seed)),
        "arrays": d,
        "fields": np.stack([normals[k] for k in FIELDS], 1),  # [n_face, 4, 3]
        "errors": np.stack([_angle(normals[k], normals["clean"]) for k in FIELDS], 1),
        "features": np.stack(features, 1),
    }


def fit_gate(cases, center, scale, seed: int = 0) -> np.ndarray:
    """`[n_feature + 1, n_field]` softmax weights of least expected per-face error."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    zs, es = [], []
    for c in cases:
        pick = rng.choice(len(c["errors"]), min(FIT_FACES, len(c["errors"])), replace=False)
        zs.append(_design(c["features"][pick], center, scale))
        # Relative to the network's mean error on the mesh: every case weighs alike.
        es.append(c["errors"][pick] / max(c["errors"][:, 0].mean(), 1e-6) / pick.size)
    z, e = np.concatenate(zs), np.concatenate(es)
    shape = (z.shape[1], e.shape[1])

    def objective(w):
        p = _softmax(z @ w.reshape(shape))
        expected = (p * e).sum(1, keepdims=True)
        grad = z.T @ (p * (e - expected))
        return float(expected.sum() + 1e-3 * w @ w), grad.ravel() + 2e-3 * w

    w = minimize(objective, np.zeros(np.prod(shape)), jac=True, method="L-BFGS-B").x
    return w.reshape(shape)


def _design(features, center, scale):
    return np.concatenate([(features - center) / scale, np.ones((len(features), 1))], 1)


def _softmax(s):
    p = np.exp(s - s.max(1, keepdims=True))
    return p / p.sum(1, keepdims=True)


def gated_result(case, weights, center, scale) -> np.ndarray:
    """The gate's field per face, then the vertex update from the network's result."""
    from dmd_jax.mesh import edge_unit_frame
    from dmd_jax.routes import fit_vertices

    d = case["arrays"]
    pick = (_design(case["features"], center, scale) @ weights).argmax(1)
    normals = case["fields"][np.arange(pick.size), pick]
    frame = edge_unit_frame(d["noisy"], d["faces"])
    return frame.invert(fit_vertices(frame.apply(d["net"]), d["faces"], normals)), pick


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reuse", action="store_true", help="reuse measured cases")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--reference", type=Path, default=RESULTS_DIR / "sota_lite.csv")
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    from dmd_jax.metrics import mesh_metrics

    warnings.simplefilter("ignore")
    cases = [load_case(p) for p in measure(args.cache, args.reuse)]
    best = best_others(args.reference, "val")
    stacked = np.concatenate([c["features"] for c in cases])
    center, scale = stacked.mean(0), stacked.std(0) + 1e-9

    def error(c, x):
        d = c["arrays"]
        return float(mesh_metrics(np.asarray(x, np.float64), d["clean"], d["faces"])["normal_deg"])

    methods = ("default", "network", "mesh oracle", "face oracle (normals)", "face gate")
    rows = {}  # label -> method -> [(error, best other)]
    share = {}  # label -> [n_field] share of faces the gate picks
    names = sorted({c["key"][0] for c in cases})
    for held in names:
        weights = fit_gate([c for c in cases if c["key"][0] != held], center, scale)
        for c in (c for c in cases if c["key"][0] == held):
            gated, pick = gated_result(c, weights, center, scale)
            fields = [error(c, c["arrays"][k]) for k in FIELDS]
            values = (
                error(c, c["arrays"]["default"]),
                fields[0],
                min(fields),
                float(c["errors"].min(1).mean()),
                error(c, gated),
            )
            label = protocol.NoiseCondition(c["key"][1], c["key"][2]).label
            for m, v in zip(methods, values, strict=True):
                rows.setdefault(label, {}).setdefault(m, []).append((v, best[c["key"]]))
            share.setdefault(label, []).append(np.bincount(pick, minlength=len(FIELDS)) / pick.size)

    labels = list(rows)
    table = [
        [
            m,
            *(per_shape_cell(rows[lb][m]) for lb in labels),
            per_shape_cell([p for lb in labels for p in rows[lb][m]]),
        ]
        for m in methods
    ]
    picks = [[label, *(f"{s:.0%}" for s in np.mean(share[label], 0))] for label in labels]
    write_report(
        args.out_dir / "face_gate.md",
        title="A per-face choice of normal field after the network (validation split)",
        env=environment(),
        intro=__doc__.split("\n\n")[1] + "\n\n" + __doc__.split("\n\n")[2],
        sections=[
            (
                "Mean normal error / per-shape geometric mean over the best other library "
                "method / share within 5 % (20 validation crops per condition)",
                markdown_table(["", *labels, "all"], table),
            ),
            (
                "Faces the gate gives each field",
                markdown_table(["condition", *(FIELD_NAMES[k] for k in FIELDS)], picks),
            ),
        ],
    )
    print((args.out_dir / "face_gate.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
