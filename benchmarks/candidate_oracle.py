"""Which candidate normal would have been right? (validation split, `sota_lite` protocol)

The normal-first head mixes K candidate face normals (`dmd_jax.encoding.local_features`:
the noisy one, the bilateral pre-filtered ones, and with `taubin_iterations` the
Taubin-smoothed ones). This script scores each candidate *alone*, followed by the same
parameter-free vertex update the model ends with, on the `sota_lite` meshes, crops and
noise seeds (Gaussian along normals), next to the model and the library's Taubin. Where a
classic filter beats every candidate, the head cannot pick its way to that result; this is
how the Taubin candidates were found (`docs/design-decisions.md`). Writes
`benchmarks/results/candidate_oracle.md`.

    python benchmarks/candidate_oracle.py --level 0.3
    python benchmarks/candidate_oracle.py --level 0.3 --taubin-iterations 0  # filters only
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main(argv=None) -> int:
    import jax
    import jax.numpy as jnp
    from common import environment, markdown_table, write_report
    from relax_validation import validation_crops
    from sota_lite import MAX_FACES, noise_seed

    import dmd_jax
    from dmd_jax import baselines, encoding, geometry
    from dmd_jax.demo import gaussian_edge_noise
    from dmd_jax.graph import build_mesh_graph
    from dmd_jax.metrics import face_normal_errors_deg

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train-meshes", type=Path, default=HERE.parent.parent / "shared/meshes/train")
    p.add_argument("--level", type=float, default=0.3, help="σ in mean edge lengths")
    p.add_argument(
        "--taubin-iterations",
        type=int,
        default=None,
        help="Taubin candidates to score (default: the bundled model's)",
    )
    p.add_argument("--out", type=Path, default=HERE / "results" / "candidate_oracle.md")
    args = p.parse_args(argv)
    bundle = dmd_jax.load_pretrained()
    mcfg = bundle.config.model
    taubin = mcfg.taubin_iterations if args.taubin_iterations is None else args.taubin_iterations
    names = encoding.candidate_labels(mcfg.filter_iterations, taubin, mcfg.filter_sigmas)

    @jax.jit
    def candidates(x, graph):
        _, _, c = encoding.local_features(
            x,
            graph,
            filter_iterations=mcfg.filter_iterations,
            taubin_iterations=taubin,
            filter_sigmas=mcfg.filter_sigmas,
        )
        return c

    def err(v, clean, faces):
        return float(np.mean(face_normal_errors_deg(np.asarray(v, np.float64), clean, faces)))

    start = time.perf_counter()
    rows, table = [], []
    for name, clean, faces in validation_crops(args.train_meshes, MAX_FACES, every=1):
        noisy = gaussian_edge_noise(clean, faces, args.level, noise_seed(name, args.level))
        frame = encoding.mesh_frame("local", noisy, faces)
        x = jnp.asarray(frame.apply(noisy), jnp.float32)
        graph = jax.tree.map(jnp.asarray, build_mesh_graph(faces, noisy.shape[0]))
        cand = candidates(x, graph)
        corner_face = jnp.repeat(jnp.arange(faces.shape[0], dtype=graph.faces.dtype), 3)
        free = jnp.ones(x.shape[0], x.dtype)
        per = []
        for k in range(cand.shape[1]):
            moved = geometry.fit_vertices_to_normals(
                x,
                graph.faces,
                cand[:, k],
                graph.faces.reshape(-1),
                corner_face,
                free,
                mcfg.vertex_iterations,
            )
            per.append(err(frame.invert(np.asarray(moved, np.float64)), clean, faces))
        model = err(dmd_jax.denoise(noisy, faces, bundle), clean, faces)
        taubin_err = err(baselines.run_baseline("taubin", noisy, faces), clean, faces)
        rows.append([model, taubin_err, min(per), *per])
        table.append(
            [name, f"{model:.2f}", f"{taubin_err:.2f}", f"{min(per):.2f}"]
            + [f"{e:.1f}" for e in per]
        )
        print(" ".join(table[-1][:4]), flush=True)
    mean = np.mean(rows, axis=0)
    table.append(["**mean**", *(f"**{m:.2f}**" for m in mean[:3])] + [f"{m:.1f}" for m in mean[3:]])
    header = ["mesh", "model", "Taubin (library)", "best candidate", *names]
    intro = (
        f"Each candidate normal field of the bundled model's encoding alone, followed by "
        f"its {mcfg.vertex_iterations} vertex updates, on the validation split of "
        f"`{args.train_meshes.name}` (crops of at most {MAX_FACES} faces and the noise seeds "
        f"of `sota_lite.py`) at Gaussian noise of {args.level} mean edges along the vertex "
        "normals; mean face-normal error in degrees. *model*: the bundled model; *best "
        "candidate*: the lowest of the candidate columns for that mesh (an oracle that "
        f"picks one field per mesh). {time.perf_counter() - start:.0f} s."
    )
    write_report(
        args.out,
        title="Candidate normals alone, against the model and Taubin",
        env=environment(),
        intro=intro,
        sections=[("Per mesh", markdown_table(header, table))],
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
