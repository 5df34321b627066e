"""Cold start of `dmd-jax denoise`: new processes, their compiles, the cache and the warm-up.

Every row is a fresh process running the CLI (`python -m dmd_jax.cli denoise`, what the
`dmd-jax` script runs) on a noisy mesh, timed from the outside (the whole process:
Python, imports, reading, the call, writing) and by the time the CLI itself reports for
the call. Per repeat, with a new empty compilation cache under `out/`:

* `cold first`: `armadillo.obj` (86k faces) with the empty cache (a new machine, or a
  new version).
* `second, no warm-up`: `common3d_igea.ply` (80k faces) next: another rung of the shape
  ladder (`dmd_jax.shape_ladder`), so its program is compiled.
* `dmd-jax warmup`: the programs of every rung from 1k to 1M faces, compiled once.
* `after warm-up`: a new process on each of: generated grids of 10k, 300k and 500k
  faces, `common3d_ogre.ply` and igea (80k faces; armadillo and igea padded to
  different shapes before the ladder too: the table of shapes below), and a UV sphere
  of 79k faces whose poles have valence 256 (its own table layout: compiled unless the
  warm-up ran with `--all-layouts`).
* `cache off`: `DMD_JAX_COMPILE_CACHE=0`, every process compiles (as before the cache).
* `bnf`: the library's bilateral normal filter, also a fresh process, on igea.
* `warm`: `denoise` and `bnf` in one process on igea after a first call (median of the
  repeats; what the README's speed table measures).

Repeats are interleaved; medians, min-max. `--profile` adds the breakdown of one cold
call and one call after the warm-up (imports, weights, reading, tracing, lowering, XLA
compile per program, the rest of the call), quoted in `docs/cold-start.md`.

Meshes are made here, under `out/cold_start/` (never committed): Gaussian noise along
the normals, 0.3 mean edge lengths, seed 1, on `../shared/meshes` and on generated
wavy grids (`benchmarks.common.noisy_grid`) and a UV sphere.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    environment,
    markdown_table,
    write_report,
)

OUT = HERE.parent / "out" / "cold_start"
# The first process's mesh and the next one's (another rung, no warm-up between them).
FIRST = "armadillo.obj"
NEXT = "train/common3d_igea.ply"
# Meshes run in new processes after `dmd-jax warmup`: generated grids of 10k, 300k and
# 500k faces, two real ones, and a mesh with two vertices of valence 256.
AFTER_WARMUP = (
    "grid:10000",
    "train/common3d_ogre.ply",
    NEXT,
    "grid:300000",
    "grid:500000",
    "uvsphere:128",
)

# One process: the stages of a cold `denoise` call, timed, with JAX's compile events.
PROFILE = r"""
import collections, json, logging, re, sys, time
t0 = time.perf_counter()
import jax
t_jax = time.perf_counter()
from jax import monitoring
durations = collections.defaultdict(float)
counts = collections.Counter()
monitoring.register_event_duration_secs_listener(
    lambda e, d, **kw: durations.__setitem__(e, durations[e] + d))
monitoring.register_event_listener(lambda e, **kw: counts.__setitem__(e, counts[e] + 1))
jax.config.update("jax_log_compiles", True)
compiles = []
class Log(logging.Handler):
    def emit(self, record):
        m = re.match(r"Finished XLA compilation of (.*) in ([0-9.]+) sec", record.getMessage())
        if m:
            compiles.append((m.group(1), float(m.group(2))))
for name in ("jax._src.interpreters.pxla", "jax._src.dispatch", "jax._src.pjit",
             "jax._src.compiler"):
    logger = logging.getLogger(name)
    logger.addHandler(Log())
    logger.propagate = False
import dmd_jax.api, dmd_jax.inference, dmd_jax.io
t_import = time.perf_counter()
from dmd_jax.checkpoints import load_pretrained
bundle = load_pretrained()
t_weights = time.perf_counter()
v, f = dmd_jax.io.load_mesh(sys.argv[1])
t_read = time.perf_counter()
out = dmd_jax.inference.denoise(v, f, bundle)
t_call = time.perf_counter()
by_name = collections.defaultdict(list)
for name, sec in compiles:
    by_name[name].append(sec)
print(json.dumps({
    "import_jax": t_jax - t0, "import_dmd_jax": t_import - t_jax,
    "weights": t_weights - t_import, "read": t_read - t_weights, "call": t_call - t_read,
    "durations": durations, "counts": counts,
    "compiles": {k: [len(s), sum(s)] for k, s in by_name.items()},
    "flax": "flax" in sys.modules,
}))
"""

# One process: `denoise` and `bnf` warm (after a first call of each), interleaved.
WARM = r"""
import json, sys, time
import dmd_jax.inference, dmd_jax.io
from dmd_jax.baselines import bnf
from dmd_jax.checkpoints import load_pretrained
bundle = load_pretrained()
v, f = dmd_jax.io.load_mesh(sys.argv[1])
dmd_jax.inference.denoise(v, f, bundle)
bnf(v, f)
times = {"denoise": [], "bnf": []}
for _ in range(int(sys.argv[2])):
    t = time.perf_counter(); dmd_jax.inference.denoise(v, f, bundle)
    times["denoise"].append(time.perf_counter() - t)
    t = time.perf_counter(); bnf(v, f)
    times["bnf"].append(time.perf_counter() - t)
print(json.dumps(times))
"""


def noisy_mesh(shared: Path, name: str) -> Path:
    """The benchmark's noisy mesh `name` (a file under `shared`, `grid:FACES` or
    `uvsphere:SEGMENTS`) as an OBJ under `OUT`."""
    OUT.mkdir(parents=True, exist_ok=True)
    out = OUT / (name.replace("/", "_").replace(":", "_") + "_noisy.obj")
    if out.is_file():
        return out
    source = shared / name
    if name.startswith(("grid:", "uvsphere:")):
        import trimesh

        from benchmarks.common import noisy_grid

        kind, n = name.split(":")
        if kind == "grid":
            v, f = noisy_grid(int(n), seed=1)
        else:  # about 80k faces; trimesh gives its poles valence 2n
            m = trimesh.creation.uv_sphere(count=[80_000 // (4 * int(n)), int(n)])
            v, f = m.vertices, m.faces
        source = OUT / (out.stem + "_clean.obj")
        trimesh.Trimesh(v, f, process=False).export(source)
    subprocess.run(
        [
            sys.executable,
            "-m",
            "dmd_jax.cli",
            "add-noise",
            str(source),
            "-o",
            str(out),
            "--level",
            "0.3",
            "--units",
            "edge",
            "--direction",
            "normal",
            "--seed",
            "1",
            "--overwrite",
        ],
        check=True,
        capture_output=True,
    )
    return out


def mesh_facts(path: Path) -> dict:
    """Faces, vertices, largest valence, and the whole-mesh path's rung and table widths
    (and the padded sizes the scheme before the ladder gave: each count on its own)."""
    from dmd_jax.graph import build_mesh_graph, fine_padded_sizes_for
    from dmd_jax.inference import whole_mesh_graph
    from dmd_jax.io import load_mesh
    from dmd_jax.shape_ladder import layout_of

    v, f = load_mesh(path)
    g = whole_mesh_graph(f, v.shape[0], "auto")
    old = fine_padded_sizes_for(build_mesh_graph(f, v.shape[0]))
    valence = np.bincount(
        np.unique(np.sort(np.concatenate([f[:, :2], f[:, 1:], f[:, ::2]]), 1), axis=0).ravel()
    )
    return {
        "faces": int(f.shape[0]),
        "vertices": int(v.shape[0]),
        "valence": int(valence.max()),
        "rung": f"{g.n_vertex:,} / {'/'.join('-' if w is None else str(w) for w in layout_of(g))}",
        "old": f"{old.n_vertex} / {old.n_face} / {old.n_vertex_edge} / {old.n_face_edge}",
    }


def env_with(cache) -> dict:
    env = dict(os.environ)
    env["DMD_JAX_COMPILE_CACHE"] = str(cache)
    return env


def run_cli(mesh: Path, cache, method: str = "dmd") -> dict:
    """One `denoise` process: its wall time and the time it reports for the call."""
    out = OUT / "result.obj"
    start = time.perf_counter()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "dmd_jax.cli",
            "denoise",
            str(mesh),
            "-o",
            str(out),
            "--overwrite",
            "--method",
            method,
        ],
        env=env_with(cache),
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    reported = re.search(r" in ([0-9.]+) s -> ", done.stdout)
    compiled = re.search(r"compiled the network for meshes of this size \(([0-9.]+) s", done.stderr)
    return {
        "wall": wall,
        "reported": float(reported.group(1)),
        "compile": float(compiled.group(1)) if compiled else 0.0,
    }


def run_warmup(cache) -> float:
    """`dmd-jax warmup` (1k-1M faces) into `cache`; its wall time."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "dmd_jax.cli", "warmup", "--quiet"],
        env=env_with(cache),
        capture_output=True,
        text=True,
    )
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    return time.perf_counter() - start


def run_script(script: str, *args, cache="0") -> dict:
    done = subprocess.run(
        [sys.executable, "-c", script, *map(str, args)],
        env=env_with(cache),
        capture_output=True,
        text=True,
    )
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def med(xs) -> float:
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def cell(xs) -> str:
    return f"{med(xs):.2f} ({min(xs):.2f}-{max(xs):.2f})"


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def profile_rows(report: dict) -> list[list[str]]:
    d, c = report["durations"], report["counts"]
    compile_total = d.get("/jax/core/compile/backend_compile_duration", 0.0)
    trace = d.get("/jax/core/compile/jaxpr_trace_duration", 0.0)
    lower = d.get("/jax/core/compile/jaxpr_to_mlir_module_duration", 0.0)
    retrieve = d.get("/jax/compilation_cache/cache_retrieval_time_sec", 0.0)
    rows = [
        ["import jax", f"{report['import_jax']:.2f}"],
        ["import dmd_jax (API, inference, I/O)", f"{report['import_dmd_jax']:.2f}"],
        ["weights (read, check the param shapes)", f"{report['weights']:.2f}"],
        ["read the mesh", f"{report['read']:.2f}"],
        ["the `denoise` call", f"{report['call']:.2f}"],
        ["  of it, and of the weights: tracing (jaxpr)", f"{trace:.2f}"],
        ["  lowering to MLIR", f"{lower:.2f}"],
        ["  XLA compile, all programs", f"{compile_total:.2f}"],
        ["  JAX persistent cache reads", f"{retrieve:.2f}"],
        [
            "  programs compiled by XLA (or loaded by JAX's cache)",
            str(sum(n for n, _ in report["compiles"].values())),
        ],
        [
            "  network executables loaded / compiled (dmd_jax cache)",
            f"{c.get('/dmd_jax/compile_cache/executable_hit', 0)} / "
            f"{c.get('/dmd_jax/compile_cache/executable_miss', 0)}",
        ],
    ]
    # Traced and compiled, the network's Flax module is imported; loaded, it is not.
    rows.append(["  Flax imported", "yes" if report.get("flax") else "no"])
    top = sorted(report["compiles"].items(), key=lambda kv: -kv[1][1])[:4]
    for name, (n, sec) in top:
        rows.append([f"  XLA compile of {name} ({n}x)", f"{sec:.2f}"])
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=3, help="interleaved repeats (default 3)")
    p.add_argument("--shared", type=Path, default=None, help="the shared meshes folder")
    p.add_argument("--profile", action="store_true", help="add the cold call's breakdown")
    p.add_argument("--name", default="cold_start", help="report name under results/")
    args = p.parse_args(argv)
    from dmd_jax.protocol import shared_meshes_dir

    shared = args.shared or shared_meshes_dir()
    names = [FIRST, NEXT, *AFTER_WARMUP]
    meshes = {name: noisy_mesh(shared, name) for name in dict.fromkeys(names)}
    facts = {name: mesh_facts(path) for name, path in meshes.items()}
    loads = [load_average()]
    rows: dict[tuple, dict[str, list[float]]] = {}

    def add(key, result):
        for k, v in result.items():
            rows.setdefault(key, {}).setdefault(k, []).append(v)

    warm: dict[str, list[float]] = {}
    warmups = []
    for rep in range(args.repeat):
        cache = OUT / f"cache-{rep}"
        shutil.rmtree(cache, ignore_errors=True)
        add(("cold first", FIRST), run_cli(meshes[FIRST], cache))
        add(("second, no warm-up", NEXT), run_cli(meshes[NEXT], cache))
        warmups.append(run_warmup(cache))
        for name in AFTER_WARMUP:
            add(("after warm-up", name), run_cli(meshes[name], cache))
        shutil.rmtree(cache, ignore_errors=True)
        add(("cache off", NEXT), run_cli(meshes[NEXT], "0"))
        add(("bnf", NEXT), run_cli(meshes[NEXT], "0", method="bnf"))
        for key, times in run_script(WARM, meshes[NEXT], 3).items():
            warm.setdefault(key, []).extend(times)
        loads.append(load_average())
    profiles = {}
    if args.profile:
        cache = OUT / "cache-profile"
        shutil.rmtree(cache, ignore_errors=True)
        profiles["cold first call (empty cache)"] = run_script(PROFILE, meshes[FIRST], cache=cache)
        run_warmup(cache)
        profiles["new process after the warm-up (another mesh)"] = run_script(
            PROFILE, meshes[NEXT], cache=cache
        )
        shutil.rmtree(cache, ignore_errors=True)
        loads.append(load_average())

    def label(name):
        fx = facts[name]
        return f"{Path(name).name} ({fx['faces']:,} faces)"

    table = [
        [what, label(name), cell(r["reported"]), cell(r["wall"]), cell(r["compile"])]
        for (what, name), r in rows.items()
    ]
    table.append(["`dmd-jax warmup` (1k-1M faces)", "", "", cell(warmups), ""])
    for what, key in (("warm, in-process", "denoise"), ("warm bnf, in-process", "bnf")):
        table.append([what, label(NEXT), cell(warm[key]), "", ""])
    shape_rows = [
        [
            Path(n).name,
            f"{fx['faces']:,}",
            f"{fx['vertices']:,}",
            fx["valence"],
            fx["rung"],
            fx["old"],
        ]
        for n, fx in facts.items()
    ]
    sections = [
        (
            "Cold, second-process and warm calls",
            markdown_table(
                [
                    "call",
                    "mesh",
                    "time reported by the CLI, s",
                    "whole process wall, s",
                    "of it compiling the network, s",
                ],
                table,
            )
            + "\n\nMedian (min-max) of the repeats. Load average (1, 5, 15 min) before and "
            "after each repeat: " + "; ".join(loads) + ".",
        ),
        (
            "Shapes of the meshes",
            markdown_table(
                [
                    "mesh",
                    "faces",
                    "vertices",
                    "largest valence",
                    "rung: padded vertices / table widths",
                    "before the ladder: padded vertices / faces / vertex edges / face edges",
                ],
                shape_rows,
            ),
        ),
    ]
    for title, report in profiles.items():
        sections.append(
            (f"Breakdown: {title}", markdown_table(["stage", "s"], profile_rows(report)))
        )
    env = environment()
    write_report(
        RESULTS_DIR / f"{args.name}.md",
        title="Cold start of dmd-jax denoise",
        env=env,
        sections=sections,
        intro=__doc__.split("\n\n")[0],
    )
    print((RESULTS_DIR / f"{args.name}.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
