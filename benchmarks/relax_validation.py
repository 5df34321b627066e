"""Tangential relaxation after DMD-Net on the validation split (README table).

Every other file of the fixed validation split of `../shared/meshes/train`
(`dmd_jax.data.real`), cropped to a connected patch of at most 8,000 faces
(`sota_lite.crop`), Gaussian noise of a fixed seed, the bundled model, then
`dmd_jax.relax.relax_tangential` with 3 steps at several feature ratios (1.0 blocks only
the normal: uniform tangential smoothing). Writes `benchmarks/results/relax_validation.md`.

    python benchmarks/relax_validation.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

CONDITIONS = (("clean", 0.0), ("normal", 0.1), ("normal", 0.3), ("isotropic", 0.2))
RATIOS = (0.05, 0.2, 1.0)


def validation_crops(
    train_meshes: Path, max_faces: int = 8000, *, split: str = "val", every: int = 2
):
    """`(name, vertices, faces)` of every `every`-th file of a split of `train_meshes`
    (default: every other validation file), cropped to a connected patch of at most
    `max_faces` faces (`sota_lite.crop`)."""
    from sota_lite import crop

    from dmd_jax.data.real import load_meshes, mesh_files

    meshes = []
    for path in mesh_files(train_meshes, split)[::every]:
        meshes.append((path.name, *crop(*load_meshes([path])[0], max_faces)))
    return meshes


def main(argv=None) -> int:
    import dmd_jax
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.relax import relax_tangential

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train-meshes", type=Path, default=HERE.parent.parent / "shared/meshes/train")
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--out", type=Path, default=HERE / "results" / "relax_validation.md")
    args = p.parse_args(argv)
    bundle = dmd_jax.load_pretrained()
    meshes = validation_crops(args.train_meshes)
    start = time.perf_counter()
    header = ["input", "network only"] + [f"+ relax {args.steps}, ratio {r}" for r in RATIOS]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|---:" * (len(header) - 1) + "|"]
    for direction, level in CONDITIONS:
        errors = {r: [] for r in (None, *RATIOS)}
        for _, v, f in meshes:
            noisy = (
                v
                if level == 0
                else dmd_jax.add_noise(
                    1, v, f, "gaussian", level, units="edge", direction=direction
                )
            )
            out = dmd_jax.denoise(noisy, f, bundle)
            errors[None].append(mesh_metrics(out, v, f)["normal_deg"])
            for r in RATIOS:
                relaxed = relax_tangential(out, f, args.steps, feature_ratio=r)
                errors[r].append(mesh_metrics(relaxed, v, f)["normal_deg"])
        label = "clean input" if level == 0 else f"Gaussian {level} edges, {direction}"
        cells = [f"{np.mean(errors[r]):.2f}" for r in (None, *RATIOS)]
        lines.append("| " + " | ".join([label, *cells]) + " |")
        print(lines[-1], flush=True)
    text = (
        "# Tangential relaxation after DMD-Net, validation split\n\n"
        f"`python benchmarks/relax_validation.py` — {len(meshes)} meshes (every other file "
        "of the validation split, crops of at most 8,000 faces), noise seed 1, bundled "
        f"weights; mean face-normal error in degrees; {time.perf_counter() - start:.0f} s.\n\n"
        + "\n".join(lines)
        + "\n"
    )
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
