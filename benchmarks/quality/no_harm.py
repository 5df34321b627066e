"""Does a denoiser leave a clean mesh alone? Every file of `../shared/meshes`, no noise.

Runs DMD-Net (bundled weights, or `--weights`) and the library's quick classic filters on
each *clean* mesh (cropped as the benchmark protocol does, `dmd_jax.protocol.crop`) and
reports how far the output moved: the mean face-normal change in degrees and the largest
vertex move in mean edge lengths.
A good denoiser changes a clean mesh little. Writes `benchmarks/results/no_harm.md`.

    python benchmarks/quality/no_harm.py
    python benchmarks/quality/no_harm.py --weights old.msgpack --out /tmp/no_harm_old.md
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
from dmd_jax import protocol  # noqa: E402
from dmd_jax.protocol import MAX_FACES  # noqa: E402

METHODS = ("dmd", "cnr", "bnf", "taubin")


def main(argv=None) -> int:
    import dmd_jax
    from dmd_jax import baselines
    from dmd_jax.mesh import mean_edge_length
    from dmd_jax.metrics import face_normal_errors_deg

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", type=Path, default=protocol.shared_meshes_dir())
    p.add_argument("--weights", type=Path, help="DMD-Net weights file (default: bundled)")
    p.add_argument("--out", type=Path, default=RESULTS_DIR / "no_harm.md")
    args = p.parse_args(argv)
    bundle = dmd_jax.load_weights(args.weights) if args.weights else dmd_jax.load_pretrained()
    start = time.perf_counter()
    turn = {m: [] for m in METHODS}
    move = {m: [] for m in METHODS}
    rows = []
    for path in protocol.mesh_files(args.meshes):
        v, f = protocol.crop(*dmd_jax.load_mesh(path), MAX_FACES)
        h = mean_edge_length(v, f)
        row = [path.name]
        for m in METHODS:
            out = dmd_jax.denoise(v, f, bundle) if m == "dmd" else baselines.run_baseline(m, v, f)
            turn[m].append(float(np.mean(face_normal_errors_deg(out, v, f))))
            move[m].append(float(np.abs(out - v).max() / h))
            row += [f"{turn[m][-1]:.2f}", f"{move[m][-1]:.2f}"]
        rows.append(row)
        print(" ".join(row), flush=True)
    rows.append(
        ["**mean** (max for moves)"]
        + [c for m in METHODS for c in (f"**{np.mean(turn[m]):.2f}**", f"**{max(move[m]):.2f}**")]
    )
    rows.append(
        ["median"]
        + [c for m in METHODS for c in (f"{np.median(turn[m]):.2f}", f"{np.median(move[m]):.2f}")]
    )
    header = ["mesh"] + [
        f"{m} {what}" for m in METHODS for what in ("normal change (°)", "max move (edges)")
    ]
    write_report(
        args.out,
        title="A clean mesh through each denoiser",
        env=environment() | {"weights": str(args.weights or "bundled")},
        intro=(
            f"Every file of `{args.meshes.name}` without noise (crops of at most {MAX_FACES} "
            "faces, `dmd_jax.protocol.crop`), through DMD-Net and the library's CNR, BNF and "
            "Taubin with their defaults: the mean angle between the output's and the input's face "
            "normals, and the largest vertex move in mean edge lengths. Lower is better. "
            f"{time.perf_counter() - start:.0f} s."
        ),
        sections=[("Per mesh", markdown_table(header, rows))],
        weights=args.weights or BUNDLED,
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
