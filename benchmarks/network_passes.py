"""How many network passes a noisy mesh needs, measured on the training split.

`denoise(iterations=k)` applies the network k times, each pass starting from the last.
This script records, on crops of the *training* files of `../shared/meshes/train` (the
validation split stays untouched for judging the result), the mean face-normal error
after each of `--passes` passes and the mean angle each pass turned the face normals
by, for Gaussian noise along normals (the benchmark protocol) and per coordinate, from
light to the paper's heavy regime (several edge lengths): how many passes each noise
needs, and whether the first pass's turn could choose the count for the user (see
`docs/design-decisions.md`, "Network passes"). Writes
`benchmarks/results/network_passes.md` and `.json`.

    python benchmarks/network_passes.py
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

CONDITIONS = (
    ("clean", 0.0),
    ("normal", 0.1),
    ("normal", 0.2),
    ("normal", 0.3),
    ("normal", 0.5),
    ("isotropic", 0.2),
    ("isotropic", 0.5),
    ("isotropic", 1.0),
    ("isotropic", 2.0),
)


# The rule read off the training split: one pass while the first turned the normals by
# less than 18 degrees, two below 36, else four (`rule_passes`).
RULE = ((18.0, 1), (36.0, 2), (float("inf"), 4))


def rule_passes(first_turn: float) -> int:
    return next(p for bound, p in RULE if first_turn < bound)


def turn_deg(a, b, f) -> float:
    """Mean angle (degrees) between the face normals of two positions of a mesh."""
    from dmd_jax.metrics import face_normal_errors_deg

    return float(face_normal_errors_deg(b, a, f).mean())


def main(argv=None) -> int:
    from relax_validation import validation_crops

    import dmd_jax
    from dmd_jax.demo import gaussian_edge_noise
    from dmd_jax.metrics import mesh_metrics

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train-meshes", type=Path, default=HERE.parent.parent / "shared/meshes/train")
    p.add_argument("--split", default="train", choices=("train", "val"))
    p.add_argument("--every", type=int, default=5, help="every n-th file of the split")
    p.add_argument("--conditions", nargs="+", default=None, help="e.g. normal:0.1 (default: all)")
    p.add_argument("--max-faces", type=int, default=6000)
    p.add_argument("--passes", type=int, default=6)
    p.add_argument("--out", type=Path, default=HERE / "results" / "network_passes")
    args = p.parse_args(argv)
    bundle = dmd_jax.load_pretrained()
    meshes = validation_crops(args.train_meshes, args.max_faces, split=args.split, every=args.every)
    conditions = CONDITIONS
    if args.conditions:
        conditions = [(c.split(":")[0], float(c.split(":")[1])) for c in args.conditions]
    start = time.perf_counter()
    records = []
    for direction, level in conditions:
        for i, (name, clean, f) in enumerate(meshes):
            if level:
                noisy = gaussian_edge_noise(clean, f, level, 1000 + i, direction)
            else:
                noisy = np.asarray(clean, np.float64)
            x = noisy
            errs = [mesh_metrics(x, clean, f)["normal_deg"]]
            turns = []
            for _ in range(args.passes):
                y = dmd_jax.denoise(x, f, bundle)
                turns.append(turn_deg(x, y, f))
                errs.append(mesh_metrics(np.asarray(y, np.float64), clean, f)["normal_deg"])
                x = y
            records.append(
                dict(mesh=name, direction=direction, level=level, errors=errs, turns=turns)
            )
        mean = np.mean([r["errors"] for r in records[-len(meshes) :]], axis=0)
        print(f"{direction} {level}: " + " ".join(f"{e:.2f}" for e in mean), flush=True)
    wall = time.perf_counter() - start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(records, indent=1))
    report(records, args, len(meshes), wall)
    return 0


def report(records, args, n_mesh: int, wall: float) -> None:
    k = args.passes
    which = "every file" if args.every == 1 else f"every {args.every}th file"
    head = ["noise", "input"] + [f"{j} pass{'es' if j > 1 else ''}" for j in range(1, k + 1)]
    lines = [
        f"# Mean face-normal error after each network pass ({args.split} split)",
        "",
        f"`{' '.join(['python benchmarks/network_passes.py', *sys.argv[1:]])}` — {n_mesh} files "
        f"({which} of the {args.split} split of `train/`), crops of at most "
        f"{args.max_faces:,} faces, bundled weights; noise σ in mean edge lengths, one "
        f"seed per mesh. {wall:.0f} s.",
        "",
        "| " + " | ".join(head) + " |",
        "|---" + "|---:" * (len(head) - 1) + "|",
    ]
    conds = list(dict.fromkeys((r["direction"], r["level"]) for r in records))
    for d, lv in conds:
        rs = [r for r in records if (r["direction"], r["level"]) == (d, lv)]
        e = np.mean([r["errors"] for r in rs], axis=0)
        best = int(np.argmin(e[1:])) + 1
        cells = [f"**{x:.2f}**" if j == best else f"{x:.2f}" for j, x in enumerate(e)]
        lines.append(f"| {d} {lv:g} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Mean angle (degrees) each pass turned the face normals by:",
        "",
        "| noise | " + " | ".join(f"pass {j}" for j in range(1, k + 1)) + " |",
        "|---" + "|---:" * k + "|",
    ]
    for d, lv in conds:
        rs = [r for r in records if (r["direction"], r["level"]) == (d, lv)]
        t = np.mean([r["turns"] for r in rs], axis=0)
        lines.append(f"| {d} {lv:g} | " + " | ".join(f"{x:.2f}" for x in t) + " |")
    lines += [
        "",
        "The rule read off the training split (1 pass below a first turn of 18°, 2 below "
        "36°, else 4; capped at the passes run) against one pass:",
        "",
        "| noise | 1 pass | rule | mean passes of the rule |",
        "|---|---:|---:|---:|",
    ]
    for d, lv in conds:
        rs = [r for r in records if (r["direction"], r["level"]) == (d, lv)]
        ks = [min(rule_passes(r["turns"][0]), k) for r in rs]
        rule = np.mean([r["errors"][j] for r, j in zip(rs, ks, strict=True)])
        one = np.mean([r["errors"][1] for r in rs])
        lines.append(f"| {d} {lv:g} | {one:.2f} | {rule:.2f} | {np.mean(ks):.1f} |")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
