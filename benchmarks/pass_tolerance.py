"""Fits `ModelConfig.pass_tolerance` of a DMD-Net's weights on the validation split.

`denoise` runs one network pass, and another while the last pass moved the vertices by
more than `pass_tolerance` mean edges on average (`dmd_jax.inference.denoise`). How far
the first pass moves a mesh tells how noisy it was, and a second pass helps after heavy
noise and hurts after light noise. This script measures both on the validation split of
`../shared/meshes/train` (the crops and noise seeds of `sota_lite.py`, Gaussian noise
along the vertex normals at 0.05–0.5 mean edges): per mesh and level, the normal error
after one and two passes and how far the first pass moved the vertices. Then, for each
candidate tolerance, the mean normal error per level if a second pass ran exactly where
the first moved the mesh more than the tolerance. The chosen tolerance minimises the
mean over the benchmark levels 0.1 / 0.2 / 0.3. Never run on the test meshes.

Third and later passes (only where the second pass still moves the mesh more than the
tolerance) are not simulated; the report counts where that would happen.

Run: ``python benchmarks/pass_tolerance.py [--weights PATH]`` (about 5 minutes on 2
cores); writes ``results/pass_tolerance.md`` and ``.csv``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    environment,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax.protocol import MAX_FACES, crop, noise_seed  # noqa: E402

LEVELS = (0.05, 0.1, 0.2, 0.3, 0.5)
BENCHMARK_LEVELS = (0.1, 0.2, 0.3)
TOLERANCES = tuple(np.round(np.arange(0.04, 0.401, 0.01), 2))
HEADER = ["mesh", "faces", "level", "seed", "one_pass", "two_passes", "move1", "move2"]


def measure(val_dir, bundle, levels=LEVELS, max_faces: int = MAX_FACES, echo=print):
    """Rows of `HEADER`: per validation mesh and level, the errors after one and two
    passes and the mean vertex move of each pass (mean edges of the pass's input)."""
    from dmd_jax.data.real import mesh_files
    from dmd_jax.inference import denoise
    from dmd_jax.io import load_mesh
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.protocol import benchmark_noise as gaussian_edge_noise

    rows = []
    for path in mesh_files(val_dir, "val"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            clean, faces = load_mesh(path)
        clean, faces = crop(clean, faces, max_faces)
        for level in levels:
            seed = noise_seed(path.name, level)
            noisy = gaussian_edge_noise(clean, faces, level, seed)
            once = denoise(noisy, faces, bundle, iterations=1)
            twice = denoise(once, faces, bundle, iterations=1)
            err = [
                mesh_metrics(np.asarray(x, np.float64), clean, faces)["normal_deg"]
                for x in (once, twice)
            ]
            moves = [
                float(np.linalg.norm(b - a, axis=1).mean() / mean_edge_length(a, faces))
                for a, b in ((noisy, once), (once, twice))
            ]
            rows.append([path.name, len(faces), level, seed, *err, *moves])
            echo(
                f"{path.name} σ = {level}: one pass {err[0]:.2f}°, two {err[1]:.2f}°, "
                f"first pass moved {moves[0]:.3f} edges"
            )
    return rows


def simulate(rows, tolerance: float, level: float) -> float:
    """Mean normal error at `level` when the second pass runs where `move1 > tolerance`."""
    errs = [r[5] if r[6] > tolerance else r[4] for r in rows if r[2] == level]
    return float(np.mean(errs))


def choose(rows, tolerances=TOLERANCES, levels=BENCHMARK_LEVELS) -> float:
    """The tolerance with the lowest mean error over `levels` (the smallest on ties)."""
    scores = [np.mean([simulate(rows, t, lv) for lv in levels]) for t in tolerances]
    return float(tolerances[int(np.argmin(scores))])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--weights", default=None, help="weights (default: bundled)")
    parser.add_argument("--val-meshes", default=str(REPO.parent / "shared" / "meshes" / "train"))
    parser.add_argument("--name", default="pass_tolerance")
    args = parser.parse_args(argv)

    from dmd_jax.checkpoints import load_model

    bundle = load_model(args.weights)
    rows = measure(args.val_meshes, bundle)
    best = choose(rows)
    levels = sorted({r[2] for r in rows})
    curve = [
        [f"{t:.2f}"]
        + [f"{simulate(rows, t, lv):.2f}" for lv in levels]
        + [f"{np.mean([simulate(rows, t, lv) for lv in BENCHMARK_LEVELS]):.3f}"]
        for t in TOLERANCES
    ]
    per_level = [
        [
            f"{lv}",
            f"{np.mean([r[4] for r in rows if r[2] == lv]):.2f}",
            f"{np.mean([r[5] for r in rows if r[2] == lv]):.2f}",
            f"{sum(r[5] < r[4] for r in rows if r[2] == lv)} / {sum(r[2] == lv for r in rows)}",
            f"{np.median([r[6] for r in rows if r[2] == lv]):.3f}",
            f"{simulate(rows, best, lv):.2f}",
            f"{sum(r[6] > best for r in rows if r[2] == lv)}",
            f"{sum(r[6] > best and r[7] > best for r in rows if r[2] == lv)}",
        ]
        for lv in levels
    ]
    intro = " ".join(__doc__.split("\n\n")[1].split())
    intro += (
        f"\n\nWeights: {args.weights or 'bundled (dmd_jax/weights/dmd_small.msgpack)'}. "
        f"Chosen tolerance: **{best:.2f}** mean edges."
    )
    per_level_table = markdown_table(
        [
            "σ (edges)",
            "one pass",
            "two passes",
            "two better",
            "median first move",
            f"rule at {best:.2f}",
            "second pass runs",
            "a third would run",
        ],
        per_level,
    )
    curve_table = markdown_table(
        ["tolerance"] + [f"σ {lv}" for lv in levels] + ["mean of 0.1 / 0.2 / 0.3"], curve
    )
    out = RESULTS_DIR / f"{args.name}.md"
    write_report(
        out,
        title="`pass_tolerance`: when a second DMD-Net pass helps",
        env=environment(packages=("dmd_jax", "jax", "numpy")),
        intro=intro,
        sections=[
            ("Per level (validation split, mean normal error in degrees)", per_level_table),
            ("Every candidate tolerance", curve_table),
        ],
    )
    write_csv(RESULTS_DIR / f"{args.name}.csv", HEADER, rows)
    print(f"chosen tolerance {best:.2f}; wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
