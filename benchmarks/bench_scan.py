"""How long `dmd_jax.simulate_scan` takes: issue 53 asks ≤ 2 s for a 100k-face mesh at 256².

Meshes: a torus of exactly 100,000 faces (250 x 200 sections: it hides part of itself
from most views, so the z-buffer resolves occlusions), and the shared armadillo (86,482
faces) when the shared meshes are present. Each mesh is scanned from a fixed oblique view
at each resolution, cases timed round-robin (`common.time_interleaved`: median and IQR),
after one warm-up call. The report also gives the scan's size (vertices, faces) and how
the time splits between rendering the depth map and the rest (triangulation, noise).

Run `python benchmarks/bench_scan.py` (writes `results/scan.md`); `--quick` scans the
torus only, at 256², three rounds.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    environment,
    format_timing,
    markdown_table,
    time_interleaved,
    write_report,
)

VIEW = (0.4, -0.5, 0.77)  # oblique: every mesh shows occlusions and grazing parts


def torus(major_sections: int = 250, minor_sections: int = 200):
    """A torus of `2 · major · minor` faces (100,000 by default)."""
    import trimesh

    t = trimesh.creation.torus(
        major_radius=1.0,
        minor_radius=0.35,
        major_sections=major_sections,
        minor_sections=minor_sections,
    )
    return np.asarray(t.vertices, np.float64), np.asarray(t.faces, np.int64)


def meshes(quick: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {"torus": torus()}
    if quick:
        return out
    from dmd_jax.io import load_mesh
    from dmd_jax.protocol import shared_meshes_dir

    path = shared_meshes_dir() / "armadillo.obj"
    if path.is_file():
        out["armadillo"] = load_mesh(path)
    return out


def render_time(v, f, resolution: int) -> float:
    from dmd_jax.scan import render_depth, view_basis

    start = time.perf_counter()
    render_depth(np.asarray(v, np.float64), np.asarray(f, np.int64), view_basis(VIEW), resolution)
    return time.perf_counter() - start


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="torus at 256² only, 3 rounds")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR / "scan.md")
    args = parser.parse_args(argv)

    from dmd_jax.scan import simulate_scan

    resolutions = (256,) if args.quick else (256, 512)
    repeat = 3 if args.quick else 7
    env = environment()
    rows = []
    for name, (v, f) in meshes(args.quick).items():
        for res in resolutions:
            timing = time_interleaved(
                {
                    "scan": lambda v=v, f=f, res=res: simulate_scan(
                        0, v, f, view=VIEW, resolution=res
                    )
                },
                repeat=repeat,
            )["scan"]
            scan = simulate_scan(0, v, f, view=VIEW, resolution=res)
            render = float(np.median([render_time(v, f, res) for _ in range(3)]))
            rows.append(
                [
                    name,
                    f"{len(f):,}",
                    f"{res}²",
                    format_timing(timing),
                    f"{render * 1e3:.0f}",
                    f"{scan.clean.shape[0]:,}",
                    f"{scan.faces.shape[0]:,}",
                ]
            )
            print(*rows[-1], sep="  ")
    table = markdown_table(
        [
            "mesh",
            "faces",
            "resolution",
            "simulate_scan ms, median (IQR)",
            "of it: depth map ms",
            "scan vertices",
            "scan faces",
        ],
        rows,
    )
    write_report(
        args.out,
        title="simulate_scan: time of one simulated depth scan",
        env=env,
        intro=(
            "`dmd_jax.simulate_scan(0, V, F, view=VIEW, resolution=R)`, the whole call "
            "(validation, z-buffer, triangulation, scanner noise), one process; issue 53 "
            f"asks at most 2 s for 100k faces at 256². VIEW = {VIEW}."
        ),
        sections=[("Timings", table)],
        weights=None,
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
