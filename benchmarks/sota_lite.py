"""A small comparison table on real scans: mean normal error of DMD-Net vs classic filters.

Every triangle (or polygon, fan-triangulated on load) mesh in `../shared/meshes` gets
Gaussian noise of σ = 0.1, 0.2 and 0.3 × its mean edge length (the CNR / GCN-Denoiser
benchmark convention), then is denoised by

* pymeshlab Taubin smoothing (`dmd_jax.evaluate.pymeshlab_filter(..., "taubin")`),
* pymeshlab two-step smoothing (Sun et al. 2007, `"two_step"`),
* DMD-Net with the bundled weights (or `--weights`), one pass and two passes
  (`denoise(..., iterations=2)`),

and scored by the mean angle between corresponding face normals of the result and the
clean mesh, in degrees (`dmd_jax.metrics.mesh_metrics`). The noise seed of a mesh and
level is a CRC32 of `"<file name>|<level>"`, so a row does not change when files are
added to the folder. The markdown report and a CSV (with vertex and chamfer errors and
run times as well) go to `benchmarks/results/`.

```bash
python benchmarks/sota_lite.py                      # bundled weights
python benchmarks/sota_lite.py --weights run.msgpack --name sota_lite_run
```
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
import warnings
import zlib
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    REPO,
    RESULTS_DIR,
    command_line,
    environment,
    markdown_table,
    write_csv,
    write_report,
)

LEVELS = (0.1, 0.2, 0.3)
LABELS = {
    "noisy": "noisy",
    "taubin": "Taubin",
    "two_step": "two-step",
    "dmd": "DMD-Net",
    "dmd_x2": "DMD-Net ×2",
}
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl")
DEFAULT_MESH_DIR = Path(os.environ.get("DMD_SHARED_MESHES", REPO.parent / "shared" / "meshes"))
CSV_HEADER = (
    "mesh",
    "n_vertex",
    "n_face",
    "level",
    "seed",
    "method",
    "normal_deg",
    "vertex",
    "chamfer",
    "seconds",
)


def noise_seed(mesh_name: str, level: float) -> int:
    """The noise seed of one mesh and level: stable across folders and machines."""
    return zlib.crc32(f"{mesh_name}|{level:g}".encode())


def mesh_files(mesh_dir, skip=()) -> list[Path]:
    """Mesh files of `mesh_dir`, sorted by name, without the names in `skip`."""
    mesh_dir = Path(mesh_dir)
    if not mesh_dir.is_dir():
        raise FileNotFoundError(
            f"{mesh_dir}: no mesh folder (pass --meshes DIR or set DMD_SHARED_MESHES)"
        )
    unknown = set(skip) - {p.name for p in mesh_dir.iterdir()}
    if unknown:
        raise ValueError(f"--skip names files not in {mesh_dir}: {', '.join(sorted(unknown))}")
    return sorted(
        p
        for p in mesh_dir.iterdir()
        if p.suffix.lower() in MESH_SUFFIXES and p.is_file() and p.name not in set(skip)
    )


def evaluate_mesh(
    path, bundle, levels=LEVELS, baselines=(), echo=print
) -> tuple[list[list], list[str]]:
    """Noise, denoise and score one mesh at every level.

    Args:
      path: mesh file.
      bundle: the DMD-Net `ModelBundle`.
      levels: noise σ in mean edge lengths.
      baselines: extra `dmd_jax.baselines` methods to run (e.g. `bnf`, `fefp`).
      echo: progress output.

    Returns:
      `(rows, notes)`: CSV rows in `CSV_HEADER` order (one per level and method) and
      notes on the input (polygons triangulated on load).
    """
    from dmd_jax import baselines as classic
    from dmd_jax.demo import gaussian_edge_noise
    from dmd_jax.evaluate import pymeshlab_filter
    from dmd_jax.inference import denoise
    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import mesh_metrics

    path = Path(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean, faces = load_mesh(path)
    notes = [
        str(w.message).replace(str(path), path.name)
        for w in caught
        if "triangulated" in str(w.message)
    ]
    runners = {
        "taubin": lambda v: pymeshlab_filter(v, faces, "taubin"),
        "two_step": lambda v: pymeshlab_filter(v, faces, "two_step"),
        "dmd": lambda v: denoise(v, faces, bundle),
        "dmd_x2": lambda v: denoise(v, faces, bundle, iterations=2),
    }
    for name in baselines:
        runners[name] = lambda v, name=name: classic.denoise_with(name, v, faces)
    methods = ("noisy", *runners)
    rows = []
    for level in levels:
        seed = noise_seed(path.name, level)
        noisy = gaussian_edge_noise(clean, faces, level, seed)
        outputs = {"noisy": (noisy, 0.0)}
        for name, fn in runners.items():
            start = time.perf_counter()
            outputs[name] = (np.asarray(fn(noisy), np.float64), time.perf_counter() - start)
        for name in methods:
            v, seconds = outputs[name]
            m = mesh_metrics(v, clean, faces)
            rows.append(
                [
                    path.name,
                    len(clean),
                    len(faces),
                    level,
                    seed,
                    name,
                    m["normal_deg"],
                    m["vertex"],
                    m["chamfer"],
                    seconds,
                ]
            )
        errors = "  ".join(f"{_label(r[5])} {r[6]:.2f}°" for r in rows[-len(methods) :])
        echo(f"  {path.name} σ = {level:g}: {errors}")
    return rows, notes


def _label(method: str) -> str:
    return LABELS.get(method, method)


def tables(rows: list[list]) -> tuple[str, str]:
    """Markdown tables of the mean normal error: per mesh and level, and means per level.

    The `best` column names the denoiser with the lowest error of the row (ties listed
    together); the noisy input is not a denoiser and never counts as best.
    """
    by_case: dict[tuple, dict[str, float]] = {}
    n_face = {}
    for mesh, _n_vertex, faces, level, _seed, method, normal, *_ in rows:
        by_case.setdefault((mesh, level), {})[method] = normal
        n_face[mesh] = faces
    methods = list(dict.fromkeys(r[5] for r in rows))

    def best(errs: dict[str, float]) -> str:
        low = min(errs[m] for m in methods if m != "noisy")
        return ", ".join(_label(m) for m in methods if m != "noisy" and errs[m] == low)

    detail = [
        [mesh, n_face[mesh], f"{level:g}"] + [f"{errs[m]:.2f}" for m in methods] + [best(errs)]
        for (mesh, level), errs in by_case.items()
    ]
    headers = ["mesh", "faces", "σ / mean edge"] + [_label(m) for m in methods] + ["best"]
    means = []
    for level in [*sorted({lv for _, lv in by_case}), None]:
        cases = [e for (_, lv), e in by_case.items() if level is None or lv == level]
        mean = {m: float(np.mean([e[m] for e in cases])) for m in methods}
        means.append(
            ["all" if level is None else f"{level:g}", len(cases)]
            + [f"{mean[m]:.2f}" for m in methods]
            + [best(mean)]
        )
    mean_headers = ["σ / mean edge", "meshes"] + [_label(m) for m in methods] + ["best"]
    return markdown_table(headers, detail), markdown_table(mean_headers, means)


def metric_means(rows: list[list]) -> str:
    """All three metrics per method, means over meshes and levels, in the vocabulary of
    `dmd-jax evaluate` (`dmd_jax.metrics.metrics_table`, legend line included)."""
    from dmd_jax.metrics import metrics_table

    by_method: dict[str, list[list]] = {}
    for row in rows:
        by_method.setdefault(row[5], []).append(row)
    means = {}
    for method, group in by_method.items():
        m = {key: float(np.mean([r[CSV_HEADER.index(key)] for r in group])) for key in _KEYS}
        means[_label(method)] = {**m, "vertex_per_coord": m["vertex"] / 3.0}
    return metrics_table(means, label="method")


_KEYS = ("normal_deg", "vertex", "chamfer")


def _weights_description(bundle, weights) -> dict[str, str]:
    from dmd_jax.checkpoints import pretrained_path
    from dmd_jax.model import param_count

    path = pretrained_path() if weights is None else Path(weights)
    info = {
        "weights": ("bundled " if weights is None else "") + str(path),
        "model": f"preset {bundle.config.name}, {param_count(bundle.config.model):,} parameters",
    }
    if path.is_file():
        info["weights sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    for key, value in bundle.meta.items():
        info[f"weights meta: {key}"] = str(value)
    return info


def run(
    mesh_dir=DEFAULT_MESH_DIR,
    *,
    weights=None,
    levels=LEVELS,
    skip=(),
    baselines=(),
    name: str = "sota_lite",
    out_dir=RESULTS_DIR,
    echo=print,
) -> tuple[Path, Path]:
    """Runs the comparison and writes `<out_dir>/<name>.md` and `.csv`."""
    from dmd_jax.baselines import REGISTRY
    from dmd_jax.demo import load_bundle

    unknown = sorted(set(baselines) - set(REGISTRY))
    if unknown:
        raise ValueError(f"unknown baselines {unknown}; choose from {sorted(REGISTRY)}")
    files = mesh_files(mesh_dir, skip)
    if not files:
        raise ValueError(f"{mesh_dir}: no {', '.join(MESH_SUFFIXES)} files")
    bundle = load_bundle(weights)
    env = environment(
        packages=("dmd_jax", "jax", "jaxlib", "flax", "numpy", "pymeshlab", "trimesh")
    )
    env.update(_weights_description(bundle, weights))
    start = time.perf_counter()
    rows, notes = [], []
    for i, path in enumerate(files, 1):
        echo(f"[{i}/{len(files)}] {path.name}")
        mesh_rows, mesh_notes = evaluate_mesh(path, bundle, levels, baselines, echo=echo)
        rows += mesh_rows
        notes += mesh_notes
    env["wall time"] = f"{time.perf_counter() - start:.0f} s"
    detail, means = tables(rows)
    out_dir = Path(out_dir)
    csv_path = write_csv(out_dir / f"{name}.csv", CSV_HEADER, rows)
    intro = (
        "normal (°): mean angle between corresponding face normals (lower is better) after "
        "Gaussian noise of σ × the mesh's mean edge length; `best` names the denoiser "
        f"with the lowest error. Meshes: every file of `{Path(mesh_dir).name}/`"
        + (f" except {', '.join(skip)}" if skip else "")
        + ". Taubin and two-step are pymeshlab's filters with the settings of "
        "`dmd_jax.evaluate.PYMESHLAB_FILTERS`; DMD-Net ×2 applies the network twice"
        + (
            f"; {', '.join(baselines)}: `dmd_jax.baselines` with their defaults. "
            if baselines
            else ". "
        )
        + "Noise seeds: CRC32 of `<file>|<σ>` (column `seed` of the CSV, which also holds "
        "vertex and chamfer errors and run times)."
    )
    sections = [
        ("Means over meshes", means),
        ("All metrics, means over meshes and levels", metric_means(rows)),
        ("Per mesh", detail),
    ]
    if notes:
        sections.append(("Input notes", "\n".join(f"* {n}" for n in notes)))
    md_path = write_report(
        out_dir / f"{name}.md",
        title="Mean normal error on real meshes: DMD-Net vs classic filters",
        env=env,
        sections=sections,
        intro=intro,
        command=command_line(),
    )
    echo(means)
    echo(f"wrote {md_path} and {csv_path}")
    return md_path, csv_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default=str(DEFAULT_MESH_DIR), help="folder of meshes")
    parser.add_argument(
        "--weights", default=None, help="weights file or checkpoint dir (default: bundled)"
    )
    parser.add_argument("--levels", type=float, nargs="+", default=list(LEVELS))
    parser.add_argument("--skip", nargs="*", default=[], help="file names to leave out")
    parser.add_argument(
        "--baselines",
        nargs="*",
        default=[],
        help="extra dmd_jax.baselines methods as columns, e.g. bnf fefp",
    )
    parser.add_argument("--name", default="sota_lite", help="report file stem")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)
    try:
        run(
            args.meshes,
            weights=args.weights,
            levels=tuple(args.levels),
            skip=tuple(args.skip),
            baselines=tuple(args.baselines),
            name=args.name,
            out_dir=args.out_dir,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"sota_lite: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
