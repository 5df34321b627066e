"""`dmd_jax.denoise` time and peak memory against mesh size, `small` and `paper` presets.

Meshes are triangulated grids (`common.grid_faces`: interior valence 6, as a
remeshed surface) of 1k to 1M faces, bent into a wavy height field and given Gaussian
noise of 0.2 edge lengths. `small` runs the bundled weights, whose pass rule
(the weights' policy) gives these meshes one pass (the JSON's `passes`); `paper`
params are freshly initialised (`model.init_params`): the cost of a forward pass does not
depend on their values.

Every size runs in a FRESH subprocess, so its peak resident memory (`ru_maxrss`) is its
own. There the network is compiled first (`jit(...).lower(...).compile()`, timed: that
is the compile time), then these cases are timed round-robin:

* `denoise`: `dmd_jax.denoise(vertices, faces, bundle)`, end to end: validation,
  canonical frame, `build_mesh_graph`, padding, host-to-device copy, the network, copy
  back;
* `network`: the jitted network alone, on the padded batch already on the device, with
  the ELL neighbour tables `denoise` uses (`graph.with_ell_layout`);
* `network (segment_sum)`: the same network on the same batch without the tables, so
  every aggregation is a sorted `segment_sum` (as in training);
* `build_mesh_graph`: the host-side graph construction alone;
* `pymeshlab two_step` (at `--pymeshlab-faces`): `baselines.meshlab.pymeshlab_filter(v, f,
  "two_step")`, the classic two-step filter (Sun et al. 2007, 20 normal and 50 vertex
  iterations), for the ratio against `denoise` at that size;
* `bnf` (at the same size): `dmd_jax.baselines.bnf(v, f)` with its defaults, the
  library's quickest feature-preserving filter, compiled by a first call.

The scaling exponent is the least-squares slope of log(median denoise time) against
log(faces) over the sizes >= 10k faces. The `paper` preset stops at the first size whose
denoise median exceeds `--paper-max-s` or whose peak memory exceeds `--paper-max-gib`,
and skips sizes whose extrapolated memory would not fit in the machine.

Run `python benchmarks/bench_inference.py --help`; `make bench` runs the default set.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    available_gib,
    command_line,
    environment,
    format_ms,
    format_timing,
    markdown_table,
    median,
    noisy_grid,
    peak_rss_gib,
    plot_loglog,
    time_interleaved,
    write_csv,
    write_report,
    write_text,
)

PRESETS = ("small", "paper")
FACES = (1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000)
CASES = (
    "denoise",
    "network",
    "network (segment_sum)",
    "build_mesh_graph",
    "pymeshlab two_step",
    "bnf",
)
FIT_FROM = 10_000
# Above this many faces the `paper` preset's segment-sum comparison is skipped: its
# per-edge messages (`[n_edge, 512]`) ran out of the 24 GiB machine at 300k faces.
PAPER_SEGMENT_SUM_MAX_FACES = 100_000
# Timed rounds of one size stop short of this, so a size stays within the 600 s a worker
# process may run.
HARD_CAP_S = 400.0


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------
# Worker: one preset and one size, in its own process
# --------------------------------------------------------------------------------------


def measure(
    preset: str,
    n_face: int,
    *,
    repeat: int = 5,
    budget_s: float = 300.0,
    min_rounds: int = 3,
    pymeshlab: bool = False,
) -> dict:
    """Compiles and times one preset on one mesh size in this process (see module doc).

    Args:
      preset: a preset of `dmd_jax.config`.
      n_face: target face count.
      repeat: timed rounds at most...
      budget_s: ...as long as they fit in this many seconds...
      min_rounds: ...but at least this many (capped by `repeat`) while they fit in
        `HARD_CAP_S`.
      pymeshlab: time `pymeshlab two_step` as well.

    Returns:
      A JSON-able dict: sizes, compile seconds, times per case, peak RSS.
    """
    import jax
    import jax.numpy as jnp

    from dmd_jax import config, encoding, forward, inference, model
    from dmd_jax import graph as graph_lib
    from dmd_jax.baselines import bnf
    from dmd_jax.baselines.meshlab import pymeshlab_filter
    from dmd_jax.checkpoints import ModelBundle, load_pretrained

    load = os.getloadavg()[0]
    if preset == "small":
        # The bundled weights: their config decides how many passes `denoise` runs
        # (its policy's pass rule), so the measured call is the one users make.
        bundle = load_pretrained()
        cfg = bundle.config
    else:
        cfg = config.preset(preset)
        params = model.init_params(cfg.model, jax.random.PRNGKey(0))
        bundle = ModelBundle(params=params, config=cfg, meta={})
    v, f = noisy_grid(n_face)
    rss_before = peak_rss_gib()

    # The network on the padded batch `denoise` builds, compiled ahead of time: the jit
    # cache then holds it, and `denoise` below does not compile again.
    predict = forward.predictor(cfg)
    x = encoding.mesh_frame(cfg.model.encoding, v, f).apply(v)
    # The padded graph exactly as `denoise` builds it (its padding policy and ELL
    # tables); the same graph without the tables, aggregated by segment sums, is the
    # comparison.
    graph = inference.whole_mesh_graph(f, v.shape[0], "auto")
    noisy = jnp.asarray(graph_lib.pad_vertex_array(x.astype(np.float32), graph.n_vertex))
    graph_ell = jax.tree.map(jnp.asarray, graph)
    graph_seg = jax.tree.map(jnp.asarray, graph._replace(vertex_ell=None, face_ell=None))
    start = time.perf_counter()
    compiled = predict.lower(bundle.params, noisy, graph_ell).compile()
    compile_s = time.perf_counter() - start
    temp = compiled.memory_analysis()
    temp_gib = None if temp is None else temp.temp_size_in_bytes / 2**30

    start, cpu_start = time.perf_counter(), time.process_time()
    out, info = inference.denoise(v, f, bundle, return_info=True)
    first_s = time.perf_counter() - start
    cpu_s = time.process_time() - cpu_start
    if not np.all(np.isfinite(out)) or out.shape != v.shape:
        raise AssertionError("denoise returned a wrong shape or non-finite vertices")
    rss_denoise = peak_rss_gib()
    compare = preset != "paper" or n_face <= PAPER_SEGMENT_SUM_MAX_FACES
    if compare:
        # Run after the memory reading above, so the peak is that of `denoise` alone.
        predict(bundle.params, noisy, graph_seg).block_until_ready()

    cpu_times = []

    def timed_denoise():
        start = time.process_time()
        result = inference.denoise(v, f, bundle)
        cpu_times.append(time.process_time() - start)
        return result

    cases = {
        "denoise": timed_denoise,
        "network": lambda: predict(bundle.params, noisy, graph_ell),
        "build_mesh_graph": lambda: graph_lib.build_mesh_graph(f, v.shape[0]),
    }
    if compare:
        cases["network (segment_sum)"] = lambda: predict(bundle.params, noisy, graph_seg)
    if pymeshlab:
        cases["pymeshlab two_step"] = lambda: pymeshlab_filter(v, f, "two_step")
        # The library's quickest feature-preserving filter, compiled by a first call.
        bnf(v, f)
        cases["bnf"] = lambda: bnf(v, f)
    # A round costs about three denoise calls (denoise, two networks; the rest is small).
    rounds = int(np.clip(budget_s // max(3.5 * first_s, 1e-3), 1, repeat))
    if rounds < min(min_rounds, repeat) and min_rounds * 3.5 * first_s <= HARD_CAP_S:
        rounds = min(min_rounds, repeat)
    warmup = 0 if first_s > 10 else 1
    timings = time_interleaved(cases, repeat=rounds, warmup=warmup)
    device = jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    return {
        "preset": preset,
        "faces": int(f.shape[0]),
        "vertices": int(v.shape[0]),
        "padded_vertices": int(graph.n_vertex),
        "padded_faces": int(graph.n_face),
        "load_1min": load,
        "compile_s": compile_s,
        "passes": info.passes,
        "first_call_s": first_s,
        "first_call_cpu_s": cpu_s,
        "denoise_cpu_s": cpu_times[warmup:],
        "xla_temp_gib": temp_gib,
        "device_peak_gib": None if not stats else stats.get("peak_bytes_in_use", 0) / 2**30,
        "device": f"{device.platform} ({device.device_kind})",
        "rss_before_gib": rss_before,
        "peak_rss_gib": rss_denoise,
        "peak_rss_all_gib": peak_rss_gib(),
        "times": {name: list(t.times) for name, t in timings.items()},
    }


# --------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------


def run_worker(preset: str, n_face: int, args) -> dict:
    """`measure` in a fresh Python process; returns its dict or `{"error": ...}`."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", preset, str(n_face)]
    cmd += ["--repeat", str(args.repeat), "--budget-s", str(args.budget_s)]
    cmd += ["--min-rounds", str(args.min_rounds)]
    if n_face == args.pymeshlab_faces:
        cmd.append("--pymeshlab")
    try:
        proc = subprocess.run(
            cmd, cwd=REPO, capture_output=True, text=True, timeout=args.worker_timeout_s
        )
    except subprocess.TimeoutExpired:
        return {"error": f"ran past {args.worker_timeout_s:.0f} s"}
    if proc.returncode == -9:
        return {"error": "killed by SIGKILL (exit -9; usually the kernel's out-of-memory killer)"}
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
        return {"error": f"exit {proc.returncode}: {tail[0][:200]}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def cpu_seconds(row: dict) -> float:
    """Median process CPU time (all threads) of one denoise call."""
    return median(row.get("denoise_cpu_s") or [row["first_call_cpu_s"]])


def case_seconds(row: dict, case: str) -> float:
    """Median seconds of a case of one size; `denoise CPU` is process CPU time."""
    return cpu_seconds(row) if case == "denoise CPU" else median(row["times"][case])


def fit_exponent(rows: list[dict], case: str = "denoise") -> float | None:
    """Least-squares slope of log time against log faces over the sizes >= FIT_FROM."""
    pts = [(r["faces"], case_seconds(r, case)) for r in rows if r["faces"] >= FIT_FROM]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def sweep(preset: str, sizes, args) -> tuple[list[dict], list[str]]:
    """Runs the sizes of one preset in order; stops the `paper` preset at its limits."""
    rows, notes = [], []
    limited = preset == "paper"
    for n_face in sizes:
        if limited and rows:
            last = rows[-1]
            ratio = n_face / last["faces"]
            grown = last["rss_before_gib"] + ratio * (last["peak_rss_gib"] - last["rss_before_gib"])
            room = min(args.paper_max_gib, 0.8 * available_gib())
            if grown > room:
                notes.append(
                    f"`{preset}` at {n_face:,} faces skipped: memory extrapolated linearly "
                    f"from {last['faces']:,} faces is {grown:.1f} GiB, more than the "
                    f"{room:.1f} GiB allowed (limit {args.paper_max_gib:g} GiB, 80 % of "
                    "the memory available)"
                )
                break
        print(f"{preset} {n_face:,} faces ...", file=sys.stderr, flush=True)
        row = run_worker(preset, n_face, args)
        if "error" in row:
            notes.append(f"`{preset}` at {n_face:,} faces failed: {row['error']}")
            break
        rows.append(row)
        t = median(row["times"]["denoise"])
        print(
            f"  denoise {t:.3f} s, network {median(row['times']['network']):.3f} s, "
            f"graph {median(row['times']['build_mesh_graph']):.3f} s, "
            f"compile {row['compile_s']:.1f} s, peak {row['peak_rss_gib']:.2f} GiB",
            file=sys.stderr,
            flush=True,
        )
        if limited and (t > args.paper_max_s or row["peak_rss_gib"] > args.paper_max_gib):
            notes.append(
                f"`{preset}` stopped after {row['faces']:,} faces: denoise {t:.1f} s "
                f"(limit {args.paper_max_s:g} s), peak {row['peak_rss_gib']:.1f} GiB "
                f"(limit {args.paper_max_gib:g} GiB)"
            )
            break
    return rows, notes


def _segment_sum_cells(t: dict) -> list[str]:
    seg = t.get("network (segment_sum)")
    if not seg:  # results from before the network used ELL tables
        return ["—", "—"]
    return [format_timing(seg), f"{median(seg) / median(t['network']):.2f}×"]


def table(rows: list[dict]) -> str:
    """Times: one line per preset and size."""
    headers = ["preset", "faces", "vertices", "padded vertices", "compile s"]
    headers += ["denoise ms (IQR)", "network ms (IQR)", "build_mesh_graph ms (IQR)"]
    headers += ["rest ms", "network, segment_sum ms (IQR)", "segment_sum / ELL"]
    headers += ["denoise CPU s", "runs", "load", "run"]
    body = []
    for r in rows:
        t = r["times"]
        rest = median(t["denoise"]) - median(t["network"]) - median(t["build_mesh_graph"])
        body.append(
            [r["preset"], f"{r['faces']:,}", f"{r['vertices']:,}", f"{r['padded_vertices']:,}"]
            + [f"{r['compile_s']:.1f}", format_timing(t["denoise"]), format_timing(t["network"])]
            + [format_timing(t["build_mesh_graph"]), format_ms(rest)]
            + _segment_sum_cells(t)
            + [f"{cpu_seconds(r):.3g}", len(t["denoise"]), f"{r['load_1min']:.1f}"]
            + [r.get("run", 0)]
        )
    return markdown_table(headers, body)


def memory_table(rows: list[dict]) -> str:
    """Memory: peak RSS of the size's process, XLA's temporary buffer, device peak."""
    device = any(r.get("device_peak_gib") is not None for r in rows)
    headers = ["preset", "faces", "peak RSS GiB", "RSS before GiB", "XLA temp GiB"]
    headers += ["device peak GiB"] if device else []
    body = []
    for r in rows:
        temp = r.get("xla_temp_gib")
        line = [r["preset"], f"{r['faces']:,}", f"{r['peak_rss_gib']:.2f}"]
        line += [f"{r['rss_before_gib']:.2f}", "—" if temp is None else f"{temp:.2f}"]
        if device:
            peak = r.get("device_peak_gib")
            line.append("—" if peak is None else f"{peak:.2f}")
        body.append(line)
    return markdown_table(headers, body)


def targets(rows: list[dict], args) -> tuple[str, list[tuple]]:
    """The issue's targets, each with the measured value and met / missed."""
    out = []
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset]
        for case, what in (("denoise", "wall time"), ("denoise CPU", "CPU time")):
            k = fit_exponent(mine, case)
            if k is None:
                continue
            sizes = [r["faces"] for r in mine if r["faces"] >= FIT_FROM]
            out.append(
                (
                    f"`{preset}` scaling exponent ≤ 1.1 (denoise {what}, {min(sizes):,}–"
                    f"{max(sizes):,} faces)",
                    f"{k:.2f}",
                    "met" if k <= 1.1 else "missed",
                )
            )
    big = [r for r in rows if r["preset"] == "small" and r["faces"] >= 900_000]
    if big:
        r = big[0]
        t = median(r["times"]["denoise"])
        out.append(
            (
                f"`small` denoises {r['faces']:,} faces in ≤ 30 s",
                f"{t:.1f} s",
                "met" if t <= 30 else "missed",
            )
        )
        cpu = cpu_seconds(r)
        out.append(
            (
                "same, on 2 dedicated cores (estimated: wall ≤ CPU time of a call, "
                "which on idle cores cannot be exceeded by compute-bound work)",
                f"{cpu:.1f} CPU s",
                "met (estimated)" if cpu <= 30 else "missed (estimated)",
            )
        )
        out.append(
            (
                f"`small` denoises {r['faces']:,} faces in ≤ 8 GB peak memory",
                f"{r['peak_rss_gib'] * 2**30 / 1e9:.2f} GB",
                "met" if r["peak_rss_gib"] * 2**30 <= 8e9 else "missed",
            )
        )
    for r in rows:
        if "pymeshlab two_step" in r["times"]:
            ratio = median(r["times"]["denoise"]) / median(r["times"]["pymeshlab two_step"])
            out.append(
                (
                    f"`{r['preset']}` faster than pymeshlab two-step at {r['faces']:,} faces "
                    "(denoise / two_step, same process, interleaved)",
                    f"{ratio:.2f}× ({format_ms(median(r['times']['denoise']))} ms vs "
                    f"{format_ms(median(r['times']['pymeshlab two_step']))} ms)",
                    "met" if ratio < 1 else "missed",
                )
            )
        if "bnf" in r["times"]:
            ratio = median(r["times"]["denoise"]) / median(r["times"]["bnf"])
            out.append(
                (
                    f"`{r['preset']}` no slower than bnf at {r['faces']:,} faces "
                    "(denoise / bnf, same process, interleaved)",
                    f"{ratio:.2f}× ({format_ms(median(r['times']['denoise']))} ms vs "
                    f"{format_ms(median(r['times']['bnf']))} ms)",
                    "met" if ratio <= 1 else "missed",
                )
            )
    return markdown_table(["target", "measured", ""], out), out


CSV_HEADERS = (
    "preset",
    "faces",
    "vertices",
    "padded_vertices",
    "case",
    "median_s",
    "q1_s",
    "q3_s",
    "runs",
    "compile_s",
    "peak_rss_gib",
    "rss_before_gib",
)


def csv_rows(rows: list[dict]) -> list[tuple]:
    out = []
    for r in rows:
        for case, times in r["times"].items():
            q1, q3 = np.percentile(times, [25, 75])
            out.append(
                (r["preset"], r["faces"], r["vertices"], r["padded_vertices"], case)
                + (median(times), float(q1), float(q3), len(times), r["compile_s"])
                + (r["peak_rss_gib"], r["rss_before_gib"])
            )
    return out


def plot(rows: list[dict], path: Path) -> Path:
    time_series, mem_series = {}, {}
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset]
        faces = [r["faces"] for r in mine]
        for case in ("denoise", "denoise CPU", "network"):
            k = fit_exponent(mine, case)
            label = f"{preset} {case}" + (f" (slope {k:.2f})" if k is not None else "")
            time_series[label] = (faces, [case_seconds(r, case) for r in mine])
        mem_series[f"{preset} peak RSS"] = (faces, [r["peak_rss_gib"] for r in mine])
    graph_rows = {r["faces"]: r for r in rows}  # host work: the same for every preset
    faces = sorted(graph_rows)
    k = fit_exponent(list(graph_rows.values()), "build_mesh_graph")
    time_series["build_mesh_graph" + (f" (slope {k:.2f})" if k is not None else "")] = (
        faces,
        [median(graph_rows[n]["times"]["build_mesh_graph"]) for n in faces],
    )
    for r in rows:
        if "pymeshlab two_step" in r["times"]:
            time_series["pymeshlab two_step"] = (
                [r["faces"]],
                [median(r["times"]["pymeshlab two_step"])],
            )
    return plot_loglog(
        path,
        [("median time (s)", time_series), ("peak resident memory (GiB)", mem_series)],
        xlabel="faces",
        ylabel="",
        suptitle="dmd_jax.denoise on noisy grids (float32, CPU); fresh process per size",
    )


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    p.add_argument("--faces", type=int, nargs="+", default=list(FACES), help="target faces")
    p.add_argument("--repeat", type=int, default=5, help="timed rounds at most")
    p.add_argument(
        "--budget-s", type=float, default=300.0, help="seconds per size for the timed rounds"
    )
    p.add_argument(
        "--min-rounds",
        type=int,
        default=3,
        help=f"timed rounds per size at least, where they fit in {HARD_CAP_S:.0f} s",
    )
    p.add_argument("--pymeshlab-faces", type=int, default=100_000)
    p.add_argument("--paper-max-s", type=float, default=60.0)
    p.add_argument("--paper-max-gib", type=float, default=16.0)
    p.add_argument("--worker-timeout-s", type=float, default=600.0)
    p.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    p.add_argument("--name", default="inference", help="stem of the result files")
    p.add_argument(
        "--append",
        action="store_true",
        help="keep the other presets' results from an earlier run (<name>.json) and "
        "report them together; lets `make bench` run each preset as its own command",
    )
    p.add_argument(
        "--worker",
        nargs=2,
        metavar=("PRESET", "FACES"),
        help="internal: measure one size in this process and print JSON",
    )
    p.add_argument("--pymeshlab", action="store_true", help="internal, with --worker")
    p.add_argument(
        "--report-only",
        action="store_true",
        help="measure nothing: rewrite the report, CSV and plot from <name>.json",
    )
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        preset, n_face = args.worker[0], int(args.worker[1])
        result = measure(
            preset,
            n_face,
            repeat=args.repeat,
            budget_s=args.budget_s,
            min_rounds=args.min_rounds,
            pymeshlab=args.pymeshlab,
        )
        print(json.dumps(result))
        return 0
    env = environment(("jax", "jaxlib", "flax", "numpy", "pymeshlab"))
    env["memory available at start"] = f"{available_gib():.1f} GiB"
    out = Path(args.out)
    raw_path = out / f"{args.name}.json"
    runs, rows, notes = [], [], []
    if args.report_only:
        old = json.loads(raw_path.read_text())
        last = old["runs"][-1]
        env = last.get("env") or {
            **env,
            "date (UTC)": last["date (UTC)"],
            "git commit": last["git commit"],
            "load average (1 min) at start": last["load at start"],
            "load average (1 min) at end": last["load at end"],
            "XLA_FLAGS": last["XLA_FLAGS"],
            "GLIBC_TUNABLES": last["GLIBC_TUNABLES"],
        }
        report(args, old["runs"], old["rows"], old["notes"], env)
        return 0
    if args.append and raw_path.is_file():
        # Keep what this run does not measure again: other presets, other sizes.
        old = json.loads(raw_path.read_text())
        redo = {(p, n) for p in args.presets for n in args.faces}

        def again(preset: str, faces: int) -> bool:
            return any(p == preset and abs(faces / n - 1) < 0.05 for p, n in redo)

        rows = [r for r in old["rows"] if not again(r["preset"], r["faces"])]
        notes = [n for n in old["notes"] if n["preset"] not in args.presets]
        kept = sorted({r["run"] for r in rows})
        runs = [old["runs"][i] for i in kept]
        for r in rows:
            r["run"] = kept.index(r["run"])
    for preset in args.presets:
        new, why = sweep(preset, sorted(args.faces), args)
        for r in new:
            r["run"] = len(runs)
        rows += new
        notes += [{"preset": preset, "text": text} for text in why]
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    runs.append(
        {
            "presets": list(args.presets),
            "command": command_line(),
            "date (UTC)": env["date (UTC)"],
            "git commit": env["git commit"],
            "load at start": env["load average (1 min) at start"],
            "load at end": env["load average (1 min) at end"],
            "XLA_FLAGS": env["XLA_FLAGS"],
            "GLIBC_TUNABLES": env["GLIBC_TUNABLES"],
            "device": env["JAX backend"],
            "env": env,
        }
    )
    order = {p: i for i, p in enumerate(PRESETS)}
    rows.sort(key=lambda r: (order[r["preset"]], r["faces"]))
    out.mkdir(parents=True, exist_ok=True)
    write_text(raw_path, json.dumps({"runs": runs, "rows": rows, "notes": notes}, indent=1))
    report(args, runs, rows, notes, env)
    return 0


def report(args, runs: list[dict], rows: list[dict], notes: list[dict], env: dict) -> None:
    """Writes `<name>.md`, `.csv` and `.png` from the collected rows."""
    out = Path(args.out)
    target_md, _ = targets(rows, args)
    fits = []
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset]
        for case in ("denoise", "denoise CPU", "network", "build_mesh_graph"):
            k = fit_exponent(mine, case)
            fits.append((preset, case, "—" if k is None else f"{k:.2f}"))
    method = [
        "- Each size runs in a fresh process; `peak RSS` is its `ru_maxrss` after the "
        "compilation and one `denoise` call (`RSS before`: after imports, params and "
        "mesh, before any of that). Sizes are the real faces of the grid.",
        "- `compile s`: `jit(...).lower(...).compile()` of the network at that padded "
        "size (the jit cache then holds it; `denoise` does not compile again).",
        "- Times: medians over `runs` round-robin rounds of every case of one size, after "
        "one warm-up call each (none when the first denoise took over 10 s); IQR in "
        "brackets. `rest` = denoise − network − build_mesh_graph: validation, canonical "
        "frame, padding, host↔device copies (three separate medians, so under load it "
        "can come out negative). `denoise CPU s`: process CPU time (all threads) of one "
        "denoise call after compilation; with 2 cores, wall time on idle cores is at "
        "least half of it.",
        "- `XLA temp GiB`: the compiled network's temporary buffer "
        "(`compiled.memory_analysis().temp_size_in_bytes`); `device peak GiB` (GPU "
        "runs): `peak_bytes_in_use` of the device.",
        f"- Exponents: least squares of log median time on log faces, sizes ≥ {FIT_FROM:,}.",
        "- `load`: the 1-minute load average when the size's process started. Above the "
        "core count (`nproc`) other processes share the cores and absolute times are "
        "inflated by a varying factor; ratios within one size are interleaved and "
        "comparable.",
    ]
    sections = [
        ("Targets", target_md),
        ("Time", table(rows)),
        ("Memory", memory_table(rows)),
        ("Fitted exponents", markdown_table(["preset", "case", "exponent"], fits)),
        ("Method", "\n".join(method)),
    ]
    if notes:
        text = "\n".join(f"- {n['text']}" for n in notes)
        sections.insert(2, ("Stopped or skipped sizes", text))
    run_rows = [
        (i, f"`{r['command']}`", r["date (UTC)"], r["git commit"])
        + (r["load at start"], r["load at end"], r.get("XLA_FLAGS", "(unset)"))
        + (r.get("GLIBC_TUNABLES", "(unset)"), r.get("device", ""))
        for i, r in enumerate(runs)
    ]
    headers = ["run", "command", "date (UTC)", "commit", "load at start", "load at end"]
    headers += ["XLA_FLAGS", "GLIBC_TUNABLES", "device"]
    sections.append(("Runs in this report", markdown_table(headers, run_rows)))
    write_report(
        out / f"{args.name}.md",
        title="Inference scaling: dmd_jax.denoise time and memory vs mesh size",
        intro="\n\n".join(__doc__.split("\n\n")[1:2]),
        env=env,
        sections=sections,
        command=runs[-1]["command"],
    )
    write_csv(out / f"{args.name}.csv", CSV_HEADERS, csv_rows(rows))
    if rows:
        plot(rows, out / f"{args.name}.png")
    print(f"wrote {out / (args.name + '.md')}")


if __name__ == "__main__":
    raise SystemExit(main())
