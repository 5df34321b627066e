"""The library's comparison table on real meshes: every denoiser, the benchmark protocol.

Every mesh of two sets, `shared` (every triangle or polygon mesh of `../shared/meshes`,
polygons fan-triangulated on load) and `val` (the fixed validation split of the real
training meshes `../shared/meshes/train`, `dmd_jax.data.real`, never trained on), gets
the benchmark noise of `dmd_jax.protocol` (Gaussian, σ = 0.1, 0.2 and 0.3 × its mean
edge length along the vertex normals: the CNR / GCN-Denoiser protocol; meshes above
`protocol.MAX_FACES` faces cropped), then is denoised by every denoiser of the
library: the classic filters of `dmd_jax.baselines.REGISTRY`, CNR and DMD-Net (bundled
weights, or `--weights`), with pymeshlab's Taubin and two-step filters as a reference.
Each result is scored by the mean angle between corresponding face normals and the
clean mesh's, in degrees (`dmd_jax.metrics.mesh_metrics`, which also gives the vertex
and chamfer errors kept in the CSV), and timed. The noise seed of a mesh and level is a
CRC32 of `"<file name>|<level>"` (`protocol.noise_seed`), so a row does not change when
files are added.

```bash
python benchmarks/quality/sota_lite.py              # bundled weights (make sota-lite)
python benchmarks/quality/sota_lite.py --weights run.msgpack --name sota_lite_run
python benchmarks/quality/sota_lite.py --reuse      # rerun DMD-Net only, reuse the rest
```
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    command_line,
    environment,
    file_sha256,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax import protocol  # noqa: E402
from dmd_jax.protocol import MAX_FACES, MESH_SUFFIXES, NOISE_LEVELS  # noqa: E402

LEVELS = NOISE_LEVELS
REFERENCE = protocol.REFERENCE_METHODS
DEFAULT_MESH_DIR = protocol.shared_meshes_dir()
# The fixed validation split of the real training meshes (dmd_jax.data.real).
DEFAULT_VAL_DIR = protocol.validation_dir()
CSV_HEADER = (
    "set",
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


def _runner(method: str, faces, bundle):
    from dmd_jax import baselines as classic
    from dmd_jax.baselines.meshlab import pymeshlab_filter
    from dmd_jax.inference import denoise

    if method in REFERENCE:
        return lambda v: pymeshlab_filter(v, faces, method.removeprefix("meshlab_"))
    if method == "dmd":
        return lambda v: denoise(v, faces, bundle)
    if method == "dmd_x2":
        return lambda v: denoise(v, faces, bundle, iterations=2)
    return lambda v: classic.run_baseline(method, v, faces)


def evaluate_mesh(
    path,
    bundle,
    levels=LEVELS,
    methods=None,
    *,
    mesh_set="shared",
    cached=None,
    max_faces: int = 0,
    echo=print,
) -> tuple[list[list], list[str]]:
    """Noise, denoise and score one mesh at every level.

    Args:
      path: mesh file.
      bundle: the DMD-Net `ModelBundle`.
      levels: noise σ in mean edge lengths (Gaussian, along the vertex normals).
      methods: method ids (default `protocol.benchmark_methods()`).
      mesh_set: the set's name, the first CSV column.
      cached: `{(set, mesh, level, seed, method): row}` of earlier rows to reuse instead
        of rerunning (classic methods are deterministic; DMD-Net rows are never cached).
      max_faces: crop a larger mesh to a connected patch of this many faces
        (`protocol.crop`); 0 keeps every mesh whole.
      echo: progress output.

    Returns:
      `(rows, notes)`: CSV rows in `CSV_HEADER` order (one per level and method, the
      noisy input first) and notes on the input (polygons triangulated on load).
    """
    from dmd_jax.io import load_mesh
    from dmd_jax.metrics import mesh_metrics

    methods = protocol.benchmark_methods() if methods is None else tuple(methods)
    cached = cached or {}
    path = Path(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean, faces = load_mesh(path)
    clean, faces = protocol.crop(clean, faces, max_faces)
    notes = [
        str(w.message).replace(str(path), path.name)
        for w in caught
        if "triangulated" in str(w.message)
    ]
    rows = []
    for level in levels:
        seed = protocol.noise_seed(path.name, level)
        noisy = protocol.benchmark_noise(clean, faces, level, seed)
        block = []
        for name in ("noisy", *methods):
            key = (mesh_set, path.name, float(level), int(seed), name)
            if key in cached and not name.startswith("dmd"):
                block.append(cached[key])
                continue
            start = time.perf_counter()
            v = noisy if name == "noisy" else _runner(name, faces, bundle)(noisy)
            seconds = 0.0 if name == "noisy" else time.perf_counter() - start
            m = mesh_metrics(np.asarray(v, np.float64), clean, faces)
            block.append(
                [
                    mesh_set,
                    path.name,
                    len(clean),
                    len(faces),
                    float(level),
                    int(seed),
                    name,
                    m["normal_deg"],
                    m["vertex"],
                    m["chamfer"],
                    seconds,
                ]
            )
        rows += block
        errors = "  ".join(f"{_label(r[6])} {r[7]:.2f}°" for r in block)
        echo(f"  {path.name} σ = {level:g}: {errors}")
    return rows, notes


_label = protocol.label


def _best(errs: dict[str, float], methods: list[str]) -> str:
    """The library denoiser(s) with the lowest error (not the input, not MeshLab's)."""
    own = [m for m in methods if m != "noisy" and m not in REFERENCE]
    low = min(errs[m] for m in own)
    return ", ".join(_label(m) for m in own if errs[m] == low)


def _margin(errs: dict[str, float], methods: list[str]) -> str:
    """DMD-Net's error minus the best other library denoiser's (negative: DMD-Net wins)."""
    if "dmd" not in methods:
        return ""
    others = [m for m in methods if m not in ("noisy", "dmd", "dmd_x2") and m not in REFERENCE]
    if not others:
        return ""
    return f"{errs['dmd'] - min(errs[m] for m in others):+.2f}"


def tables(rows: list[list]) -> tuple[str, str, str]:
    """Markdown tables of the mean normal error, per mesh set: per mesh and level, means
    per level, and the median run time of each method.

    The `best` column names the library denoiser with the lowest error (the noisy input
    and MeshLab's reference filters never count); `DMD-Net margin` is DMD-Net's error
    minus the best other library denoiser's, so negative means DMD-Net wins.
    """
    by_case: dict[tuple, dict[str, float]] = {}
    n_face = {}
    seconds: dict[tuple, list[float]] = {}
    for mesh_set, mesh, _n_vertex, faces, level, _seed, method, normal, *_rest in rows:
        by_case.setdefault((mesh_set, mesh, level), {})[method] = normal
        n_face[mesh] = faces
        seconds.setdefault((mesh_set, method), []).append(_rest[-1])
    methods = list(dict.fromkeys(r[6] for r in rows))
    sets = list(dict.fromkeys(r[0] for r in rows))
    labels = [_label(m) for m in methods]

    detail = [
        [mesh_set, mesh, n_face[mesh], f"{level:g}"]
        + [f"{errs[m]:.2f}" for m in methods]
        + [_best(errs, methods), _margin(errs, methods)]
        for (mesh_set, mesh, level), errs in by_case.items()
    ]
    headers = ["set", "mesh", "faces", "σ / mean edge", *labels, "best", "DMD-Net margin"]
    means = []
    for mesh_set in sets:
        levels = sorted({lv for (st, _, lv) in by_case if st == mesh_set})
        for level in [*levels, None]:
            cases = [
                e
                for (st, _, lv), e in by_case.items()
                if st == mesh_set and (level is None or lv == level)
            ]
            mean = {m: float(np.mean([e[m] for e in cases])) for m in methods}
            means.append(
                [mesh_set, "all" if level is None else f"{level:g}", len(cases)]
                + [f"{mean[m]:.2f}" for m in methods]
                + [_best(mean, methods), _margin(mean, methods)]
            )
    mean_headers = ["set", "σ / mean edge", "cases", *labels, "best", "DMD-Net margin"]
    timing = [
        [mesh_set]
        + [
            f"{np.median(seconds[(mesh_set, m)]):.3f}" if (mesh_set, m) in seconds else ""
            for m in methods
            if m != "noisy"
        ]
        for mesh_set in sets
    ]
    timing_headers = ["set", *[_label(m) for m in methods if m != "noisy"]]
    return (
        markdown_table(headers, detail),
        markdown_table(mean_headers, means),
        markdown_table(timing_headers, timing),
    )


def metric_means(rows: list[list]) -> str:
    """All three metrics per method, means over meshes and levels, in the vocabulary of
    `dmd-jax evaluate` (`dmd_jax.metrics.metrics_table`, legend line included)."""
    from dmd_jax.metrics import metrics_table

    by_method: dict[str, list[list]] = {}
    for row in rows:
        by_method.setdefault(row[6], []).append(row)
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
        "policy": ", ".join(f"{k}={v}" for k, v in bundle.policy.to_dict().items()),
    }
    if path.is_file():
        info["weights sha256"] = file_sha256(path, 16)
    for key, value in bundle.meta.items():
        info[f"weights meta: {key}"] = str(value)
    return info


def read_cached(csv_path) -> dict[tuple, list]:
    """Rows of an earlier report, keyed `(set, mesh, level, seed, method)`."""
    import csv

    csv_path = Path(csv_path)
    if not csv_path.is_file():
        return {}
    out = {}
    with open(csv_path) as fh:
        for r in csv.DictReader(fh):
            if list(r) != list(CSV_HEADER):
                return {}  # another layout: recompute everything
            row = [
                r["set"],
                r["mesh"],
                int(r["n_vertex"]),
                int(r["n_face"]),
                float(r["level"]),
                int(r["seed"]),
                r["method"],
                float(r["normal_deg"]),
                float(r["vertex"]),
                float(r["chamfer"]),
                float(r["seconds"]),
            ]
            out[(row[0], row[1], row[4], row[5], row[6])] = row
    return out


def run(
    mesh_dir=DEFAULT_MESH_DIR,
    *,
    val_dir=DEFAULT_VAL_DIR,
    weights=None,
    levels=LEVELS,
    skip=(),
    methods=None,
    name: str = "sota_lite",
    out_dir=RESULTS_DIR,
    reuse: bool = False,
    reuse_from=(),
    sets=("shared", "val"),
    max_faces: int = MAX_FACES,
    echo=print,
) -> tuple[Path, Path]:
    """Runs the comparison and writes `<out_dir>/<name>.md` and `.csv`.

    Args:
      mesh_dir: folder of test meshes (every file, set `shared`).
      val_dir: folder of real training meshes whose fixed validation split
        (`dmd_jax.data.real`) is the second set, `val`; None leaves it out.
      weights: DMD-Net weights (default: bundled).
      levels: noise σ in mean edge lengths.
      skip: file names of `mesh_dir` to leave out.
      methods: method ids (default `protocol.benchmark_methods()`).
      name, out_dir: report file stem and folder.
      reuse: take rows of classic methods from an existing `<name>.csv` (same mesh,
        level, seed and method) instead of recomputing them.
      reuse_from: more CSV files to take such rows from (e.g. the sets run separately).
      sets: which sets to run (`shared`, `val`).
      max_faces: meshes above this many faces are cropped to a connected patch of it
        (`protocol.crop`); 0 runs whole meshes.
    """
    from dmd_jax.baselines import REGISTRY
    from dmd_jax.checkpoints import load_model

    methods = protocol.benchmark_methods() if methods is None else tuple(methods)
    known = {*REFERENCE, *REGISTRY, "cnr", "dmd", "dmd_x2"}
    unknown = sorted(set(methods) - known)
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(known)}")
    unknown_sets = sorted(set(sets) - {"shared", "val"})
    if unknown_sets or not sets:
        raise ValueError(f"unknown mesh sets {unknown_sets}; choose from shared, val")
    wanted, sets = sets, {}
    if "shared" in wanted:
        sets["shared"] = protocol.mesh_files(mesh_dir, skip)
        if not sets["shared"]:
            raise ValueError(f"{mesh_dir}: no {', '.join(MESH_SUFFIXES)} files")
    if val_dir is not None and "val" in wanted:
        sets["val"] = protocol.validation_files(val_dir)
    if not sets:
        raise ValueError("no mesh set to run (--no-val with --sets val)")
    bundle = load_model(weights)
    env = environment(
        packages=("dmd_jax", "jax", "jaxlib", "flax", "numpy", "pymeshlab", "trimesh")
    )
    env.update(_weights_description(bundle, weights))
    out_dir = Path(out_dir)
    cached = {}
    for csv_file in ([out_dir / f"{name}.csv"] if reuse else []) + [Path(p) for p in reuse_from]:
        cached.update(read_cached(csv_file))
    start = time.perf_counter()
    rows, notes = [], []
    total = sum(len(files) for files in sets.values())
    i = 0
    for mesh_set, files in sets.items():
        for path in files:
            i += 1
            echo(f"[{i}/{total}] {mesh_set}: {path.name}")
            mesh_rows, mesh_notes = evaluate_mesh(
                path,
                bundle,
                levels,
                methods,
                mesh_set=mesh_set,
                cached=cached,
                max_faces=max_faces,
                echo=echo,
            )
            rows += mesh_rows
            notes += mesh_notes
    env["wall time"] = f"{time.perf_counter() - start:.0f} s" + (
        " (classic rows reused from the previous report)" if cached else ""
    )
    detail, means, timing = tables(rows)
    csv_path = write_csv(out_dir / f"{name}.csv", CSV_HEADER, rows)
    intro = (
        "normal (°): mean angle between corresponding face normals (lower is better) after "
        "Gaussian noise of σ × the mesh's mean edge length along the vertex normals (the "
        "benchmark protocol of CNR and GCN-Denoiser). Sets: `shared` = every file of "
        f"`{Path(mesh_dir).name}/`"
        + (f" except {', '.join(skip)}" if skip else "")
        + (
            f"; `val` = the fixed validation split of `{Path(val_dir).name}/` "
            "(`dmd_jax.data.real.validation_names`), never trained on"
            if val_dir is not None
            else ""
        )
        + (
            f". Meshes above {max_faces:,} faces are cropped to the connected "
            f"{max_faces:,}-face patch grown from face 0 (`protocol.crop`), to keep the slowest "
            "filters (GNF, L0: ~1 ms per face) within a CPU session; `--max-faces 0` runs "
            "whole meshes"
            if max_faces
            else ""
        )
        + ". `best` names the library denoiser with the lowest error; MeshLab Taubin and "
        "two-step are pymeshlab's filters (`dmd_jax.baselines.meshlab.PYMESHLAB_FILTERS`), "
        "shown as a reference and never counted as best; every other column is "
        "`dmd_jax.baselines` "
        "with its defaults (CNR with its bundled weights). `DMD-Net margin` = DMD-Net "
        "minus the best other library denoiser (negative: DMD-Net wins). Noise seeds: "
        "CRC32 of `<file>|<σ>` (column `seed` of the CSV, which also holds vertex and "
        "chamfer errors and run times)."
    )
    sections = [
        ("Means over meshes", means),
        ("Median run time per mesh (s)", timing),
        ("All metrics, means over meshes and levels", metric_means(rows)),
        ("Per mesh", detail),
    ]
    if notes:
        sections.append(("Input notes", "\n".join(f"* {n}" for n in notes)))
    md_path = write_report(
        out_dir / f"{name}.md",
        title="Mean normal error on real meshes: every denoiser of the library",
        env=env,
        sections=sections,
        intro=intro,
        command=command_line(),
        weights=BUNDLED if weights is None else weights,
    )
    echo(means)
    echo(f"wrote {md_path} and {csv_path}")
    return md_path, csv_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default=str(DEFAULT_MESH_DIR), help="folder of meshes")
    parser.add_argument(
        "--val-meshes",
        default=str(DEFAULT_VAL_DIR),
        help="folder of real training meshes whose validation split is the second set",
    )
    parser.add_argument("--no-val", action="store_true", help="leave the validation set out")
    parser.add_argument(
        "--weights", default=None, help="weights file or checkpoint dir (default: bundled)"
    )
    parser.add_argument("--levels", type=float, nargs="+", default=list(LEVELS))
    parser.add_argument("--skip", nargs="*", default=[], help="file names to leave out")
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        help="methods to run (default: MeshLab's two, every dmd_jax.baselines method, cnr, "
        "dmd; dmd_x2 applies DMD-Net twice)",
    )
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="reuse the classic methods' rows of an existing report of the same name",
    )
    parser.add_argument(
        "--reuse-from", nargs="*", default=[], help="more CSV reports to reuse rows from"
    )
    parser.add_argument("--sets", nargs="+", default=["shared", "val"], choices=("shared", "val"))
    parser.add_argument(
        "--max-faces",
        type=int,
        default=MAX_FACES,
        help="crop larger meshes to a connected patch of this many faces (0: whole meshes)",
    )
    parser.add_argument("--name", default="sota_lite", help="report file stem")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)
    try:
        run(
            args.meshes,
            val_dir=None if args.no_val else args.val_meshes,
            weights=args.weights,
            levels=tuple(args.levels),
            skip=tuple(args.skip),
            methods=None if args.methods is None else tuple(args.methods),
            name=args.name,
            out_dir=args.out_dir,
            reuse=args.reuse,
            reuse_from=tuple(args.reuse_from),
            sets=tuple(args.sets),
            max_faces=args.max_faces,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"sota_lite: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
