"""What each network pass of `denoise` costs, beside BNF, in one process.

The default call runs the passes its policy chooses (one, on the Gaussian 0.2-edge mesh
here); more passes (`iterations=`, or the learned smoothing controller) each run the
network again on the last pass's output, with the Jacobi vertex update or the converged
solve. Rows: the call with 1, 2, 4 and 8 passes under each update, `bnf` and the default
call, interleaved rounds after one warm-up call each (so every program is compiled
before timing); medians. The cost of a pass is the slope of a least-squares line through
the passes' medians.

`--filter-iterations 90 60` adds the default call with the bundled network's bilateral
pre-filters run that many passes instead of its 120 (another function of the mesh than the
one trained: what a network with cheaper pre-filters would cost, issue 64).

    python benchmarks/bench_pass_cost.py --faces 100000 --repeat 5
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    environment,
    markdown_table,
    noisy_grid,
    write_report,
)

PASSES = (1, 2, 4, 8)
UPDATES = ("jacobi", "solve")


def _label(update: str, passes: int) -> str:
    return f"{update}, {passes} pass" + ("es" if passes > 1 else "")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--faces", type=int, default=100_000, help="faces of the noisy grid")
    p.add_argument("--repeat", type=int, default=5, help="interleaved rounds")
    p.add_argument("--name", default="pass_cost", help="report name under results/")
    p.add_argument(
        "--filter-iterations",
        type=int,
        nargs="*",
        default=[],
        help="also the default call with this many pre-filter passes (each)",
    )
    args = p.parse_args(argv)

    import dmd_jax
    from dmd_jax.baselines import bnf
    from dmd_jax.checkpoints import load_pretrained

    v, f = noisy_grid(args.faces)
    bundle = load_pretrained()
    bundles = {u: bundle.with_vertex_update(u) for u in ("jacobi", "solve")}
    cases = {"bnf": lambda: bnf(v, f), "denoise (default)": lambda: dmd_jax.denoise(v, f, bundle)}
    for update in UPDATES:
        for k in PASSES:
            cases[_label(update, k)] = lambda b=bundles[update], k=k: dmd_jax.denoise(
                v, f, b, iterations=k, presmooth=0
            )
    for n in args.filter_iterations:
        cheaper = bundle._replace(
            config=bundle.config.replace(model=bundle.config.model.replace(filter_iterations=n))
        )
        cases[f"denoise (default), {n} pre-filter passes"] = lambda b=cheaper: dmd_jax.denoise(
            v, f, b
        )
    _, info = dmd_jax.denoise(v, f, bundle, return_info=True)
    times: dict[str, list[float]] = {name: [] for name in cases}
    for fn in cases.values():
        fn()  # compile, and the first call's one-off costs
    for _ in range(args.repeat):
        for name, fn in cases.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    med = {name: float(np.median(t)) * 1e3 for name, t in times.items()}
    base = med["bnf"]
    rows = [
        [
            name,
            f"{med[name]:.0f}",
            f"{min(t) * 1e3:.0f} - {max(t) * 1e3:.0f}",
            f"{med[name] / base:.2f}",
        ]
        for name, t in times.items()
    ]
    slope_rows = []
    for update in UPDATES:
        y = [med[_label(update, k)] for k in PASSES]
        slope, intercept = np.polyfit(PASSES, y, 1)
        slope_rows.append([update, f"{slope:.0f}", f"{intercept:.0f}", f"{slope / base:.2f}"])
    env = environment()
    env["mesh"] = f"common.noisy_grid({args.faces}): {len(v):,} vertices, {len(f):,} faces"
    env["default call"] = f"{info.passes} pass(es), {info.presmooth_steps} Laplacian steps"
    env["pre-filter passes"] = str(bundle.config.model.filter_iterations)
    sections = [
        (
            "Times, ms",
            markdown_table(["case", "median", "range", "/ bnf"], rows),
        ),
        (
            "Per pass",
            markdown_table(
                ["vertex update", "ms per pass", "ms besides the passes", "a pass / bnf"],
                slope_rows,
            )
            + "\n\nLeast-squares line through the 1, 2, 4, 8-pass medians.",
        ),
    ]
    write_report(
        RESULTS_DIR / f"{args.name}.md",
        title="What a network pass costs",
        env=env,
        sections=sections,
        intro=__doc__.split("\n\n")[0],
    )
    print((RESULTS_DIR / f"{args.name}.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
