"""Does a whole mesh want the amount of smoothing its small pieces want?

On real meshes of the training split (never the validation split), under the
benchmark's Gaussian noise along the normals, the controller's grid (every option,
`smoothing_set.pass_errors`, held vertices as `denoise` holds them) is searched on the
15,000-face crop that the validation protocol takes (`protocol.crop`) and on two crops
of 400-1200 faces at random faces (the size of the controller's first training
examples, `smoothing_set.PATCH_FACES`). The report counts the best option's passes per
crop size. Deterministic (seed 5 picks the meshes and the small crops).

```bash
python benchmarks/quality/whole_vs_crops.py --meshes 10 --levels 0.1 0.2
python benchmarks/quality/whole_vs_crops.py --report-only
```
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import REPO, RESULTS_DIR, markdown_table, provenance, write_text  # noqa: E402

DEFAULT_CSV = REPO / "runs" / "exp" / "whole_vs_crops.csv"
DEFAULT_REPORT = RESULTS_DIR / "controller_whole_vs_crops.md"
WHOLE_FACES = 15_000  # protocol.MAX_FACES: the validation split's crop


def run(n_meshes: int, levels, out_csv, real_root, echo=print) -> None:
    from dmd_jax import protocol
    from dmd_jax.checkpoints import load_model
    from dmd_jax.consistency import oriented_faces
    from dmd_jax.controller import option_errors, options
    from dmd_jax.data.real import mesh_files, patch_mesh
    from dmd_jax.data.smoothing_set import (
        PATCH_FACES,
        PRESMOOTH_GRID,
        SEARCH_PASSES,
        UPDATES,
        held_vertices,
        pass_errors,
    )
    from dmd_jax.io import load_mesh

    files = mesh_files(real_root, "train")
    rng = np.random.default_rng(5)
    pick = [files[i] for i in sorted(rng.choice(len(files), n_meshes, replace=False))]
    net = load_model(None)
    opts = options(PRESMOOTH_GRID, UPDATES, SEARCH_PASSES)
    Path(out_csv).parent.mkdir(parents=True, exist_ok=True)
    with open(out_csv, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["mesh", "crop", "level", "faces", "best", "best_deg"])
        for path in pick:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                v, f = load_mesh(path)
            v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
            crops = [("whole", protocol.crop(v, f, WHOLE_FACES))]
            for j in range(2):
                n = int(rng.integers(*PATCH_FACES))
                small = (
                    patch_mesh(v, f, int(rng.integers(len(f))), n)
                    if len(f) > n
                    else (v, f.astype(np.int32))
                )
                crops.append((f"small{j}", small))
            for level in levels:
                condition = protocol.parse_condition(f"{level}")
                seed = protocol.condition_seed(path.name, condition)
                for tag, (cv, cf) in crops:
                    t = time.perf_counter()
                    target, noisy, tri = protocol.condition_mesh(cv, cf, condition, seed)
                    # As `denoise` reads it: consistently wound, its held vertices held.
                    oriented, _ = oriented_faces(np.asarray(tri), len(noisy))
                    held = held_vertices(noisy, oriented)
                    errors, _ = pass_errors(
                        noisy, target, oriented if held.any() else tri, net, held
                    )
                    row = option_errors(errors[None], PRESMOOTH_GRID, UPDATES, SEARCH_PASSES)[0]
                    b = int(np.argmin(row))
                    w.writerow([path.name, tag, level, len(tri), opts[b].label, f"{row[b]:.4f}"])
                    fh.flush()
                    echo(
                        f"{path.name} {tag} {level} ({len(tri)} faces): {opts[b].label} "
                        f"{row[b]:.2f}° ({time.perf_counter() - t:.0f} s)"
                    )


def _passes(label: str) -> int:
    return int(label.rsplit("_", 1)[1]) if "_" in label else 0


def report(out_csv, out_md) -> Path:
    with open(out_csv) as fh:
        rows = list(csv.DictReader(fh))
    table = []
    for level in sorted({r["level"] for r in rows}, key=float):
        for crop in ("whole", "small"):
            sel = [r for r in rows if r["level"] == level and r["crop"].startswith(crop)]
            counts = Counter(_passes(r["best"]) for r in sel)
            table.append(
                [
                    level,
                    f"{WHOLE_FACES:,}-face crop" if crop == "whole" else "400-1200-face crops",
                    len(sel),
                    ", ".join(f"{k}: {counts[k]}" for k in sorted(counts)),
                    sum(1 for r in sel if _passes(r["best"]) > 1),
                    sum(1 for r in sel if r["best"].startswith("p0_")),
                ]
            )
    meshes = sorted({r["mesh"] for r in rows})
    text = "\n".join(
        [
            "# Whole meshes and their small pieces: the best amount of smoothing",
            "",
            provenance(),
            "",
            __doc__.split("\n\n")[1].replace("\n", " "),
            "",
            f"Meshes ({len(meshes)}): {', '.join(meshes)}.",
            "",
            "```bash",
            "python benchmarks/quality/whole_vs_crops.py --meshes 10 --levels 0.1 0.2",
            "```",
            "",
            markdown_table(
                [
                    "Gaussian σ (edges)",
                    "crop",
                    "cases",
                    "best option's passes: meshes",
                    "more than one pass",
                    "no pre-smoothing",
                ],
                table,
            ),
            "",
            "A model that scores a large mesh by its small pieces learns what the pieces "
            "want; the controller's whole-mesh examples (`smoothing_set.WHOLE_FROM`) "
            "teach it what the whole wants (docs/controller.md).",
            "",
        ]
    )
    return write_text(out_md, text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=int, default=10)
    parser.add_argument("--levels", type=float, nargs="+", default=[0.1, 0.2])
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    parser.add_argument("--report", default=str(DEFAULT_REPORT))
    parser.add_argument("--real", default=str(REPO.parent / "shared" / "meshes" / "train"))
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args(argv)
    if not args.report_only:
        run(args.meshes, args.levels, args.csv, args.real)
    print(f"wrote {report(args.csv, args.report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
