"""The cost of a fresh output buffer on CPU: JAX with and without glibc's huge pages.

A memory-bound op (`x * 2 + 1`, float32) timed four ways, each in a child process with
`GLIBC_TUNABLES` unset and with `glibc.malloc.hugetlb=1` (the tunable is read at
process start):

* `jax fresh`: `jit(x * 2 + 1)`, a new output buffer every call;
* `jax donated`: the same op with the input donated, so the output reuses its buffer;
* `numpy fresh`: `x * 2 + 1` in NumPy (NumPy asks for huge pages on its own buffers);
* `numpy out=`: into a preallocated array.

The gap between `jax fresh` and `jax donated` is the page-fault cost of a new buffer;
on this kind of machine it dominates memory-bound JAX ops at a few hundred thousand
rows, which is why `make bench` runs JAX with the tunable.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    Timing,
    environment,
    format_ms,
    markdown_table,
    time_interleaved,
    write_report,
)

SIZES = (100_000, 300_000, 1_000_000)
WIDTH = 64
CASES = ("jax fresh", "jax donated", "numpy fresh", "numpy out=")
SETTINGS = {"default glibc": None, "glibc.malloc.hugetlb=1": "glibc.malloc.hugetlb=1"}


def measure(sizes, repeat: int) -> dict[str, dict[str, list[float]]]:
    """Times the four cases at every size in this process: `{size: {case: times}}`."""
    import jax
    import jax.numpy as jnp

    fresh = jax.jit(lambda x: x * 2.0 + 1.0)
    # Donated: keeps values bounded over many calls; the buffer is reused in place.
    donated = jax.jit(lambda x: x * 0.5 + 1.0, donate_argnums=0)
    out = {}
    for n in sizes:
        x_np = np.random.default_rng(0).standard_normal((n, WIDTH), dtype=np.float32)
        x = jnp.asarray(x_np)
        state = {"y": jnp.asarray(x_np)}
        buffer = np.empty_like(x_np)

        def run_donated(state=state):
            state["y"] = donated(state["y"])
            return state["y"]

        def run_numpy_out(x_np=x_np, buffer=buffer):
            np.multiply(x_np, 2.0, out=buffer)
            buffer += 1.0
            return buffer

        cases = {
            "jax fresh": lambda x=x: fresh(x),
            "jax donated": run_donated,
            "numpy fresh": lambda x_np=x_np: x_np * 2.0 + 1.0,
            "numpy out=": run_numpy_out,
        }
        timings = time_interleaved(cases, repeat=repeat, warmup=2)
        out[str(n)] = {name: list(t.times) for name, t in timings.items()}
    return out


def run_child(tunable: str | None, sizes, repeat: int) -> dict:
    env = dict(os.environ)
    env.pop("GLIBC_TUNABLES", None)
    if tunable:
        env["GLIBC_TUNABLES"] = tunable
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--repeat", str(repeat)]
    cmd += ["--sizes", *map(str, sizes)]
    result = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    p.add_argument("--repeat", type=int, default=15)
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="allocation")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.sizes, args.repeat)))
        return 0
    env = environment()
    env["GLIBC_TUNABLES"] = "per row (child processes)"
    rows = []
    for label, tunable in SETTINGS.items():
        results = run_child(tunable, args.sizes, args.repeat)
        for n in args.sizes:
            t = {name: Timing(tuple(v)) for name, v in results[str(n)].items()}
            line = [f"{n:,} × {WIDTH}", f"{n * WIDTH * 4 / 2**20:.0f}", label]
            line += [f"{format_ms(t[c].median)} ({format_ms(t[c].iqr)})" for c in CASES]
            line += [f"{t['jax fresh'].median / t['numpy fresh'].median:.2f}×"]
            rows.append(line)
    headers = ["array", "MiB", "allocator"] + [f"{c} ms (IQR)" for c in CASES]
    text = markdown_table(headers + ["jax fresh / numpy fresh"], rows)
    print(text)
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    write_report(
        args.out / f"{args.name}.md",
        title="Fresh output buffers: JAX vs NumPy, with and without huge pages",
        intro="\n\n".join(__doc__.split("\n\n")[1:]),
        env=env,
        sections=[("Results (`x * 2 + 1`, float32, medians)", text)],
    )
    print(f"wrote {args.out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
