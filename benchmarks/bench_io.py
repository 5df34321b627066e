"""Reading and writing large binary PLY meshes with `dmd_jax.io` (issue 17).

For each size a FRESH worker process writes the noisy grid of
`common.noisy_grid` with `save_mesh(".ply")` (binary, float32 coordinates,
through trimesh) and reads it back with `load_mesh`, timing each and reporting the
peak resident memory (`ru_maxrss`) after each step. The mesh is generated in the worker
before the clock starts; its arrays are part of the peak (a user holds them too).

Run `python benchmarks/bench_io.py --faces 2000000 20000000`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    command_line,
    environment,
    markdown_table,
    noisy_grid,
    peak_rss_gib,
    write_report,
    write_text,
)


def worker(n_face: int) -> dict:
    from dmd_jax.io import load_mesh, save_mesh

    v, f = noisy_grid(n_face)
    rss_mesh = peak_rss_gib()
    with tempfile.TemporaryDirectory(prefix="bench_io_") as tmp:
        path = Path(tmp) / "mesh.ply"
        t = time.perf_counter()
        save_mesh(path, v, f)
        write_s = time.perf_counter() - t
        rss_write = peak_rss_gib()
        size = path.stat().st_size
        del v
        t = time.perf_counter()
        v2, f2 = load_mesh(path)
        read_s = time.perf_counter() - t
        if not (f2.shape == f.shape and (f2 == f).all()):
            raise AssertionError("faces changed in the round trip")
    return {
        "faces": int(f.shape[0]),
        "vertices": int(v2.shape[0]),
        "file_mb": size / 1e6,
        "write_s": write_s,
        "read_s": read_s,
        "rss_mesh_gib": rss_mesh,
        "peak_after_write_gib": rss_write,
        "peak_after_read_gib": peak_rss_gib(),
        "load_1min": os.getloadavg()[0],
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--faces", nargs="+", type=int, default=[2_000_000, 20_000_000])
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--worker", type=int)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker)))
        return 0
    rows = []
    for n in args.faces:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(n)]
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{n:,}: failed: {proc.stderr.strip()[-300:]}", file=sys.stderr)
            continue
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(rows[-1], file=sys.stderr)
    env = environment(("numpy", "trimesh"))
    table = [
        (
            f"{r['faces']:,}",
            f"{r['file_mb']:.0f}",
            f"{r['write_s']:.1f}",
            f"{r['read_s']:.1f}",
            f"{r['rss_mesh_gib']:.2f}",
            f"{r['peak_after_write_gib']:.2f}",
            f"{r['peak_after_read_gib']:.2f}",
            f"{r['load_1min']:.1f}",
        )
        for r in rows
    ]
    headers = ["faces", "file MB", "save_mesh s", "load_mesh s", "RSS with mesh GiB"]
    headers += ["peak after save GiB", "peak after load GiB", "load"]
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "io_large.json", json.dumps(rows, indent=1))
    write_report(
        args.out / "io_large.md",
        title="Large binary PLY: save_mesh and load_mesh time and memory",
        intro=__doc__.split("\n\n")[1],
        env=env,
        sections=[("Results", markdown_table(headers, table))],
        command=command_line(),
        weights=None,  # mesh files only
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
