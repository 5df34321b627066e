"""What training buys the bundled model over its fixed parts (validation split).

The normal-first head mixes K candidate face normals (the noisy one and bilateral
pre-filtered ones, `dmd_jax.encoding.local_features`) with learnt weights and adds a
learnt correction; with its head zeroed it averages the candidates with equal weights,
and the (parameter-free) vertex update follows. This script compares, on every other
file of the validation split of `../shared/meshes/train` (crops of at most 8,000 faces,
as `relax_validation.py`), the noisy input, that candidate mean (the bundled model with
its head's kernel and bias set to zero), and the bundled model. Writes
`benchmarks/results/candidate_mean.md`.

    python benchmarks/candidate_mean.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

CONDITIONS = (("normal", 0.1), ("normal", 0.2), ("normal", 0.3), ("isotropic", 0.2))


def zero_head(params):
    """The bundled params with the normal-first head's Dense layer set to zero."""
    import jax

    def zero(path, x):
        keys = [getattr(k, "key", None) for k in path]
        return x * 0 if "denoiser" in keys and "head" in keys else x

    return jax.tree_util.tree_map_with_path(zero, params)


def main(argv=None) -> int:
    from relax_validation import validation_crops

    import dmd_jax
    from dmd_jax.checkpoints import ModelBundle
    from dmd_jax.metrics import mesh_metrics

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train-meshes", type=Path, default=HERE.parent.parent / "shared/meshes/train")
    p.add_argument("--out", type=Path, default=HERE / "results" / "candidate_mean.md")
    args = p.parse_args(argv)
    bundle = dmd_jax.load_pretrained()
    if bundle.config.model.head != "normal":
        raise SystemExit("the bundled model has no normal-first head")
    mean_bundle = ModelBundle(params=zero_head(bundle.params), config=bundle.config, meta={})
    meshes = validation_crops(args.train_meshes)
    start = time.perf_counter()
    header = ["input", "noisy", "candidate mean (head zeroed)", "bundled model", "trained share"]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|---:" * (len(header) - 1) + "|"]
    for direction, level in CONDITIONS:
        err = {"noisy": [], "mean": [], "model": []}
        for _, v, f in meshes:
            noisy = dmd_jax.add_noise(1, v, f, "gaussian", level, units="edge", direction=direction)
            err["noisy"].append(mesh_metrics(noisy, v, f)["normal_deg"])
            err["mean"].append(
                mesh_metrics(dmd_jax.denoise(noisy, f, mean_bundle), v, f)["normal_deg"]
            )
            err["model"].append(mesh_metrics(dmd_jax.denoise(noisy, f, bundle), v, f)["normal_deg"])
        n, m, d = (float(np.mean(err[k])) for k in ("noisy", "mean", "model"))
        share = (m - d) / (n - d) if n > d else float("nan")
        label = f"Gaussian {level} edges, {direction}"
        lines.append(f"| {label} | {n:.2f} | {m:.2f} | {d:.2f} | {100 * share:.0f} % |")
        print(lines[-1], flush=True)
    text = (
        "# What training buys over the fixed candidate normals (validation split)\n\n"
        f"`python benchmarks/candidate_mean.py` — {len(meshes)} meshes (every other file of "
        "the validation split, crops of at most 8,000 faces), noise seed 1; mean face-normal "
        "error in degrees. *Candidate mean*: the bundled model with its head zeroed, i.e. "
        "the equal-weight mean of the noisy and pre-filtered face normals followed by the "
        "vertex update, no learnt weight involved. *Trained share*: the part of the "
        "model's total error reduction (noisy → bundled) that the learnt weights add over "
        f"the candidate mean. {time.perf_counter() - start:.0f} s.\n\n" + "\n".join(lines) + "\n"
    )
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
