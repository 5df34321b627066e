"""`dmd_jax.denoise` on meshes of millions of faces under a memory budget (issue 17).

Meshes are the noisy wavy grids of `common.noisy_grid` (interior valence 6,
Gaussian noise of 0.2 edge lengths), generated once per size by this process and handed
to a FRESH worker process as `.npy` files, so the worker's peak resident memory
(`ru_maxrss`, GiB = 2^30 bytes) holds only the mesh, the runtime and `denoise`. The
`small` preset runs the bundled weights (`load_pretrained()`); `paper` fresh params
(`model.init_params`; the cost does not depend on their values).

Each worker times ONE `denoise` call, as a user runs it: the first call, so it includes
compilation (one program per patch shape and pass), the partition, the halos and
the host-side graphs. Modes:

* `default`: `denoise(v, f, bundle, max_memory=BUDGET)`: whole mesh when it fits the
  budget, patches otherwise;
* `patches`: the patch path with the patch size the budget gives, even where the whole
  mesh would fit (so the patch path's own scaling is measured from 1M faces up);
* `whole`: the whole-mesh path, only where its estimated memory fits 80 % of the
  memory available.

Run `python benchmarks/bench_inference_scale.py --help`; `make bench-inference` runs it.
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
from types import SimpleNamespace

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    available_gib,
    command_line,
    environment,
    markdown_table,
    noisy_grid,
    peak_rss_gib,
    write_csv,
    write_report,
    write_text,
)

MODES = ("default", "patches", "whole")
# The budget the targets are judged under: 8 GB (10^9 bytes) of peak resident memory,
# less about 0.5 GiB the worker holds before the call (imports, weights, the mesh at
# 20M faces) and some margin for the estimate.
DEFAULT_BUDGET = "6.5GiB"
CSV_HEADERS = [
    "preset",
    "mode",
    "faces",
    "vertices",
    "path",
    "wall_s",
    "cpu_s",
    "peak_rss_gib",
    "rss_before_gib",
    "patch_size",
    "patches",
    "largest_padded_vertices",
    "halo_rings",
    "budget_gib",
    "load_1min",
]


def worker(preset: str, n_face: int, mode: str, mesh_dir: Path, budget: str) -> dict:
    """One `denoise` call in this (fresh) process; returns the row."""
    import jax

    import dmd_jax
    from dmd_jax import config, memory_plan, model, patch_runner
    from dmd_jax.checkpoints import ModelBundle

    load = os.getloadavg()[0]
    v = np.load(mesh_dir / "vertices.npy")
    f = np.load(mesh_dir / "faces.npy")
    if preset == "small":
        bundle = dmd_jax.load_pretrained()
    else:
        cfg = config.preset(preset)
        bundle = ModelBundle(model.init_params(cfg.model, jax.random.PRNGKey(0)), cfg, {})
    rss_before = peak_rss_gib()
    start, cpu = time.perf_counter(), time.process_time()
    if mode == "default":
        out, info = dmd_jax.denoise(v, f, bundle, max_memory=budget, return_info=True)
    elif mode == "patches":
        # The patch path forced, sized from the same budget (`memory_plan.plan` would
        # take the whole-mesh path where it fits); the weights' own pass policy.
        vv, ff = dmd_jax.mesh.validate_mesh(v, f)
        budget_bytes = memory_plan.parse_memory(budget)
        out, stats = patch_runner.denoise_patches(
            vv, ff, bundle, bundle.policy, "auto", budget_bytes
        )
        info = SimpleNamespace(path="patches", budget_bytes=budget_bytes)
        info.__dict__.update(stats._asdict())
    else:
        out, info = dmd_jax.denoise(v, f, bundle, max_memory=10**15, return_info=True)
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu
    if out.shape != v.shape or not np.all(np.isfinite(out)):
        raise AssertionError("denoise returned a wrong shape or non-finite vertices")
    budget_bytes = info.budget_bytes
    return {
        "preset": preset,
        "mode": mode,
        "faces": int(f.shape[0]),
        "vertices": int(v.shape[0]),
        "path": info.path,
        "wall_s": wall,
        "cpu_s": cpu,
        "peak_rss_gib": peak_rss_gib(),
        "rss_before_gib": rss_before,
        "patch_size": getattr(info, "patch_size", None),
        "patches": getattr(info, "patches", None),
        "largest_padded_vertices": getattr(info, "largest_padded_vertices", None),
        "halo_rings": getattr(info, "halo_rings", None),
        "budget_gib": None if budget_bytes in (None, 10**15) else budget_bytes / 2**30,
        "load_1min": load,
    }


def whole_fits(preset: str, n_face: int) -> bool:
    """Whether the whole-mesh path's estimate fits 80 % of the memory available."""
    from dmd_jax import config, memory_plan

    cfg = config.preset(preset).model
    per_vertex = memory_plan.network_bytes_per_vertex(cfg)
    per_vertex += memory_plan.WHOLE_HOST_BYTES_PER_PADDED_VERTEX
    est = per_vertex * memory_plan.padded_vertices_estimate(n_face // 2, n_face)
    return est <= 0.8 * available_gib() * 2**30


def run(args) -> list[dict]:
    rows = []
    for preset in args.presets:
        for n_face in args.faces:
            with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
                v, f = noisy_grid(n_face)
                np.save(Path(tmp) / "vertices.npy", v)
                np.save(Path(tmp) / "faces.npy", f)
                del v, f
                for mode in args.modes:
                    if mode == "whole" and not whole_fits(preset, n_face):
                        print(f"{preset} {n_face:,} whole: does not fit, skipped", file=sys.stderr)
                        continue
                    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker"]
                    cmd += [preset, str(n_face), mode, tmp, "--max-memory", args.max_memory]
                    print(f"{preset} {n_face:,} {mode} ...", file=sys.stderr, flush=True)
                    try:
                        proc = subprocess.run(
                            cmd,
                            cwd=REPO,
                            capture_output=True,
                            text=True,
                            timeout=args.worker_timeout_s,
                        )
                    except subprocess.TimeoutExpired:
                        print(f"  ran past {args.worker_timeout_s:.0f} s", file=sys.stderr)
                        continue
                    if proc.returncode != 0:
                        tail = (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]
                        print(f"  failed: {tail[:300]}", file=sys.stderr)
                        continue
                    row = json.loads(proc.stdout.strip().splitlines()[-1])
                    print(
                        f"  {row['path']}: {row['wall_s']:.1f} s, peak {row['peak_rss_gib']:.2f} "
                        f"GiB, patch size {row['patch_size']}, patches {row['patches']}",
                        file=sys.stderr,
                        flush=True,
                    )
                    rows.append(row)
    return rows


def fit(rows: list[dict], lo: int, hi: int) -> float | None:
    pts = [(r["faces"], r["wall_s"]) for r in rows if lo * 0.95 <= r["faces"] <= hi * 1.05]
    if len({p[0] for p in pts}) < 2:
        return None
    return float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0])


def report(rows: list[dict], runs: list[dict], out: Path, name: str, env: dict) -> None:
    def cell(x, fmt):
        return "—" if x is None else format(x, fmt)

    table = [
        (
            r["preset"],
            r["mode"],
            f"{r['faces']:,}",
            r["path"],
            f"{r['wall_s']:.1f}",
            f"{r['cpu_s']:.1f}",
            f"{r['peak_rss_gib']:.2f}",
            f"{r['peak_rss_gib'] * 2**30 / 1e9:.2f}",
            cell(r["patch_size"], ","),
            cell(r["patches"], "d"),
            cell(r["largest_padded_vertices"], ","),
            cell(r["halo_rings"], "d"),
            cell(r["budget_gib"], ".2f"),
            f"{r['load_1min']:.1f}",
        )
        for r in rows
    ]
    headers = ["preset", "mode", "faces", "path", "wall s", "CPU s", "peak RSS GiB"]
    headers += ["peak RSS GB", "patch size (owned vertices)", "patches (all passes)"]
    headers += ["largest patch (padded vertices)", "halo rings", "budget GiB", "load"]
    fits = []
    for preset in dict.fromkeys(r["preset"] for r in rows):
        for mode in MODES:
            mine = sorted(
                (r for r in rows if r["preset"] == preset and r["mode"] == mode),
                key=lambda r: r["faces"],
            )
            if len(mine) >= 2:
                k = fit(mine, mine[0]["faces"], mine[-1]["faces"])
                span = f"{mine[0]['faces']:,}–{mine[-1]['faces']:,}"
                fits.append((preset, mode, span, cell(k, ".2f")))
    method = [
        "- One fresh worker process per (preset, size, mode); the mesh is loaded from .npy "
        "files the driver wrote, so generating it does not count in the peak.",
        "- `wall s`: one call, compilation included (every call in a fresh process pays it "
        "again); `CPU s`: process CPU time of that call (all threads).",
        "- `peak RSS`: the worker's `ru_maxrss` after the call (imports, weights and mesh "
        "included); GB = 10^9 bytes, GiB = 2^30.",
        "- Exponents: least squares of log wall time on log faces over the sizes listed.",
        "- `load`: 1-minute load average when the worker started; above 2 (the cores) "
        "other jobs shared the machine and times are inflated.",
    ]
    run_rows = [
        (i, f"`{r['command']}`", r["date (UTC)"], r["git commit"]) for i, r in enumerate(runs)
    ]
    write_report(
        out / f"{name}.md",
        title="Large meshes: patch-wise dmd_jax.denoise under a memory budget",
        intro="\n\n".join(__doc__.split("\n\n")[:3]),
        env=env,
        sections=[
            ("Results", markdown_table(headers, table)),
            (
                "Fitted exponents (wall time)",
                markdown_table(["preset", "mode", "faces", "exponent"], fits),
            ),
            ("Method", "\n".join(method)),
            (
                "Runs in this report",
                markdown_table(["run", "command", "date (UTC)", "commit"], run_rows),
            ),
        ],
        command=runs[-1]["command"] if runs else None,
    )
    write_csv(out / f"{name}.csv", CSV_HEADERS, [[r.get(h) for h in CSV_HEADERS] for r in rows])
    print(f"wrote {out / (name + '.md')}")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=["small"], choices=("small", "paper", "test"))
    p.add_argument("--faces", nargs="+", type=int, default=[1_000_000, 5_000_000])
    p.add_argument("--modes", nargs="+", default=["default"], choices=MODES)
    p.add_argument("--max-memory", default=DEFAULT_BUDGET, help="budget passed to denoise")
    p.add_argument("--worker-timeout-s", type=float, default=7200.0)
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="inference_scale")
    p.add_argument("--append", action="store_true", help="keep other rows of <name>.json")
    p.add_argument("--worker", nargs=4, metavar=("PRESET", "FACES", "MODE", "MESH_DIR"))
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        preset, n_face, mode, mesh_dir = args.worker
        row = worker(preset, int(n_face), mode, Path(mesh_dir), args.max_memory)
        print(json.dumps(row))
        return 0
    env = environment(("jax", "jaxlib", "numpy", "scipy"))
    env["memory available at start"] = f"{available_gib():.1f} GiB"
    raw = args.out / f"{args.name}.json"
    rows, runs = [], []
    if args.append and raw.is_file():
        old = json.loads(raw.read_text())
        redo = {(p, n, m) for p in args.presets for n in args.faces for m in args.modes}
        rows = [
            r
            for r in old["rows"]
            if not any(
                r["preset"] == p and r["mode"] == m and abs(r["faces"] / n - 1) < 0.05
                for p, n, m in redo
            )
        ]
        runs = old["runs"]
    new = run(args)
    rows += new
    runs.append(
        {
            "command": command_line(),
            "date (UTC)": env["date (UTC)"],
            "git commit": env["git commit"],
        }
    )
    rows.sort(key=lambda r: (r["preset"], MODES.index(r["mode"]), r["faces"]))
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(raw, json.dumps({"runs": runs, "rows": rows}, indent=1))
    report(rows, runs, args.out, args.name, env)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
