"""Does a denoiser leave a clean mesh alone? Every file of `../shared/meshes`, no noise.

Runs DMD-Net (bundled weights, or `--weights`) and the library's quick classic filters on
each *clean* mesh (cropped as the benchmark protocol does, `dmd_jax.protocol.crop`) and
reports how far the output moved: the mean face-normal change in degrees and the largest
vertex move in mean edge lengths.
A good denoiser changes a clean mesh little. Writes `benchmarks/results/no_harm.md`.

Three sets (`--sets`): `shared` (the files), `stress` (the generated CAD shapes of
`dmd_jax.data.stress`: pyramid, cube, ... where a small turn of a flat face shows), and
`scan` (a noise-free simulated depth scan of each shared file, `protocol.condition_mesh`
with a `scan` condition of level 0: range-image tessellation, open boundaries, slivers).
Per set, DMD-Net's normal change over the smallest of the other methods' is summarised
per mesh: geometric mean and the worst ratio with its mesh (`dmd_jax.comparison`).

    python benchmarks/quality/no_harm.py
    python benchmarks/quality/no_harm.py --weights old.msgpack --out /tmp/no_harm_old.md
    python benchmarks/quality/no_harm.py --sets stress scan --max-meshes 2 --out /tmp/x.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    environment,
    markdown_table,
    write_report,
)
from dmd_jax import comparison, protocol  # noqa: E402
from dmd_jax.protocol import MAX_FACES  # noqa: E402

METHODS = ("dmd", "cnr", "bnf", "taubin")
SETS = ("shared", "stress", "scan")


def meshes(folder: Path, sets, max_meshes: int = 0):
    """`(set, name, vertices, faces)` of every clean mesh to run, set by set."""
    import dmd_jax

    out = []
    files = protocol.mesh_files(folder) if {"shared", "scan"} & set(sets) else []
    if max_meshes:
        files = files[:max_meshes]
    for mesh_set in sets:
        if mesh_set == "stress":
            from dmd_jax.data.stress import STRESS_SHAPES, stress_shape

            names = STRESS_SHAPES[:max_meshes] if max_meshes else STRESS_SHAPES
            out += [("stress", name, *stress_shape(name)) for name in names]
            continue
        for path in files:
            v, f = protocol.crop(*dmd_jax.load_mesh(path), MAX_FACES)
            if mesh_set == "scan":
                condition = protocol.NoiseCondition(protocol.SCAN_KIND, 0.0)
                seed = protocol.condition_seed(path.name, condition)
                v, _, f = protocol.condition_mesh(v, f, condition, seed)
            out.append((mesh_set, path.name, v, f))
    return out


def ratio_rows(turn_by_mesh: dict) -> list[list[str]]:
    """Per set: DMD-Net's normal change over the best other method's, per mesh."""
    rows = []
    for mesh_set in dict.fromkeys(k[0] for k in turn_by_mesh):
        cases = {k: v for k, v in turn_by_mesh.items() if k[0] == mesh_set}
        ratios = comparison.ratios_to_best_other(
            cases, "dmd", METHODS, floor=comparison.RATIO_FLOOR_DEG
        )
        s = comparison.summarise_ratios(ratios)
        rows.append(
            [
                mesh_set,
                str(s.n),
                f"{s.geometric_mean:.3f}",
                str(s.best),
                f"{s.worst:.2f} ({s.worst_case[1]})",
            ]
        )
    return rows


def main(argv=None) -> int:
    import dmd_jax
    from dmd_jax import baselines
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.metrics import face_normal_errors_deg

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", type=Path, default=protocol.shared_meshes_dir())
    p.add_argument("--weights", type=Path, help="DMD-Net weights file (default: bundled)")
    p.add_argument("--out", type=Path, default=RESULTS_DIR / "no_harm.md")
    p.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS))
    p.add_argument("--max-meshes", type=int, default=0, help="first N meshes per set (0: all)")
    args = p.parse_args(argv)
    if args.max_meshes < 0:
        p.error("--max-meshes must be >= 0")
    bundle = dmd_jax.load_weights(args.weights) if args.weights else dmd_jax.load_pretrained()
    start = time.perf_counter()
    turn = {m: [] for m in METHODS}
    move = {m: [] for m in METHODS}
    turn_by_mesh: dict[tuple, dict[str, float]] = {}
    rows = []
    for mesh_set, name, v, f in meshes(args.meshes, args.sets, args.max_meshes):
        h = mean_edge_length(v, f)
        row = [mesh_set, name]
        for m in METHODS:
            out = dmd_jax.denoise(v, f, bundle) if m == "dmd" else baselines.run_baseline(m, v, f)
            turn[m].append(float(np.mean(face_normal_errors_deg(out, v, f))))
            move[m].append(float(np.abs(out - v).max() / h))
            turn_by_mesh.setdefault((mesh_set, name), {})[m] = turn[m][-1]
            row += [f"{turn[m][-1]:.2f}", f"{move[m][-1]:.2f}"]
        rows.append(row)
        print(" ".join(row), flush=True)
    rows.append(
        ["**all**", "**mean** (max for moves)"]
        + [c for m in METHODS for c in (f"**{np.mean(turn[m]):.2f}**", f"**{max(move[m]):.2f}**")]
    )
    rows.append(
        ["all", "median"]
        + [c for m in METHODS for c in (f"{np.median(turn[m]):.2f}", f"{np.median(move[m]):.2f}")]
    )
    header = ["set", "mesh"] + [
        f"{m} {what}" for m in METHODS for what in ("normal change (°)", "max move (edges)")
    ]
    ratios = markdown_table(
        [
            "set",
            "meshes",
            "DMD-Net / best other (geometric mean)",
            "DMD-Net best",
            "worst ratio (mesh)",
        ],
        ratio_rows(turn_by_mesh),
    )
    write_report(
        args.out,
        title="A clean mesh through each denoiser",
        env=environment() | {"weights": str(args.weights or "bundled")},
        intro=(
            f"Clean meshes (sets: {', '.join(args.sets)}): every file of `{args.meshes.name}` "
            f"without noise (crops of at most {MAX_FACES} faces, `dmd_jax.protocol.crop`); "
            "the generated CAD shapes of `dmd_jax.data.stress`; a noise-free simulated "
            f"depth scan of each file ({protocol.SCAN_RESOLUTION}², `dmd_jax.simulate_scan`, "
            "view drawn from the seed). Through DMD-Net and the library's CNR, BNF and "
            "Taubin with their defaults: the mean angle between the output's and the "
            "input's face normals, and the largest vertex move in mean edge lengths. Lower "
            "is better. Ratios: DMD-Net's normal change over the smallest other method's, "
            f"per mesh (changes below {comparison.RATIO_FLOOR_DEG:g}° count as "
            f"{comparison.RATIO_FLOOR_DEG:g}°). {time.perf_counter() - start:.0f} s."
        ),
        sections=[
            ("Per mesh: DMD-Net against the best other method", ratios),
            ("Per mesh", markdown_table(header, rows)),
        ],
        weights=args.weights or BUNDLED,
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
