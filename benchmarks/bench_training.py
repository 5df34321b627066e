"""Training throughput: steps/s and meshes/s per preset and batch size, compilations per epoch.

Training meshes are procedural shapes of `dmd_jax.data` (one per category, seed 0),
remeshed into 800–1600 vertices, so an epoch touches a few vertex buckets. For every
preset and batch size a fresh `train.Trainer` (the `joint` scheme: one phase, one step
function) runs:

1. the first epoch (`ceil(n_mesh / batch)` steps of `pipeline.training_batch`): its
   wall time includes compilation, and `Trainer.compiles` after it is compared with the
   number of distinct padded sizes among its batches (one program per bucket);
2. one untimed step on every bucket the timed steps will use (so none of them compiles);
3. timed steps, round-robin over the batch sizes of the preset (one step of batch 1,
   one of batch 2, ..., each cycling through its own prebuilt batches from epoch 2
   on): `step` is `Trainer.train_step` on a prebuilt batch until its outputs are
   ready; `input` is `pipeline.training_batch` (noise, rotation, padding) on the host.

steps/s = 1 / median step time; meshes/s = batch size × steps/s. `serial` adds the input
pipeline to the step, as `train.train` runs them (one after the other in one thread).

Run `python benchmarks/bench_training.py --help`; `make bench` runs the default set.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    command_line,
    environment,
    format_timing,
    markdown_table,
    median,
    peak_rss_gib,
    time_interleaved,
    write_csv,
    write_report,
    write_text,
)

PRESETS = ("test", "small", "paper")
BATCH_SIZES = {"test": (1, 2, 4), "small": (1, 2, 4), "paper": (1,)}
N_MESH = 8
VERTEX_RANGE = (800, 1600)


def make_meshes(n_mesh: int, vertex_range=VERTEX_RANGE, *, seed: int = 0):
    """`n_mesh` procedural shapes, one per category in order, in the canonical frame."""
    from dmd_jax.data import CATEGORIES, generate_shape

    lo, hi = vertex_range
    n_cat = len(CATEGORIES)
    return [
        generate_shape(CATEGORIES[i % n_cat], seed, i // n_cat, min_vertices=lo, max_vertices=hi)
        for i in range(n_mesh)
    ]


class Run:
    """One preset and batch size: its trainer, state and prebuilt batches."""

    def __init__(self, preset: str, batch_size: int, examples, *, timed_steps: int, edits=None):
        import jax

        from dmd_jax import config, train

        self.preset, self.batch_size, self.examples = preset, batch_size, examples
        cfg = config.preset(preset).with_edits(edits or {})
        cfg = cfg.with_edits({"train": {"batch_size": batch_size}})
        self.cfg = cfg
        self.noise = cfg.noise
        self.trainer = train.Trainer(cfg)
        self.steps_per_epoch = math.ceil(len(examples) / batch_size)
        first = [self.batch(s) for s in range(self.steps_per_epoch)]
        self.state = self.trainer.init(first[0])
        self.epoch_sizes = {b.noisy.shape[-2] for b in first}
        start = time.perf_counter()
        for b in first:
            self.state, out = self.trainer.train_step(self.state, b)
        jax.block_until_ready(out)
        self.first_epoch_s = time.perf_counter() - start
        self.epoch_compiles = self.trainer.compiles
        # Timed steps start at epoch 2, so they are not the batches that compiled.
        start_step = self.steps_per_epoch
        self.timed = [self.batch(s) for s in range(start_step, start_step + timed_steps)]
        self.timed_sizes = {b.noisy.shape[-2] for b in self.timed}
        for n in sorted(self.timed_sizes - self.epoch_sizes):
            b = next(b for b in self.timed if b.noisy.shape[-2] == n)
            self.state, out = self.trainer.train_step(self.state, b)
            jax.block_until_ready(out)
        self.total_compiles = self.trainer.compiles
        self.position = 0
        self.input_step = start_step

    def batch(self, step: int):
        from dmd_jax import pipeline

        t = self.cfg.train
        return pipeline.training_batch(
            self.examples,
            step,
            batch_size=self.batch_size,
            seed=t.seed,
            noise=self.noise,
            rotate=t.rotate,
            encoding=self.cfg.model.encoding,
        )

    def step(self):
        """One train step on the next prebuilt batch (outputs for `block`)."""
        b = self.timed[self.position % len(self.timed)]
        self.position += 1
        self.state, out = self.trainer.train_step(self.state, b)
        return out

    def input(self):
        """Builds the next batch on the host, as `train.train` does every step."""
        self.input_step += 1
        return self.batch(self.input_step)


def measure(preset: str, batch_sizes, examples, *, rounds: int, edits=None) -> list[dict]:
    """Runs one preset at every batch size; timings round-robin over the batch sizes.

    Args:
      preset: a preset of `dmd_jax.config`.
      batch_sizes: meshes per step.
      examples: `pipeline.MeshExample`s.
      rounds: timed steps per batch size.
      edits: `ExperimentConfig.with_edits` applied to the preset (smaller models in
        the smoke test).
    """
    import jax

    runs = []
    for bs in batch_sizes:
        print(f"{preset} batch {bs}: first epoch ...", file=sys.stderr, flush=True)
        run = Run(preset, bs, examples, timed_steps=rounds, edits=edits)
        print(
            f"  {run.first_epoch_s:.1f} s, {run.epoch_compiles} compiles, "
            f"{len(run.epoch_sizes)} buckets",
            file=sys.stderr,
            flush=True,
        )
        runs.append(run)
    load = os.getloadavg()[0]
    cases = {}
    for run in runs:
        cases[f"step {run.batch_size}"] = run.step
        cases[f"input {run.batch_size}"] = run.input
    timings = time_interleaved(cases, repeat=rounds, warmup=0)
    rows = []
    for run in runs:
        if run.trainer.compiles != run.total_compiles:
            raise AssertionError(f"{preset} batch {run.batch_size}: a timed step compiled")
        rows.append(
            {
                "preset": preset,
                "batch_size": run.batch_size,
                "params": int(sum(np.size(x) for x in jax.tree.leaves(run.state.params))),
                "meshes": len(examples),
                "steps_per_epoch": run.steps_per_epoch,
                "first_epoch_s": run.first_epoch_s,
                "epoch_compiles": run.epoch_compiles,
                "epoch_buckets": sorted(int(n) for n in run.epoch_sizes),
                "timed_buckets": sorted(int(n) for n in run.timed_sizes),
                "step_times": list(timings[f"step {run.batch_size}"].times),
                "input_times": list(timings[f"input {run.batch_size}"].times),
                "load_1min": load,
                "peak_rss_gib": peak_rss_gib(),
            }
        )
    return rows


def table(rows: list[dict]) -> str:
    headers = ["preset", "params", "batch", "step ms (IQR)", "steps/s", "meshes/s"]
    headers += ["input ms (IQR)", "serial meshes/s", "runs", "load"]
    body = []
    for r in rows:
        step, inp = median(r["step_times"]), median(r["input_times"])
        body.append(
            [r["preset"], f"{r['params']:,}", r["batch_size"], format_timing(r["step_times"])]
            + [f"{1 / step:.3g}", f"{r['batch_size'] / step:.3g}", format_timing(r["input_times"])]
            + [f"{r['batch_size'] / (step + inp):.3g}", len(r["step_times"])]
            + [f"{r['load_1min']:.1f}"]
        )
    return markdown_table(headers, body)


def compile_table(rows: list[dict]) -> str:
    headers = ["preset", "batch", "steps/epoch", "padded vertex buckets in epoch 1"]
    headers += ["distinct", "compilations", "equal", "first epoch s"]
    body = []
    for r in rows:
        buckets = r["epoch_buckets"]
        body.append(
            [r["preset"], r["batch_size"], r["steps_per_epoch"]]
            + [", ".join(f"{n:,}" for n in buckets), len(buckets), r["epoch_compiles"]]
            + ["yes" if len(buckets) == r["epoch_compiles"] else "**no**"]
            + [f"{r['first_epoch_s']:.1f}"]
        )
    return markdown_table(headers, body)


CSV_HEADERS = (
    "preset",
    "batch_size",
    "case",
    "median_s",
    "q1_s",
    "q3_s",
    "runs",
    "epoch_compiles",
    "epoch_buckets",
    "first_epoch_s",
)


def csv_rows(rows: list[dict]) -> list[tuple]:
    out = []
    for r in rows:
        for case in ("step", "input"):
            times = r[f"{case}_times"]
            q1, q3 = np.percentile(times, [25, 75])
            out.append(
                (r["preset"], r["batch_size"], case, median(times), float(q1), float(q3))
                + (len(times), r["epoch_compiles"], len(r["epoch_buckets"]), r["first_epoch_s"])
            )
    return out


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10.4, 4.2))
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset]
        bs = [r["batch_size"] for r in mine]
        ax[0].plot(bs, [1 / median(r["step_times"]) for r in mine], "o-", label=preset)
        ax[1].plot(
            bs, [r["batch_size"] / median(r["step_times"]) for r in mine], "o-", label=preset
        )
    for a, title in zip(ax, ("steps/s", "meshes/s"), strict=True):
        a.set_xscale("log", base=2)
        a.set_yscale("log")
        a.set_xlabel("batch size (meshes)")
        a.set_title(title, fontsize=10)
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("Training step throughput (CPU, float32, joint scheme)", fontsize=10)
    fig.tight_layout()
    from dmd_jax.io import atomic_write

    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"), overwrite=True)
    plt.close(fig)
    return Path(path)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=["test", "small"], choices=PRESETS)
    p.add_argument(
        "--batch-sizes",
        type=int,
        nargs="+",
        default=None,
        help="default: 1 2 4 (test, small) and 1 (paper)",
    )
    p.add_argument("--meshes", type=int, default=N_MESH, help="training meshes")
    p.add_argument("--vertices", type=int, nargs=2, default=list(VERTEX_RANGE))
    p.add_argument("--rounds", type=int, default=8, help="timed steps per batch size")
    p.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    p.add_argument("--name", default="training", help="stem of the result files")
    p.add_argument(
        "--append",
        action="store_true",
        help="keep the other presets' results from an earlier run (<name>.json)",
    )
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    env = environment(("jax", "jaxlib", "flax", "optax", "numpy"))
    start = time.perf_counter()
    meshes = make_meshes(args.meshes, tuple(args.vertices))
    from dmd_jax import pipeline

    examples = pipeline.make_examples(meshes)
    data_s = time.perf_counter() - start
    out = Path(args.out)
    raw_path = out / f"{args.name}.json"
    runs, rows = [], []
    if args.append and raw_path.is_file():
        old = json.loads(raw_path.read_text())
        runs = [r for r in old["runs"] if not set(r["presets"]) & set(args.presets)]
        rows = [r for r in old["rows"] if r["preset"] not in args.presets]
    for preset in args.presets:
        sizes = args.batch_sizes or BATCH_SIZES[preset]
        rows += measure(preset, sizes, examples, rounds=args.rounds)
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    nv = [len(v) for v, _ in meshes]
    runs.append(
        {
            "presets": list(args.presets),
            "command": command_line(),
            "date (UTC)": env["date (UTC)"],
            "git commit": env["git commit"],
            "load at start": env["load average (1 min) at start"],
            "load at end": env["load average (1 min) at end"],
            "meshes": f"{len(nv)} meshes of {min(nv):,}–{max(nv):,} vertices "
            f"(generated in {data_s:.0f} s)",
        }
    )
    order = {p: i for i, p in enumerate(PRESETS)}
    rows.sort(key=lambda r: (order[r["preset"]], r["batch_size"]))
    out.mkdir(parents=True, exist_ok=True)
    write_text(raw_path, json.dumps({"runs": runs, "rows": rows}, indent=1))
    method = [
        "- `step`: `Trainer.train_step` on a prebuilt batch, waited on; `input`: "
        "`pipeline.training_batch` (noise, rotation, canonical frames, padding) on the "
        "host. Medians over `runs` timed steps (IQR in brackets), round-robin over every "
        "batch size of a preset (step and input alternate), no timed step compiles.",
        "- `serial meshes/s` = batch / (step + input): `train.train` builds each batch "
        "in the same thread before its step.",
        "- Compilations: `Trainer.compiles` (programs in the jit caches of its steps) after "
        "the first epoch, against the distinct padded vertex counts among that epoch's "
        "batches (all padded sizes derive from the vertex bucket and the batch size).",
        "- `load`: the 1-minute load average before the timed steps. Above `nproc` other "
        "processes share the cores and absolute times are inflated by a varying factor.",
    ]
    run_rows = [
        (", ".join(r["presets"]), f"`{r['command']}`", r["date (UTC)"], r["git commit"])
        + (r["load at start"], r["load at end"], r["meshes"])
        for r in runs
    ]
    headers = ["presets", "command", "date (UTC)", "commit", "load at start", "load at end"]
    sections = [
        ("Throughput", table(rows)),
        ("Compilations in the first epoch", compile_table(rows)),
        ("Method", "\n".join(method)),
        ("Runs in this report", markdown_table(headers + ["data"], run_rows)),
    ]
    write_report(
        out / f"{args.name}.md",
        title="Training throughput per preset and batch size",
        intro="\n\n".join(__doc__.split("\n\n")[1:2]),
        env=env,
        sections=sections,
        weights=None,  # trains from fresh params
    )
    write_csv(out / f"{args.name}.csv", CSV_HEADERS, csv_rows(rows))
    if rows:
        plot(rows, out / f"{args.name}.png")
    print(f"wrote {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
