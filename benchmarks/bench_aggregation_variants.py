"""Formulations of the same GCN aggregation, to pick the fastest one that keeps the design.

Every variant computes `out[i] = sum_j A[i, j] x[j]` from index arrays only (no dense
adjacency), on one triangulated grid, timed round-robin against SciPy CSR:

* `segment_sum sorted`: `dmd_jax.ops.gcn_aggregate` (receivers sorted, flag set);
* `segment_sum unsorted`: the same edges shuffled, `indices_are_sorted=False`;
* `ell chain, autodiff`: padded-neighbour table, one gather per slot summed in a loop
  fusion; backward by autodiff (a scatter-add);
* `ell chain, gather VJP`: the same with the gather-only backward of
  `gcn_aggregate_ell` but no fusion boundary;
* `ell (gcn_aggregate_ell)`: what `dmd_jax.ops` ships (gather VJP + fusion boundary);
* `ell gather-then-sum`: `(x[nbr] * w[..., None]).sum(1)`;
* `ell einsum`: `einsum("nkd,nk->nd", x[nbr], w)`;
* `ell scan over slots`: `lax.scan` over the slots, accumulating `[n, d]`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_aggregation import gcn_edges, grid_faces  # noqa: E402
from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    environment,
    format_ms,
    markdown_table,
    time_interleaved,
    write_report,
)
from dmd_jax import ops  # noqa: E402
from dmd_jax.graph import ell_layout  # noqa: E402


def _segment_sum_unsorted(x, s, r, w):
    messages = x[s] * w[:, None]
    return jax.ops.segment_sum(messages, r, num_segments=x.shape[0])


@jax.custom_vjp
def _ell_chain_vjp(x, nbr, w, rev):
    return ops._ell_sum(x, nbr, w)


def _ell_chain_vjp_fwd(x, nbr, w, rev):
    return ops._ell_sum(x, nbr, w), (nbr, w, rev)


def _ell_chain_vjp_bwd(res, g):
    nbr, w, rev = res
    return ops._ell_sum(g, nbr, w[nbr, rev]), None, None, None


_ell_chain_vjp.defvjp(_ell_chain_vjp_fwd, _ell_chain_vjp_bwd)


def _ell_gather_sum(x, nbr, w, rev):
    return (x[nbr] * w[..., None]).sum(axis=1)


def _ell_einsum(x, nbr, w, rev):
    return jnp.einsum("nkd,nk->nd", x[nbr], w)


def _ell_scan(x, nbr, w, rev):
    def step(acc, slot):
        idx, weight = slot
        return acc + x[idx] * weight[:, None], None

    out, _ = jax.lax.scan(step, jnp.zeros_like(x), (nbr.T, w.T))
    return out


VARIANTS = {
    "segment_sum sorted": ("edges", ops.gcn_aggregate),
    "segment_sum unsorted": ("shuffled", _segment_sum_unsorted),
    "ell chain, autodiff": ("ell", lambda x, nbr, w, rev: ops._ell_sum(x, nbr, w)),
    "ell chain, gather VJP": ("ell", _ell_chain_vjp),
    "ell (gcn_aggregate_ell)": ("ell", ops.gcn_aggregate_ell),
    "ell gather-then-sum": ("ell", _ell_gather_sum),
    "ell einsum": ("ell", _ell_einsum),
    "ell scan over slots": ("ell", _ell_scan),
}


def run(n_target: int, width: int, *, repeat: int = 5, seed: int = 0):
    """Returns `(n_node, [(variant, fwd Timing, fwd+bwd Timing)])`, SciPy last."""
    faces, n = grid_faces(n_target)
    s, r, w = gcn_edges(faces, n)
    rng = np.random.default_rng(seed)
    x_np = rng.standard_normal((n, width), dtype=np.float32)
    perm = rng.permutation(s.size)
    operands = {
        "edges": (s, r, w),
        "shuffled": (s[perm], r[perm], w[perm]),
        "ell": tuple(ell_layout(s, r, w, n)),
    }
    operands = {k: tuple(jnp.asarray(a) for a in v) for k, v in operands.items()}
    x = jnp.asarray(x_np)
    csr = sp.csr_matrix((w, (r, s)), shape=(n, n))
    csr_t = csr.T.tocsr()
    expected = {"fwd": csr @ x_np, "fwd+bwd": csr_t @ (2.0 * (csr @ x_np))}
    cases = {}
    for mode in ("fwd", "fwd+bwd"):
        for name, (kind, fn) in VARIANTS.items():
            if mode == "fwd":
                jitted = jax.jit(fn)
            else:
                jitted = jax.jit(jax.grad(lambda x, *a, fn=fn: jnp.sum(fn(x, *a) ** 2)))
            cases[name, mode] = lambda f=jitted, a=operands[kind]: f(x, *a)
        if mode == "fwd":
            cases["scipy_csr", mode] = lambda: csr @ x_np
        else:
            cases["scipy_csr", mode] = lambda: csr_t @ (2.0 * (csr @ x_np))
    for (name, mode), fn in cases.items():
        got = np.asarray(fn())
        err = np.abs(got - expected[mode]).max() / np.abs(expected[mode]).max()
        if not err < 1e-4:
            raise AssertionError(f"{name} {mode}: relative error {err:.2e} against SciPy")
    timings = time_interleaved(cases, repeat=repeat, warmup=1)
    names = [*VARIANTS, "scipy_csr"]
    return n, [(name, timings[name, "fwd"], timings[name, "fwd+bwd"]) for name in names]


def table(n: int, width: int, results) -> str:
    ref_f, ref_b = results[-1][1].median, results[-1][2].median
    rows = [
        (
            f"{n:,}",
            width,
            name,
            f"{format_ms(f.median)} ({format_ms(f.iqr)})",
            f"{format_ms(b.median)} ({format_ms(b.iqr)})",
            f"{f.median / ref_f:.2f}×",
            f"{b.median / ref_b:.2f}×",
        )
        for name, f, b in results
    ]
    headers = ["nodes", "width", "variant", "fwd ms (IQR)", "fwd+bwd ms (IQR)"]
    return markdown_table(headers + ["fwd / scipy", "fwd+bwd / scipy"], rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[100_000])
    p.add_argument("--widths", type=int, nargs="+", default=[64])
    p.add_argument("--repeat", type=int, default=9, help="timed rounds")
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="aggregation_variants")
    args = p.parse_args(argv)
    env = environment()
    sections = []
    for width in args.widths:
        for n_target in args.sizes:
            n, results = run(n_target, width, repeat=args.repeat)
            text = table(n, width, results)
            print(text, flush=True)
            sections.append((f"{n:,} nodes, width {width}", text))
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    write_report(
        args.out / f"{args.name}.md",
        title="GCN aggregation: formulations compared",
        intro="\n\n".join(__doc__.split("\n\n")[1:]),
        env=env,
        sections=sections,
    )
    print(f"wrote {args.out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
