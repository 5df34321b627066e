"""Measures vmapped against sequential seeds at an ablation preset; writes a small report.

    python -m experiments.seed_speedup --preset cpu --seeds 3 --steps 20 --rounds 5

In one process, for the preset's base config and `--seeds` seeds: *sequential* is one
`Trainer.train_step` per seed per step (what training the seeds one after the other
costs per step), *vmapped* is one `multiseed.seeds_step` call for all seeds. Each round
times `--steps` steps of both, interleaved so that a change of machine load hits both
alike; compile steps are left out. Each step is timed with its batch construction on
the host (noise, rotation, padding: part of what training costs) and without it, and
its process CPU time is taken (less sensitive to other jobs on a shared machine). The
report (`--out`, default `experiments/results/seed_speedup.md` and `.json`) gives medians
of the per-step times and their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def measure(preset: str, n_seeds: int, steps: int, rounds: int, data_dir: Path) -> dict:
    """Per-step times (seconds) of both ways; see the module docstring."""
    import jax

    from experiments import multiseed, runner
    from experiments import studies as st

    p = st.get_preset(preset)
    runner.apply_xla_opt_level(p.xla_opt_level)
    runner.ensure_dataset(p, data_dir, progress=False)
    train_ex, _ = runner.load_examples(str(data_dir), p.eval_meshes)
    gammas = runner.ensure_calibration(data_dir, train_ex) if p.calibrate_curvature else None
    base = st.base_config(p, gammas)
    cfgs = [base.with_edits({"train": {"seed": s}}) for s in range(n_seeds)]

    from dmd_jax.train import Trainer

    trainers = [Trainer(c) for c in cfgs]
    first = multiseed.seeds_batch(train_ex, cfgs, 0)
    states = [tr.init(jax.tree.map(lambda x, i=i: x[i], first)) for i, tr in enumerate(trainers)]
    stacked = multiseed.stack_trees(states)
    vstep = multiseed.seeds_step(base, "all")
    from dmd_jax.pipeline import training_batch

    def seq_batch(c, step):
        t = c.train
        return training_batch(
            train_ex,
            step,
            batch_size=t.batch_size,
            seed=c.train.seed,
            noise=c.noise,
            rotate=t.rotate,
            encoding=c.model.encoding,
        )

    out: dict[str, list[float]] = {
        k: [] for k in ("sequential", "vmapped", "sequential_compute", "vmapped_compute")
    }
    out |= {"sequential_cpu": [], "vmapped_cpu": []}
    step = 0
    # Warm-up: compile both programs (every batch of this preset pads to one bucket).
    for i, tr in enumerate(trainers):
        states[i], m = tr.train_step(states[i], seq_batch(cfgs[i], step))
        jax.block_until_ready(m)
    b = multiseed.seeds_batch(train_ex, cfgs, step)
    stacked, m = vstep(stacked, b.noisy, b.clean, b.graph, multiseed.step_rngs(cfgs, step))
    jax.block_until_ready(m)
    # The noise sampler compiles once per mesh size, the first time it meets a mesh: build
    # every batch of the measured steps once first, so neither way pays for that.
    for k in range(1, rounds * steps + 1):
        multiseed.seeds_batch(train_ex, cfgs, k)
        for c in cfgs:
            seq_batch(c, k)
    loads = [os.getloadavg()[0]]
    for _ in range(rounds):
        for _ in range(steps):
            step += 1
            t0, p0 = time.perf_counter(), time.process_time()
            compute = 0.0
            for i, tr in enumerate(trainers):
                batch = seq_batch(cfgs[i], step)
                c0 = time.perf_counter()
                states[i], m = tr.train_step(states[i], batch)
                jax.block_until_ready(m)
                compute += time.perf_counter() - c0
            out["sequential"].append(time.perf_counter() - t0)
            out["sequential_cpu"].append(time.process_time() - p0)
            out["sequential_compute"].append(compute)
            t0, p0 = time.perf_counter(), time.process_time()
            b = multiseed.seeds_batch(train_ex, cfgs, step)
            rngs = multiseed.step_rngs(cfgs, step)
            c0 = time.perf_counter()
            stacked, m = vstep(stacked, b.noisy, b.clean, b.graph, rngs)
            jax.block_until_ready(m)
            out["vmapped_compute"].append(time.perf_counter() - c0)
            out["vmapped"].append(time.perf_counter() - t0)
            out["vmapped_cpu"].append(time.process_time() - p0)
        loads.append(os.getloadavg()[0])
    med = {k: float(np.median(v)) for k, v in out.items()}
    return {
        "preset": preset,
        "seeds": n_seeds,
        "steps_per_round": steps,
        "rounds": rounds,
        "median_s": med,
        "speedup": med["sequential"] / med["vmapped"],
        "speedup_compute": med["sequential_compute"] / med["vmapped_compute"],
        "cpu_ratio": med["sequential_cpu"] / med["vmapped_cpu"],
        "load_average_1min": loads,
        "host": runner.host_info(),
        "base": {
            "width": base.model.width,
            "batch_size": base.train.batch_size,
            "encoding": base.model.encoding,
            "head": base.model.head,
        },
    }


def report(r: dict, command: str) -> str:
    """The markdown report of `measure`'s result."""
    m = r["median_s"]
    n = r["seeds"]
    h = r["host"]
    loads = ", ".join(f"{x:.1f}" for x in r["load_average_1min"])
    return (
        f"# Seeds side by side: vmapped vs sequential (preset `{r['preset']}`)\n\n"
        f"Generated by `{command}`.\n\n"
        f"Base config of the preset (width {r['base']['width']}, batch "
        f"{r['base']['batch_size']}, encoding `{r['base']['encoding']}`, head "
        f"`{r['base']['head']}`), {n} seeds, {r['rounds']} rounds of "
        f"{r['steps_per_round']} steps, both ways interleaved in one process; medians of "
        f"the per-step times (one step = one step of every seed), compile steps left out.\n\n"
        "| | sequential (one `Trainer.train_step` per seed) | vmapped (`multiseed.seeds_step`) "
        "| speed-up |\n|---|---:|---:|---:|\n"
        f"| step incl. host batch building | {m['sequential'] * 1e3:.1f} ms | "
        f"{m['vmapped'] * 1e3:.1f} ms | {r['speedup']:.2f}× |\n"
        f"| device step only | {m['sequential_compute'] * 1e3:.1f} ms | "
        f"{m['vmapped_compute'] * 1e3:.1f} ms | {r['speedup_compute']:.2f}× |\n"
        f"| process CPU time per step (all threads) | {m['sequential_cpu'] * 1e3:.1f} ms | "
        f"{m['vmapped_cpu'] * 1e3:.1f} ms | {r['cpu_ratio']:.2f}× |\n\n"
        f"Host: {h['processor']}, {h['cpu_count']} CPUs, jax {h['jax']} ({h['backend']}); "
        f"1-minute load average before and after each round: {loads} (the machine was "
        "shared with other jobs).\n"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--data-dir", type=Path, help="default data/ablate-<dataset>")
    parser.add_argument("--out", type=Path, default=REPO / "experiments/results/seed_speedup")
    args = parser.parse_args(argv)
    from experiments import studies as st

    data = args.data_dir or REPO / "data" / f"ablate-{st.get_preset(args.preset).dataset_name}"
    r = measure(args.preset, args.seeds, args.steps, args.rounds, data)
    command = (
        f"python -m experiments.seed_speedup --preset {args.preset} --seeds {args.seeds} "
        f"--steps {args.steps} --rounds {args.rounds}"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(r | {"command": command}, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(report(r, command))
    print(report(r, command))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
