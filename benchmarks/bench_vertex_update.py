"""What the normal-first head's vertex update costs against a whole `denoise` call.

On one noisy wavy height field of about `--faces` faces (`common.noisy_grid`), in one
process, timed round-robin (`common.time_interleaved`, medians):

* `denoise`: `dmd_jax.denoise(vertices, faces)` with the bundled weights and policy,
  end to end (the default call);
* `denoise, solve`: the same call with the bundled config switched to
  `vertex_update="solve"` (`dmd_jax.vertex_update`, default tolerance);
* `jacobi 10`: Sun et al.'s update, the bundled model's 10 iterations
  (`geometry.fit_vertices_to_normals`), compiled alone;
* `solve`: `vertex_update.solve_vertices_to_normals` at its defaults, compiled alone.

The two updates get the bundled network's own face normals of the mesh (one forward
pass, in the model's frame) and its positions, so the solve takes the iterations it
takes inside `denoise`. The ratios divide each update's time, times the network passes
the call ran, by the default call's time.

```bash
python benchmarks/bench_vertex_update.py               # 100k faces, 5 rounds
python benchmarks/bench_vertex_update.py --faces 10000 --repeat 3
```
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    command_line,
    environment,
    format_ms,
    markdown_table,
    noisy_grid,
    time_interleaved,
    write_report,
)


def run(n_face: int, repeat: int, name: str, out_dir=RESULTS_DIR, echo=print) -> Path:
    import jax
    import jax.numpy as jnp

    from dmd_jax import geometry
    from dmd_jax.checkpoints import load_model
    from dmd_jax.encoding import mesh_frame
    from dmd_jax.graph import build_mesh_graph
    from dmd_jax.inference import denoise
    from dmd_jax.model import DMDNet
    from dmd_jax.vertex_update import solve_vertices_to_normals

    v, f = noisy_grid(n_face)
    bundle = load_model()
    model_cfg = bundle.config.model
    if model_cfg.head != "normal":
        raise ValueError("the bundled model has no normal-first head: no vertex update to time")
    solve_bundle = bundle.with_vertex_update("solve")

    # The network's own normals, in its frame, as the update sees them inside `denoise`.
    x = jnp.asarray(mesh_frame(model_cfg.encoding, v, f).apply(v), jnp.float32)
    graph = jax.tree.map(jnp.asarray, build_mesh_graph(f, v.shape[0]))
    apply = jax.jit(lambda p, x, g: DMDNet(model_cfg).apply({"params": p}, x, g)[2])
    normals = apply(bundle.params, x, graph)["face_normals"]
    faces = jnp.asarray(f)

    # Faces are arguments, as inside the model: closed over, XLA would fold the
    # vertex degrees into constants.
    @jax.jit
    def jacobi(x, faces, n):
        corner_face = jnp.repeat(jnp.arange(faces.shape[0], dtype=faces.dtype), 3)
        free = jnp.ones(x.shape[0], x.dtype)
        return geometry.fit_vertices_to_normals(
            x, faces, n, faces.reshape(-1), corner_face, free, model_cfg.vertex_iterations
        )

    solve = jax.jit(lambda x, faces, n: solve_vertices_to_normals(x, faces, n, return_info=True))
    _, info = solve(x, faces, normals)
    _, call = denoise(v, f, bundle, return_info=True)
    _, solve_call = denoise(v, f, solve_bundle, return_info=True)
    echo(f"{f.shape[0]:,} faces: {int(info.iterations)} CG iterations; passes {call.passes}")

    timings = time_interleaved(
        {
            "denoise": lambda: denoise(v, f, bundle),
            "denoise, solve": lambda: denoise(v, f, solve_bundle),
            f"jacobi {model_cfg.vertex_iterations}": lambda: jacobi(x, faces, normals),
            "solve": lambda: solve(x, faces, normals)[0],
        },
        repeat=repeat,
        warmup=1,
    )
    base = timings["denoise"].median
    rows = []
    for case, t in timings.items():
        passes = solve_call.passes if case == "denoise, solve" else call.passes
        share = t.median / base if case.startswith("denoise") else passes * t.median / base
        rows.append(
            [
                case,
                format_ms(t.median),
                f"{format_ms(t.min)} - {format_ms(max(t.times))}",
                t.n,
                f"{share:.3f}",
            ]
        )
    table = markdown_table(["case", "median", "range", "runs", "share of the default call"], rows)
    env = environment(packages=("dmd_jax", "jax", "jaxlib", "numpy"))
    env.update(
        {
            "mesh": f"common.noisy_grid({n_face}): {v.shape[0]:,} vertices, {f.shape[0]:,} faces",
            "network passes": f"default call {call.passes}, with the solve {solve_call.passes}",
            "solve": f"{int(info.iterations)} CG iterations, residual {float(info.residual):.1e}",
        }
    )
    intro = (
        "Share: an update's median time times the network passes the default call ran, "
        "over the default call's median (`denoise` rows: the whole call's). Same process, "
        "interleaved rounds after one warm-up call each."
    )
    path = write_report(
        Path(out_dir) / f"{name}.md",
        title="The vertex update against the default denoise call",
        env=env,
        sections=[("Times", table)],
        intro=intro,
        command=command_line(),
    )
    echo(table)
    echo(f"wrote {path}")
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--faces", type=int, default=100_000, help="faces of the test mesh")
    parser.add_argument("--repeat", type=int, default=5, help="timed rounds")
    parser.add_argument("--name", default="vertex_update", help="report file stem")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)
    run(args.faces, args.repeat, args.name, args.out_dir)


if __name__ == "__main__":
    main()
