"""Peak memory and time of `dmd_jax.denoise` against mesh size (one process per size).

Each size runs in a fresh child process, so `ru_maxrss` (the peak resident set size of
that process, Linux) holds the imports, the weights, the mesh, XLA's compilation and the
forward pass of that size only. The mesh is a torus grid (`rows × rows` quads split in
two), closed and regular, with exactly `2 · rows²` faces. Params are those of
`--weights`, or zeros of the `small` preset's shapes by default: memory and time do not
depend on the values.

```bash
python benchmarks/denoise_memory.py --faces 25000 50000 100000 200000
```
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import environment, markdown_table  # noqa: E402

SIZES = (25_000, 50_000, 100_000, 200_000)


def torus_grid(rows: int):
    """A closed torus of `rows²` vertices and `2 · rows²` triangles (NumPy arrays)."""
    import numpy as np

    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, rows, endpoint=False),
        np.linspace(0, 2 * np.pi, rows, endpoint=False),
        indexing="ij",
    )
    big, small = 1.0, 0.35
    vertices = np.stack(
        [(big + small * np.cos(v)) * np.cos(u), (big + small * np.cos(v)) * np.sin(u),
         small * np.sin(v)], axis=-1,
    ).reshape(-1, 3)  # fmt: skip
    i, j = np.meshgrid(np.arange(rows), np.arange(rows), indexing="ij")
    a = i * rows + j
    b = ((i + 1) % rows) * rows + j
    c = ((i + 1) % rows) * rows + (j + 1) % rows
    d = i * rows + (j + 1) % rows
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return vertices, faces.reshape(-1, 3).astype(np.int32)


def measure_child(n_faces: int, weights: str | None) -> dict:
    """Runs in the child: builds the mesh, denoises twice, reports RSS and times."""
    import resource
    import time

    import jax
    import numpy as np

    from dmd_jax.config import preset
    from dmd_jax.inference import ModelBundle, denoise, load_weights
    from dmd_jax.model import param_shapes

    def rss_mib() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    if weights:
        bundle = load_weights(weights)
    else:
        cfg = preset("small")
        params = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), param_shapes(cfg.model))
        bundle = ModelBundle(params, cfg, {})
    rows = round(math.sqrt(n_faces / 2))
    v, f = torus_grid(rows)
    before = rss_mib()
    start = time.perf_counter()
    denoise(v, f, bundle)
    first = time.perf_counter() - start
    start = time.perf_counter()
    denoise(v, f, bundle)
    second = time.perf_counter() - start
    return {
        "faces": len(f),
        "vertices": len(v),
        "preset": bundle.config.name,
        "rss_before_mib": before,
        "peak_rss_mib": rss_mib(),
        "first_call_s": first,
        "second_call_s": second,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--faces", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--weights", default=None, help="weights file (default: small zeros)")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(measure_child(args.child, args.weights)))
        return 0
    rows = []
    for n in args.faces:
        cmd = [sys.executable, __file__, "--child", str(n)]
        if args.weights:
            cmd += ["--weights", args.weights]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        rows.append(
            [
                f"{r['faces']:,}",
                f"{r['vertices']:,}",
                r["preset"],
                f"{r['rss_before_mib']:.0f}",
                f"{r['peak_rss_mib']:.0f}",
                f"{r['peak_rss_mib'] - r['rss_before_mib']:.0f}",
                f"{r['first_call_s']:.1f}",
                f"{r['second_call_s']:.1f}",
            ]
        )
        print(rows[-1], flush=True)
    env = environment(packages=("jax", "jaxlib", "flax"))
    print(" | ".join(f"{k}: {env[k]}" for k in ("CPU", "nproc", "jax", "JAX backend")))
    print(
        markdown_table(
            [
                "faces",
                "vertices",
                "preset",
                "RSS before (MiB)",
                "peak RSS (MiB)",
                "peak − before (MiB)",
                "1st call (s)",
                "2nd call (s)",
            ],
            rows,
        )  # fmt: skip
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
