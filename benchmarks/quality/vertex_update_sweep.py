"""Why the converged vertex update is regularised as it is: Jacobi counts against solves.

The meshes of `tests/test_vertex_update.py` (an icosphere with a hole, a procedural CAD
part, an open height-field grid), each under three noises: along the vertex normals
(Gaussian 0.3 mean edges; on the grid correlated, 0.7), scanner noise (0.8 edges,
`dmd_jax.add_noise(..., "scanner")`) and isotropic Gaussian (0.3 edges per coordinate).
Target normals: the clean mesh's, or those perturbed by 8° per face (iid, a stand-in for
predicted normals). Every cell: mean face-normal error in degrees after the update, and
after a slash the faces whose normal turned against its target (the noisy input's own
count first). Columns: Sun et al.'s Jacobi update at 10 to 300 steps, and the solve
(`dmd_jax.vertex_update`, default tolerance) at tangent weights 0.1 (the default), 0.03
and 0.01, and isotropic (normal and tangent weights both 1e-4: plain Tikhonov).

```bash
python benchmarks/quality/vertex_update_sweep.py     # about 5 minutes on 2 cores
```
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    RESULTS_DIR,
    command_line,
    environment,
    markdown_table,
    write_report,
)

JACOBI = (10, 30, 100, 300)
SOLVES = {"t 0.1": (1e-3, 0.1), "t 0.03": (1e-3, 0.03), "t 0.01": (1e-3, 0.01)}
SOLVES["isotropic 1e-4"] = (1e-4, 1e-4)


def _mean_edge(v, f):
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())


def _along_normals(v, f, level, seed, smooth=0):
    import scipy.sparse as sp

    from dmd_jax.noise import vertex_normals_np

    t = np.random.default_rng(seed).standard_normal((len(v), 1))
    if smooth:
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e = np.concatenate([e, e[:, ::-1]])
        adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), (len(v), len(v))).tocsr()
        adj.data[:] = 1.0
        deg = np.asarray(adj.sum(1)).ravel()
        for _ in range(smooth):
            t = 0.5 * t + 0.5 * (adj @ t) / deg[:, None]
        t /= t.std()
    return v + level * _mean_edge(v, f) * t * vertex_normals_np(v, f)


def meshes() -> dict:
    """`{name: (vertices, faces)}`: the test file's three meshes."""
    import trimesh

    from dmd_jax.data.shapes import generate_shape

    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)
    f = f[v[f].mean(axis=1)[:, 2] < 0.8]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(used.size)
    sphere = (v[used], remap[f].astype(np.int32))
    n = 40
    xs = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(xs, xs)
    z = 0.15 * np.sin(3 * x) * np.cos(2 * y) + 0.1 * x * y
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    grid = (
        np.stack([x.ravel(), y.ravel(), z.ravel()], 1),
        np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int32),
    )
    cad = generate_shape("blocks", 0, 0, min_vertices=1500, max_vertices=2000)
    return {"sphere with a hole": sphere, "CAD part": cad, "open grid": grid}


def noises(name, v, f) -> dict:
    """`{label: noisy vertices}` of one mesh."""
    from dmd_jax.api import add_noise

    normal = (
        ("normal 0.7, correlated", _along_normals(v, f, 0.7, 3, smooth=3))
        if name == "open grid"
        else ("normal 0.3", _along_normals(v, f, 0.3, 1))
    )
    return {
        normal[0]: normal[1],
        "scanner 0.8": add_noise(3, v, f, "scanner", 0.8, units="edge"),
        "isotropic 0.3": add_noise(3, v, f, "gaussian", 0.3, units="edge", direction="isotropic"),
    }


def run(out_dir=RESULTS_DIR, name: str = "vertex_update_sweep", echo=print) -> Path:
    import jax
    import jax.numpy as jnp

    from dmd_jax import geometry
    from dmd_jax.mesh import face_normals_np
    from dmd_jax.vertex_update import solve_vertices_to_normals

    jax.config.update("jax_enable_x64", True)

    @jax.jit
    def jacobi(x, faces, n, k):
        cf = jnp.repeat(jnp.arange(faces.shape[0], dtype=faces.dtype), 3)
        free = jnp.ones(x.shape[0], x.dtype)
        return geometry.fit_vertices_to_normals(x, faces, n, faces.reshape(-1), cf, free, k)

    solve = jax.jit(solve_vertices_to_normals, static_argnames=("normal_weight", "tangent_weight"))

    def cell(x, clean, f, n):
        x = np.asarray(x, np.float64)
        a, b = face_normals_np(x, f), face_normals_np(clean, f)
        err = float(np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0))).mean())
        flips = int(((a * n).sum(1) <= 0).sum())
        return f"{err:.2f} / {flips}"

    rows = []
    for mesh, (v, f) in meshes().items():
        for noise, x0 in noises(mesh, v, f).items():
            for degrees in (0.0, 8.0):
                n = face_normals_np(v, f)
                if degrees:
                    rng = np.random.default_rng(3)
                    n = n + np.radians(degrees) * rng.standard_normal(n.shape)
                    n /= np.linalg.norm(n, axis=1, keepdims=True)
                row = [mesh, noise, "clean" if not degrees else "8° per face", cell(x0, v, f, n)]
                row += [cell(jacobi(x0, f, n, k), v, f, n) for k in JACOBI]
                row += [
                    cell(solve(x0, f, n, normal_weight=mu_n, tangent_weight=mu_t), v, f, n)
                    for mu_n, mu_t in SOLVES.values()
                ]
                rows.append(row)
                echo(" | ".join(str(c) for c in row))
    headers = ["mesh", "noise", "targets", "noisy"]
    headers += [f"Jacobi {k}" for k in JACOBI] + [f"solve, {k}" for k in SOLVES]
    table = markdown_table(headers, rows)
    path = write_report(
        Path(out_dir) / f"{name}.md",
        title="The vertex update: Jacobi steps against regularised solves",
        env=environment(packages=("dmd_jax", "jax", "jaxlib", "numpy")),
        sections=[("Mean face-normal error (°) / faces turned against their target", table)],
        intro=__doc__.split("\n\n")[1].replace("\n", " "),
        command=command_line(),
        weights=None,
    )
    echo(f"wrote {path}")
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--name", default="vertex_update_sweep", help="report file stem")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)
    run(args.out_dir, args.name)


if __name__ == "__main__":
    main()
