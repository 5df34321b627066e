"""Steps per CPU-second of the long run's recipe, with and without the candidate pool.

Issue 62 item 3 ("half the cost per step"). The long run (`scripts/train_long.sh`) trains
preset `small` at 120 filter passes through the converged vertex solve; every step
computes the `"local"` encoding's parameter-free candidate fields (nine bilateral fields,
two Taubin ones) of its two noisy meshes. With `train.candidate_pool` they are computed
once per cached noisy draw, outside the step (`pipeline.CandidatePool`), each draw serving
`train.candidate_uses` visits of its mesh, and a background thread builds the batches
(`pipeline.Prefetcher`). In one process, on one training set, round-robin:

* `today`: the run as it is: `pipeline.training_batch` on the host (noise, rotation,
  padding to the step's vertex bucket), then `Trainer.train_step`, which encodes the
  meshes (one program per bucket; every bucket a timed step meets is compiled first).
* `pool, uses U`: `train.train`'s loop with `candidate_pool=1, candidate_uses=U`: the
  prefetcher's batches, each padded to the smallest of four size classes that holds it
  (`pad_to="classes"`, the default with a pool: four programs, compiled before the
  first step), ELL tables of fixed width, `Trainer.train_step` with the cached inputs.
  Each timed window is whole cycles of the pool (`U` epochs), so the draws it
  re-encodes are the steady state's share.

A case's figure is steps / CPU seconds of the process (`time.process_time`, every thread,
the pool's thread included) over its windows, so other load on the machine matters
less than for wall time; wall-clock steps/s are given beside.

Run `python benchmarks/bench_train_long.py --help`; `make bench-train` runs the default.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    environment,
    markdown_table,
    write_csv,
    write_report,
    write_text,
)

# The long run's settings: preset `small`, then scripts/recipe_common.sh's LAST_FINETUNE
# and scripts/train_long.sh's --set edits (the data and schedule lengths aside).
LONG_RUN_EDITS = {
    "train": {"lr": 2e-4, "warmup_steps": 50, "seed": 11, "steps": 100_000},
    "loss": {"normal": 3.0, "face_normal": 3.0},
    "noise": {
        "p_normal": 0.8,
        "p_clean": 0.1,
        "p_scanner": 0.25,
        "edge_levels": [0.05, 0.1, 0.1, 0.15, 0.2, 0.2, 0.25, 0.3, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0],
    },
    "model": {"filter_iterations": 120, "vertex_update": "solve", "vertex_tangent_weight": 0.1},
}
INIT_FROM = REPO / "dmd_jax" / "weights" / "dmd_small.msgpack"


def training_meshes(dataset: Path, n_mesh: int, stress_copies: int):
    """`n_mesh` training meshes of the procedural dataset, evenly spread over its sizes
    (its largest included, which sets the padded size), and the stress family."""
    from dmd_jax.data.store import load_dataset
    from dmd_jax.data.training_sets import stress_meshes

    records = load_dataset(dataset).split("train")
    meshes = [r.load() for r in records]
    order = np.argsort([len(m[0]) for m in meshes])
    pick = np.unique(np.linspace(0, len(order) - 1, n_mesh).round().astype(int))
    return [meshes[order[i]] for i in pick] + list(stress_meshes(stress_copies))


class Today:
    """The run's step as it is: host batch (bucket padding), then the step."""

    def __init__(self, cfg, examples, params, steps):
        import jax

        from dmd_jax import train

        self.cfg, self.examples, self.steps = cfg, examples, list(steps)
        self.trainer = train.Trainer(cfg)
        self.state = self._start(params)
        self.position = 0
        # Compile every bucket the timed steps use, untimed.
        seen = set()
        for s in self.steps:
            b = self.batch(s)
            if b.noisy.shape not in seen:
                seen.add(b.noisy.shape)
                self.state, out = self.trainer.train_step(self.state, b)
                jax.block_until_ready(out)
        self.compiles = self.trainer.compiles
        self.buckets = sorted(int(s[-2]) for s in seen)

    def _start(self, params):
        from dmd_jax import parallel, train

        state = self.trainer.init(self.batch(0))
        return parallel.replicate(
            self.trainer.mesh, state._replace(params=train.split_params(params))
        )

    def batch(self, step):
        from dmd_jax import pipeline

        t = self.cfg.train
        return pipeline.training_batch(
            self.examples,
            step,
            batch_size=t.batch_size,
            seed=t.seed,
            noise=self.cfg.noise,
            rotate=t.rotate,
            encoding=self.cfg.model.encoding,
        )

    def window(self, n_steps):
        import jax

        out = None
        for _ in range(n_steps):
            s = self.steps[self.position % len(self.steps)]
            self.position += 1
            self.state, out = self.trainer.train_step(self.state, self.batch(s))
        jax.block_until_ready(out)


class Pooled:
    """`train.train`'s loop with the candidate pool: prefetched cached batches."""

    def __init__(self, cfg, examples, params, uses):
        import jax

        from dmd_jax import parallel, pipeline, train

        cfg = cfg.with_edits({"train": {"candidate_pool": 1, "candidate_uses": uses}})
        t = cfg.train
        self.cfg, self.uses = cfg, uses
        self.trainer = train.Trainer(cfg)
        self.pool = pipeline.CandidatePool.from_config(examples, cfg)
        self.examples = examples
        # The run's padding with a pool (`train_and_evaluate`'s "auto"): size classes.
        self.classes = pipeline.size_classes(examples, t.batch_size, train.PAD_CLASSES)
        # Whole cycles of the pool: `uses` epochs re-encode every draw once.
        self.cycle = uses * -(-len(examples) // t.batch_size)
        state = self.trainer.init(self.batch(0))
        self.state = parallel.replicate(
            self.trainer.mesh, state._replace(params=train.split_params(params))
        )
        for c in self.classes:  # every class compiled first, as `train.train` does
            warm = next(s for s in range(10_000) if self.size(s).n_vertex <= c.n_vertex)
            jax.block_until_ready(self.trainer.train_step(self.state, self.pool.batch(warm, c)))
        self.compiles = self.trainer.compiles
        self.padded = [c.n_vertex for c in self.classes]
        # Fill the pool (generation 0) untimed: the windows then start in the steady state.
        self.next = self.cycle
        for s in range(self.next):
            self.pool.batch(s, self.size(s))

    def size(self, step):
        from dmd_jax import pipeline

        t = self.cfg.train
        return pipeline.step_sizes(
            self.examples, step, self.classes, batch_size=t.batch_size, seed=t.seed
        )

    def batch(self, step):
        return self.pool.batch(step, self.size(step))

    def window(self, n_steps):
        import jax

        from dmd_jax import pipeline

        source = pipeline.Prefetcher(self.batch, self.next)
        out = None
        try:
            for s in range(self.next, self.next + n_steps):
                self.state, out = self.trainer.train_step(self.state, source.get(s))
            jax.block_until_ready(out)
        finally:
            source.close()
        self.next += n_steps


def _cpu(fn, repeat: int = 3) -> float:
    """Median CPU seconds of the process over `repeat` calls of `fn` (after one warm-up)."""
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeat):
        c0 = time.process_time()
        jax.block_until_ready(fn())
        times.append(time.process_time() - c0)
    return float(np.median(times))


def profile(today: Today, step: int) -> list[tuple[str, float]]:
    """CPU seconds of the parts of today's step on the batch of `step` (its own bucket).

    The full step and its parts, each jitted alone: the encoding (`local_inputs`, the
    candidate fields, forward only: they have no parameters and the step differentiates
    only the parameters, so no backward runs through them), the network forward given
    them, the converged solve forward and forward + backward, the step given the
    encoding (segment sums, then ELL tables), and the host pipeline.
    """
    import jax
    import jax.numpy as jnp

    from dmd_jax import encoding, parallel, pipeline, train
    from dmd_jax import graph as graph_lib
    from dmd_jax.model import DMDNet
    from dmd_jax.vertex_update import solve_vertices_to_normals

    m = today.cfg.model
    batch = today.batch(step)
    group = jax.tree.map(lambda x: jnp.asarray(x[0]), batch)
    model = DMDNet(m)
    params = train.merge_params(parallel.local_copy(today.state.params))
    encode = jax.jit(lambda x, g: encoding.local_inputs(x, g, m))
    local = encode(group.noisy, group.graph)
    forward = jax.jit(lambda p, x, g, loc: model.apply({"params": p}, x, g, local=loc))
    normals = forward(params, group.noisy, group.graph, local)[2]["face_normals"]
    free = jnp.ones(group.noisy.shape[0], group.noisy.dtype)

    def solve(n):
        return solve_vertices_to_normals(
            group.noisy,
            group.graph.faces,
            n,
            free,
            tolerance=m.vertex_tolerance,
            max_iterations=m.vertex_max_iterations,
            normal_weight=m.vertex_normal_weight,
            tangent_weight=m.vertex_tangent_weight,
        )

    solve_fwd = jax.jit(solve)
    solve_grad = jax.jit(jax.grad(lambda n: jnp.sum(solve(n) ** 2)))
    stacked = jax.tree.map(lambda x: x[None], local)
    ell = graph_lib.with_fixed_ell(
        jax.tree.map(lambda x: np.asarray(x[0]), batch.graph),
        pipeline.ell_widths(today.examples),
    )
    with_ell = batch._replace(graph=jax.tree.map(lambda x: np.asarray(x)[None], ell))
    local_ell = jax.tree.map(lambda x: x[None], encode(group.noisy, jax.tree.map(jnp.asarray, ell)))
    state = today.state
    rows = [
        ("whole step (today)", _cpu(lambda: today.trainer.train_step(state, batch)[1])),
        ("encoding: candidate fields, forward", _cpu(lambda: encode(group.noisy, group.graph))),
        (
            "network forward given them (solve included)",
            _cpu(lambda: forward(params, group.noisy, group.graph, local)),
        ),
        ("converged solve, forward", _cpu(lambda: solve_fwd(normals))),
        ("converged solve, forward + backward", _cpu(lambda: solve_grad(normals))),
        (
            "step given the encoding (segment sums)",
            _cpu(lambda: today.trainer.train_step(state, batch._replace(local=stacked))[1]),
        ),
        (
            "step given the encoding (ELL tables)",
            _cpu(lambda: today.trainer.train_step(state, with_ell._replace(local=local_ell))[1]),
        ),
        (
            "encoding with ELL tables, forward",
            _cpu(lambda: encode(group.noisy, jax.tree.map(jnp.asarray, ell))),
        ),
        (
            "host: training_batch (noise, rotation, frames, padding)",
            _cpu(lambda: today.batch(step + 1)),
        ),
    ]
    return rows


def measure(args) -> dict:
    import jax

    from dmd_jax import config, pipeline, train

    cfg = config.preset("small").with_edits(LONG_RUN_EDITS)
    t0 = time.perf_counter()
    meshes = training_meshes(args.data, args.meshes, args.stress)
    examples = pipeline.make_examples(meshes)
    params = train.init_params_from(str(INIT_FROM), cfg)
    print(f"{len(examples)} meshes ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    n_steps = -(-len(examples) // cfg.train.batch_size)
    timed = range(1000 * n_steps, 1000 * n_steps + args.today_steps)
    cases = {"today": Today(cfg, examples, params, timed)}
    print(f"today: buckets {cases['today'].buckets}", file=sys.stderr, flush=True)
    parts = profile(cases["today"], timed[0]) if args.profile else []
    # The profile's programs (the step given the encoding) are not today's.
    cases["today"].programs = cases["today"].compiles
    cases["today"].compiles = cases["today"].trainer.compiles
    print(f"profile: {parts}", file=sys.stderr, flush=True)
    for uses in args.uses:
        cases[f"pool, uses {uses}"] = Pooled(cfg, examples, params, uses)
        print(f"pool uses {uses}: ready", file=sys.stderr, flush=True)
    windows = {
        name: args.today_steps if name == "today" else case.cycle for name, case in cases.items()
    }
    load = os.getloadavg()[0]
    cpu = {name: [] for name in cases}
    wall = {name: [] for name in cases}
    for r in range(args.rounds):
        for name, case in cases.items():
            w0, c0 = time.perf_counter(), time.process_time()
            case.window(windows[name])
            cpu[name].append(time.process_time() - c0)
            wall[name].append(time.perf_counter() - w0)
            print(
                f"round {r}: {name}: {windows[name] / cpu[name][-1]:.3f} steps/CPU-s",
                file=sys.stderr,
                flush=True,
            )
    for name, case in cases.items():
        if case.trainer.compiles != case.compiles:
            raise AssertionError(f"{name}: a timed step compiled")

    rows = []
    for name, case in cases.items():
        steps = windows[name] * args.rounds
        rows.append(
            {
                "case": name,
                "steps": steps,
                "cpu_s": sum(cpu[name]),
                "wall_s": sum(wall[name]),
                "window_cpu_s": cpu[name],
                "window_steps": windows[name],
                "programs": getattr(case, "programs", case.compiles),
                "padded_vertices": case.buckets if name == "today" else case.padded,
                "encoded": getattr(getattr(case, "pool", None), "encoded", None),
            }
        )
    base = rows[0]["steps"] / rows[0]["cpu_s"]
    for row in rows:
        row["steps_per_cpu_s"] = row["steps"] / row["cpu_s"]
        row["speedup"] = row["steps_per_cpu_s"] / base
        row["per_window_speedup"] = [
            row["window_steps"] / c / (rows[0]["window_steps"] / b)
            for c, b in zip(row["window_cpu_s"], rows[0]["window_cpu_s"], strict=True)
        ]
    nv = [len(m[0]) for m in meshes]
    return {
        "rows": rows,
        "profile": parts,
        "profile_vertices": int(cases["today"].batch(timed[0]).noisy.shape[-2]),
        "load": load,
        "meshes": f"{len(nv)} meshes of {min(nv):,}-{max(nv):,} vertices "
        f"({args.meshes} of {args.data}'s training split by size, {args.stress} stress "
        "family copy)",
        "ell_widths": str(cases[list(cases)[-1]].pool.ell_widths) if args.uses else "",
        "devices": str(jax.devices()),
    }


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=REPO / "data" / "gen_v2")
    p.add_argument("--meshes", type=int, default=16, help="procedural training meshes")
    p.add_argument("--stress", type=int, default=1, help="copies of the stress family")
    p.add_argument("--uses", type=int, nargs="*", default=[4], help="candidate_uses cases")
    p.add_argument("--today-steps", type=int, default=8, help="steps per window of today's")
    p.add_argument("--rounds", type=int, default=3, help="windows per case")
    p.add_argument(
        "--no-profile", dest="profile", action="store_false", help="skip the step's profile"
    )
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="train_long_speed")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    env = environment(("jax", "jaxlib", "flax", "optax", "numpy"))
    result = measure(args)
    env["load average (1 min) before timing"] = f"{result['load']:.2f}"
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    rows = result["rows"]
    headers = ["case", "steps/CPU-s", "vs today", "per round vs today", "CPU s/step"]
    headers += ["wall steps/s", "programs", "padded vertices", "draws encoded"]
    body = [
        [r["case"], f"{r['steps_per_cpu_s']:.3f}", f"**{r['speedup']:.2f}x**"]
        + [", ".join(f"{x:.2f}" for x in r["per_window_speedup"])]
        + [f"{r['cpu_s'] / r['steps']:.3f}", f"{r['steps'] / r['wall_s']:.3f}", r["programs"]]
        + [", ".join(f"{n:,}" for n in r["padded_vertices"]), r["encoded"] or "-"]
        for r in rows
    ]
    method = [
        f"- Data: {result['meshes']}; batch 2; the bundled weights (the run's `init_from`).",
        "- `today` times `--today-steps` steps per window (the same steps each round, "
        "every bucket compiled first); a pool case times one whole cycle per window "
        "(`uses` epochs, starting with the pool filled), through a fresh prefetcher.",
        "- CPU seconds: `time.process_time()` of the process (all threads) per window; "
        "`vs today` is the ratio of total steps per CPU second, `per round` each round's.",
        f"- ELL widths of the pool's batches (vertex, face; None: segment sums): "
        f"{result['ell_widths']}.",
        "- No timed step compiled (`Trainer.compiles` before and after the windows).",
    ]
    sections = [
        ("Steps per CPU second", markdown_table(headers, body)),
        ("Method", "\n".join(method)),
    ]
    if result["profile"]:
        whole = result["profile"][0][1]
        table = markdown_table(
            ["part", "CPU ms", "share of today's step"],
            [(name, f"{sec * 1e3:.0f}", f"{sec / whole:.0%}") for name, sec in result["profile"]],
        )
        note = (
            f"Today's step on the batch of its first timed step "
            f"({result['profile_vertices']:,} padded vertices), each part jitted alone, "
            "median CPU time of 3 calls (`profile`). The parts overlap (the forward "
            "includes the solve); the step given the encoding is what remains to pay."
        )
        sections.insert(1, ("Profile of one step", note + "\n\n" + table))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / f"{args.name}.json", json.dumps(result, indent=1))
    write_report(
        out / f"{args.name}.md",
        title="Long-run training steps per CPU second: candidate pool against today's recipe",
        intro="\n\n".join(__doc__.split("\n\n")[1:3]),
        env=env,
        sections=sections,
    )
    write_csv(
        out / f"{args.name}.csv",
        ("case", "steps", "cpu_s", "wall_s", "steps_per_cpu_s", "speedup"),
        [
            (r["case"], r["steps"], r["cpu_s"], r["wall_s"], r["steps_per_cpu_s"], r["speedup"])
            for r in rows
        ],
    )
    print(f"wrote {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
