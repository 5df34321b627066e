"""What one model of `make ablate-smoke` costs to compile, and which XLA flags change it.

    python -m experiments.compile_cost --repeat 3

`make ablate-smoke` (the `test` ablation preset, 2 steps per run) spends nearly all its
time compiling: one init, one shared train step (`train.shared_train_step`) and one
predictor per distinct model of the sweep. This measures those three programs for the
preset's structure row FGT-8 (every loss term on, as appendix D has it) in fresh
processes (no persistent cache), with the preset's XLA flags and with each candidate
flag added, `--repeat` times each, interleaved so that a change of machine load hits
every setting alike; the report (`--out`, default
`experiments/results/compile_cost.md` and `.json`) gives medians of XLA's compile
seconds (`/jax/core/compile/backend_compile_duration`) and of the wall time from
tracing to a finished first call.
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

REPO = Path(__file__).resolve().parents[1]
# Flags of jaxlib 0.10.2's CPU backend that could shorten compilation (others named in
# its binary are rejected as unknown, e.g. xla_cpu_disable_slp_vectorizer).
CANDIDATE_FLAGS = (
    "",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_use_xnnpack=false",
    "--xla_cpu_use_thunk_runtime=false",
    "--xla_cpu_parallel_codegen_split_count=1",
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
)


def child() -> dict:
    """Builds, compiles and runs the three programs once; seconds per program."""
    import jax
    import jax.numpy as jnp

    compiled: dict[str, float] = {}

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            name = str(kwargs.get("fun_name"))
            compiled[name] = compiled.get(name, 0.0) + duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    from dmd_jax.config import preset
    from dmd_jax.pipeline import make_examples
    from dmd_jax.train import Trainer, merge_params
    from experiments import multiseed
    from experiments.ablations import ablation_config
    from experiments.studies import get_preset

    cfg = ablation_config(preset("test").with_edits(get_preset("test").edits), "structure", "FGT-8")
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    rng = np.random.default_rng(0)
    examples = make_examples([(v + 0.01 * rng.standard_normal(v.shape), f) for _ in range(2)])
    out = {}
    t0 = time.perf_counter()
    first = multiseed.seeds_batch(examples, [cfg], 0)
    trainer = Trainer(cfg)
    state = trainer.init(jax.tree.map(lambda x: x[0], first))
    jax.block_until_ready(state)
    out["init wall"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    batch = multiseed.seeds_batch(examples, [cfg], 1)
    step = multiseed.seeds_step(cfg, "all")
    _, metrics = step(
        multiseed.stack_trees([state]),
        batch.noisy,
        batch.clean,
        batch.graph,
        multiseed.step_rngs([cfg], 1),
    )
    jax.block_until_ready(metrics)
    out["train step wall"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    group = jax.tree.map(lambda x: x[0][0], batch)
    pred = trainer._eval_fn(
        merge_params(state.params), jnp.asarray(group.noisy), jax.tree.map(jnp.asarray, group.graph)
    )
    jax.block_until_ready(pred)
    out["predictor wall"] = time.perf_counter() - t0
    out["init XLA"] = sum(s for n, s in compiled.items() if "lambda" in n)
    out["train step XLA"] = sum(s for n, s in compiled.items() if "step" in n)
    out["predictor XLA"] = sum(s for n, s in compiled.items() if "predict" in n)
    return out


def measure(flags: list[str], repeat: int, base_flags: str) -> dict[str, list[dict]]:
    """`{flag: [child result per repeat]}`, each run in a fresh process."""
    results: dict[str, list[dict]] = {f: [] for f in flags}
    for _ in range(repeat):
        for flag in flags:
            env = dict(os.environ, XLA_FLAGS=f"{base_flags} {flag}".strip())
            env.pop("JAX_COMPILATION_CACHE_DIR", None)
            done = subprocess.run(
                [sys.executable, "-m", "experiments.compile_cost", "--child"],
                cwd=REPO,
                env=env,
                capture_output=True,
                text=True,
                check=False,
            )
            if done.returncode:
                raise RuntimeError(f"{flag or 'preset flags'}: {done.stderr.strip()[-400:]}")
            results[flag].append(json.loads(done.stdout.strip().splitlines()[-1]))
    return results


def _span(values):
    return min(values), max(values)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--flags",
        action="append",
        help="XLA flags to add (repeatable; write --flags='--xla_...=v', '' for none); "
        "default: the preset's alone and each of CANDIDATE_FLAGS",
    )
    parser.add_argument("--out", type=Path, default=REPO / "experiments/results/compile_cost.md")
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child()))
        return 0
    from benchmarks.common import environment, markdown_table, provenance
    from experiments import runner
    from experiments.studies import get_preset

    base = runner.apply_xla_opt_level(get_preset("test").xla_opt_level)
    flags = args.flags if args.flags is not None else list(CANDIDATE_FLAGS)
    results = measure(flags, args.repeat, base)
    columns = list(next(iter(results.values()))[0])
    medians = {
        flag: {c: float(np.median([r[c] for r in runs])) for c in columns}
        for flag, runs in results.items()
    }
    ref = medians[flags[0]]
    rows = [
        [
            f"`{flag}`" if flag else f"preset (`{base}`)",
            *(f"{m[c]:.2f}" for c in columns),
            f"{m['train step XLA'] / ref['train step XLA']:.2f}",
            "{:.2f}–{:.2f}".format(*_span([r["train step XLA"] for r in results[flag]])),
        ]
        for flag, m in medians.items()
    ]
    table = markdown_table(
        ["XLA flags added", *columns, "train step XLA / preset", "train step XLA, range"], rows
    )
    text = "\n".join(
        [
            "# Compile cost of one ablate-smoke model",
            "",
            provenance(None),
            "",
            __doc__.split("\n\n")[2].strip(),
            "",
            "```bash",
            f"python -m experiments.compile_cost --repeat {args.repeat}",
            "```",
            "",
            f"Seconds, medians of {args.repeat} fresh processes per setting.",
            "",
            table,
            "",
            "Environment: " + ", ".join(f"{k} {v}" for k, v in environment().items()),
            "",
        ]
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
