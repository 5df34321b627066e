"""GCN aggregation `D̂^-1/2 (A + I) D̂^-1/2 X` on mesh graphs: JAX formulations vs SciPy.

Methods, all float32, all on the same graph (a triangulated grid: the primal graph of a
real mesh, interior valence 6, so 7 entries per row with the self loop):

* `segment_sum`: `dmd_jax.ops.gcn_aggregate` (gather + sorted `segment_sum`);
* `ell`: `dmd_jax.ops.gcn_aggregate_ell` (padded-neighbour gather-sum, gather-only VJP);
* `bcoo`, `bcsr`: `jax.experimental.sparse` matrix @ dense;
* `scipy_csr`: `scipy.sparse.csr_matrix @ ndarray` (backward: the transpose, prebuilt as
  CSR, times `2 out`).

"fwd" times `out = A X`; "fwd+bwd" times `grad(sum(out²))` w.r.t. X (SciPy:
`Aᵀ (2 A X)`). Index arrays and matrices are jit arguments, never closed over (closing
over them makes XLA constant-fold for seconds). Every JAX result is checked against
SciPy before timing. Ratios are against `scipy_csr` in the same process, with all
cases of one size timed round-robin.

Run `python benchmarks/bench_aggregation.py --help`; `make bench` runs the default set.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax.experimental import sparse as jsparse

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    Timing,
    environment,
    format_timing,
    gcn_edges,
    grid_faces,
    markdown_table,
    peak_rss_gib,
    plot_loglog,
    time_interleaved,
    write_csv,
    write_report,
)
from dmd_jax import ops  # noqa: E402
from dmd_jax.graph import ell_layout  # noqa: E402

METHODS = ("segment_sum", "ell", "bcoo", "bcsr", "scipy_csr")
MODES = ("fwd", "fwd+bwd")
SIZES = (10_000, 30_000, 100_000, 300_000, 1_000_000)
WIDTHS = (64, 512)
# 1M nodes × 512 floats is 2 GB per array and the segment-sum / BCOO message buffers
# are 14 GB (7M edges × 512): more than the machine can hold with other users on it.
DEFAULT_SKIP = (
    "1000000x512",
    # Already 1.2-6x slower than SciPy at 100k x 512; at 300k they would add about four
    # minutes and 8 GiB of peak memory to the run.
    "300000x512:segment_sum",
    "300000x512:bcoo",
    "300000x512:bcsr",
)
MESHES = ("armadillo.obj", "truck.obj")


# --------------------------------------------------------------------------------------
# Graphs
# --------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------
# The methods, jitted once at module level (shapes decide recompilation)
# --------------------------------------------------------------------------------------


def _sum_sq_grad(fn):
    return jax.jit(jax.grad(lambda x, *args: jnp.sum(fn(x, *args) ** 2)))


def _sparse_matmul(x, matrix):
    return matrix @ x


_JAX_FNS = {
    "segment_sum": (jax.jit(ops.gcn_aggregate), _sum_sq_grad(ops.gcn_aggregate)),
    "ell": (jax.jit(ops.gcn_aggregate_ell), _sum_sq_grad(ops.gcn_aggregate_ell)),
    "bcoo": (jax.jit(_sparse_matmul), _sum_sq_grad(_sparse_matmul)),
    "bcsr": (jax.jit(_sparse_matmul), _sum_sq_grad(_sparse_matmul)),
}


@dataclass
class Problem:
    """One graph and one feature matrix, in every method's layout."""

    label: str
    n_node: int
    n_edge: int
    width: int
    max_degree: int
    x_np: np.ndarray
    csr: sp.csr_matrix
    csr_t: sp.csr_matrix
    args: dict[str, tuple]

    def reference(self, mode: str) -> np.ndarray:
        out = self.csr @ self.x_np
        return out if mode == "fwd" else self.csr_t @ (2.0 * out)


def make_problem(senders, receivers, weight, n_node: int, width: int, *, label="", seed=0):
    """Builds every method's operands for the graph `(senders, receivers, weight)`.

    Args:
      senders, receivers, weight: `[n_edge]` edges of `A + I` both ways, weights
        `1/sqrt(d_s d_r)` (as in `MeshGraph`).
      n_node: number of nodes.
      width: feature width `d`; features are standard normal float32.
      label: the graph's name in the report.
      seed: seed of the features.
    """
    s, r, w = np.asarray(senders), np.asarray(receivers), np.asarray(weight, np.float32)
    x_np = np.random.default_rng(seed).standard_normal((n_node, width), dtype=np.float32)
    csr = sp.csr_matrix((w, (r, s)), shape=(n_node, n_node))
    csr.sort_indices()
    layout = ell_layout(s, r, w, n_node)
    x = jnp.asarray(x_np)
    sj, rj, wj = jnp.asarray(s), jnp.asarray(r), jnp.asarray(w)
    bcoo = jsparse.BCOO(
        (wj, jnp.stack([rj, sj], axis=1)),
        shape=(n_node, n_node),
        indices_sorted=True,
        unique_indices=True,
    )
    args = {
        "segment_sum": (x, sj, rj, wj),
        "ell": (x, *(jnp.asarray(a) for a in layout)),
        "bcoo": (x, bcoo),
        "bcsr": (x, jsparse.BCSR.from_bcoo(bcoo)),
    }
    return Problem(
        label=label,
        n_node=n_node,
        n_edge=int(s.size),
        width=width,
        max_degree=int(layout.neighbours.shape[1]),
        x_np=x_np,
        csr=csr,
        csr_t=csr.T.tocsr(),
        args=args,
    )


def grid_problem(n_target: int, width: int, *, seed: int = 0) -> Problem:
    """`make_problem` on the primal graph of `grid_faces(n_target)`."""
    faces, n_vertex = grid_faces(n_target)
    return make_problem(*gcn_edges(faces, n_vertex), n_vertex, width, label="grid", seed=seed)


def make_cases(problem: Problem, methods=METHODS, modes=MODES) -> dict[tuple[str, str], object]:
    """`(method, mode) -> zero-argument callable`, in round-robin order."""
    cases = {}
    for mode in modes:
        for method in methods:
            if method == "scipy_csr":
                if mode == "fwd":
                    cases[method, mode] = lambda p=problem: p.csr @ p.x_np
                else:
                    cases[method, mode] = lambda p=problem: p.csr_t @ (2.0 * (p.csr @ p.x_np))
            else:
                fn = _JAX_FNS[method][MODES.index(mode)]
                cases[method, mode] = lambda fn=fn, a=problem.args[method]: fn(*a)
    return cases


def check_cases(problem: Problem, cases) -> dict[tuple[str, str], float]:
    """Runs every case once, compares with SciPy, returns the relative max error."""
    errors = {}
    for (method, mode), fn in cases.items():
        expected = problem.reference(mode)
        got = np.asarray(fn())
        err = float(np.abs(got - expected).max() / np.abs(expected).max())
        if not err < 1e-4:
            raise AssertionError(f"{method} {mode}: relative error {err:.2e} against SciPy")
        errors[method, mode] = err
    return errors


# --------------------------------------------------------------------------------------
# Runs and reports
# --------------------------------------------------------------------------------------


@dataclass
class Row:
    graph: str
    n_node: int
    n_edge: int
    max_degree: int
    width: int
    method: str
    fwd: Timing | None
    fwd_bwd: Timing | None
    ratio_fwd: float | None
    ratio_fwd_bwd: float | None


def run_problem(problem: Problem, *, methods=METHODS, repeat=5, min_total_s=3.0, max_repeat=100):
    """Checks, then times every method on one problem round-robin: one `Row` per method.

    `scipy_csr` is always timed (every ratio is against it). Small problems get extra
    rounds until the timed calls add up to `min_total_s` (at most `max_repeat` rounds).
    """
    methods = [m for m in methods if m != "scipy_csr"] + ["scipy_csr"]
    cases = make_cases(problem, methods)
    check_cases(problem, cases)
    timings = time_interleaved(
        cases, repeat=repeat, warmup=1, min_total_s=min_total_s, max_repeat=max_repeat
    )
    ref_f, ref_b = timings[("scipy_csr", "fwd")], timings[("scipy_csr", "fwd+bwd")]
    return [
        Row(
            graph=problem.label,
            n_node=problem.n_node,
            n_edge=problem.n_edge,
            max_degree=problem.max_degree,
            width=problem.width,
            method=method,
            fwd=timings[method, "fwd"],
            fwd_bwd=timings[method, "fwd+bwd"],
            ratio_fwd=timings[method, "fwd"].median / ref_f.median,
            ratio_fwd_bwd=timings[method, "fwd+bwd"].median / ref_b.median,
        )
        for method in methods
    ]


def _ratio(r: float | None) -> str:
    return "—" if r is None else f"{r:.2f}×"


def table(rows: list[Row], *, graph_column: bool = False) -> str:
    """The markdown results table (one line per graph, width and method)."""
    headers = ["nodes", "edges", "width", "method", "fwd ms (IQR)", "fwd+bwd ms (IQR)"]
    headers += ["fwd / scipy", "fwd+bwd / scipy", "runs"]
    body = []
    for r in rows:
        line = [f"{r.n_node:,}", f"{r.n_edge:,}", r.width, r.method, format_timing(r.fwd)]
        line += [format_timing(r.fwd_bwd), _ratio(r.ratio_fwd), _ratio(r.ratio_fwd_bwd)]
        line += [r.fwd.n if r.fwd else "—"]
        if graph_column:
            line = [r.graph, r.max_degree] + line
        body.append(line)
    if graph_column:
        headers = ["graph", "max degree"] + headers
    return markdown_table(headers, body)


CSV_HEADERS = (
    "graph",
    "nodes",
    "edges",
    "max_degree",
    "width",
    "method",
    "mode",
    "median_s",
    "q1_s",
    "q3_s",
    "runs",
    "ratio_vs_scipy",
)


def csv_rows(rows: list[Row]) -> list[tuple]:
    out = []
    for r in rows:
        modes = (("fwd", r.fwd, r.ratio_fwd), ("fwd+bwd", r.fwd_bwd, r.ratio_fwd_bwd))
        for mode, t, ratio in modes:
            if t is not None:
                out.append(
                    (r.graph, r.n_node, r.n_edge, r.max_degree, r.width, r.method, mode)
                    + (t.median, t.q1, t.q3, t.n, ratio)
                )
    return out


def plot(rows: list[Row], path: Path) -> Path:
    """Log-log median time against nodes: one panel per width and mode."""
    panels = []
    for width in sorted({r.width for r in rows}):
        for mode in MODES:
            series = {}
            for method in dict.fromkeys(r.method for r in rows):
                pts = [
                    (r.n_node, (r.fwd if mode == "fwd" else r.fwd_bwd).median * 1e3)
                    for r in rows
                    if r.width == width and r.method == method
                ]
                if pts:
                    series[method] = tuple(zip(*pts, strict=True))
            panels.append((f"width {width}, {mode}", series))
    return plot_loglog(
        path,
        panels,
        xlabel="nodes",
        ylabel="median time (ms)",
        suptitle="GCN aggregation on triangulated grids (float32, CPU)",
        ncols=2,
    )


def mesh_problems(names, width: int):
    """Vertex and face graphs of meshes in ../shared/meshes (skipped when absent)."""
    from dmd_jax.graph import build_mesh_graph
    from dmd_jax.io import load_mesh
    from dmd_jax.protocol import shared_meshes_dir

    folder = shared_meshes_dir()
    for name in names:
        path = folder / name
        if not path.is_file():
            print(f"skipping {path}: absent", file=sys.stderr)
            continue
        v, f = load_mesh(path)
        g = build_mesh_graph(f, len(v))
        stem = Path(name).stem
        yield make_problem(
            g.vertex_senders,
            g.vertex_receivers,
            g.vertex_edge_weight,
            g.n_vertex,
            width,
            label=f"{stem} vertices",
        )
        yield make_problem(
            g.face_senders,
            g.face_receivers,
            g.face_edge_weight,
            g.n_face,
            width,
            label=f"{stem} faces",
        )


def parse_skip(entries) -> dict[tuple[int, int], set[str] | None]:
    """`NODESxWIDTH` (skip all) or `NODESxWIDTH:METHOD` -> {(nodes, width): methods}."""
    skip: dict[tuple[int, int], set[str] | None] = {}
    for entry in entries:
        size, _, method = entry.partition(":")
        try:
            nodes, width = (int(v) for v in size.split("x"))
        except ValueError:
            raise ValueError(
                f"--skip entries look like 300000x512[:method], got {entry!r}"
            ) from None
        if method and method not in METHODS:
            raise ValueError(f"unknown method {method!r} in --skip {entry!r}")
        if not method:
            skip[nodes, width] = None
        elif skip.get((nodes, width), set()) is not None:
            skip.setdefault((nodes, width), set()).add(method)
    return skip


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="target nodes")
    p.add_argument("--widths", type=int, nargs="+", default=list(WIDTHS))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--repeat", type=int, default=5, help="timed rounds (at least)")
    p.add_argument(
        "--min-total-s",
        type=float,
        default=3.0,
        help="extra rounds (up to 100) for problems whose timed rounds take less",
    )
    p.add_argument(
        "--skip",
        nargs="*",
        default=list(DEFAULT_SKIP),
        help="NODESxWIDTH or NODESxWIDTH:METHOD not to run (default: %(default)s)",
    )
    p.add_argument(
        "--meshes",
        nargs="*",
        default=list(MESHES),
        help="meshes of ../shared/meshes to time too, at width 64 (default: %(default)s)",
    )
    p.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    p.add_argument("--name", default="aggregation", help="stem of the result files")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    skip = parse_skip(args.skip)
    env = environment()
    rows, skipped = [], []
    timing = {"repeat": args.repeat, "min_total_s": args.min_total_s}
    for width in args.widths:
        for n_target in args.sizes:
            methods = list(args.methods)
            if (n_target, width) in skip:
                dropped = skip[n_target, width]
                if dropped is None:
                    skipped.append(f"{n_target:,} × {width} (all methods)")
                    continue
                methods = [m for m in methods if m not in dropped]
                skipped.append(f"{n_target:,} × {width}: {', '.join(sorted(dropped))}")
            problem = grid_problem(n_target, width)
            new = run_problem(problem, methods=methods, **timing)
            rows += new
            print(table(new).split("\n", 2)[2], flush=True)
    mesh_rows = []
    for problem in mesh_problems(args.meshes, 64):
        new = run_problem(problem, methods=args.methods, **timing)
        mesh_rows += new
        print(table(new, graph_column=True).split("\n", 2)[2], flush=True)
    env["load average (1 min) at end"] = f"{os.getloadavg()[0]:.2f}"
    env["peak RSS"] = f"{peak_rss_gib():.1f} GiB"
    grids = sorted({(r.n_node, r.n_edge, r.max_degree) for r in rows})
    grid_note = "; ".join(f"{n:,} nodes: {e / n:.2f} entries/row, max {d}" for n, e, d in grids)
    notes = [
        "- Times are medians over the timed rounds (`runs`) after one warm-up call per "
        "case (compilation); IQR in brackets. Ratios divide medians taken in the same "
        "process, round-robin over every method and mode of one problem.",
        "- fwd+bwd is `grad(sum(out²))` w.r.t. the features; for SciPy `Aᵀ (2 A X)` with "
        "`Aᵀ` prebuilt as CSR.",
        f"- Grids: {grid_note}.",
        "- Skipped: " + ("; ".join(skipped) if skipped else "nothing") + ".",
        "- SciPy's sparse @ dense runs on one thread; XLA uses every core the process may use.",
    ]
    sections = [("Triangulated grids", table(rows))]
    if mesh_rows:
        sections.append(
            (
                "Real meshes (width 64)",
                "Vertex and face graphs of meshes from `../shared/meshes`. ELL pads every "
                "row to the largest degree, so its work grows with max degree / mean "
                "degree.\n\n" + table(mesh_rows, graph_column=True),
            )
        )
    sections.append(("Notes", "\n".join(notes)))
    out = Path(args.out)
    write_report(
        out / f"{args.name}.md",
        title="GCN aggregation: JAX formulations vs SciPy CSR"
        + (" (glibc huge pages)" if "hugetlb=1" in env["GLIBC_TUNABLES"] else " (default glibc)"),
        intro="\n\n".join(__doc__.split("\n\n")[1:3]),
        env=env,
        sections=sections,
        weights=None,  # no trained model: sparse aggregation only
    )
    write_csv(out / f"{args.name}.csv", CSV_HEADERS, csv_rows(rows + mesh_rows))
    if rows:
        plot(rows, out / f"{args.name}.png")
    print(f"wrote {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
