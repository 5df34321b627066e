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

Beyond the Gaussian benchmark levels, heavier and impulsive noise
(`protocol.QUALITY_CONDITIONS`), the shared and val meshes get scanner noise at 0.3,
0.5 and 0.8 edges (`protocol.SCANNER_CONDITIONS`: along one view, correlated, as depth
sensors) and are scanned by the depth-camera simulator at two levels
(`protocol.SCAN_CONDITIONS`: each method denoises the range-image mesh, scored against
its exact ground truth). A third set, `stress`, holds the generated CAD shapes of
`dmd_jax.data.stress` (pyramid, cube, ...), clean and at light Gaussian noise
(`protocol.STRESS_CONDITIONS`). Every set and condition reports DMD-Net's per-mesh ratio
to the best other method: geometric mean and the worst ratio with its mesh.
The report's tables are built by `benchmarks/quality/sota_tables.py` from the rows run here.

```bash
python benchmarks/quality/sota_lite.py              # bundled weights (make sota-lite)
python benchmarks/quality/sota_lite.py --weights run.msgpack --name sota_lite_run
python benchmarks/quality/sota_lite.py --reuse      # rerun DMD-Net only, reuse the rest
# only the new conditions on two meshes per set, keeping every other row of the report:
python benchmarks/quality/sota_lite.py --conditions scanner:0.5 scan:0.5 --max-meshes 2 \
    --reuse --merge
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
    write_csv,
    write_report,
)

# Re-exported: the report's tables and row layout have always been read from here.
from benchmarks.quality.sota_tables import (  # noqa: E402
    COL,
    CONDITIONS,
    CSV_HEADER,
    OLD_CSV_HEADER,
    REFERENCE,
    STRESS_CONDITIONS,
    _label,
    condition_label,  # noqa: F401 (re-exported)
    metric_means,
    per_shape_table,
    region_table,
    tables,
)
from dmd_jax import comparison, protocol  # noqa: E402
from dmd_jax.protocol import MAX_FACES, MESH_SUFFIXES  # noqa: E402

SETS = ("shared", "val", "stress")
DEFAULT_MESH_DIR = protocol.shared_meshes_dir()
# The fixed validation split of the real training meshes (dmd_jax.data.real).
DEFAULT_VAL_DIR = protocol.validation_dir()


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
    conditions=CONDITIONS,
    methods=None,
    *,
    mesh_set="shared",
    cached=None,
    max_faces: int = 0,
    echo=print,
) -> tuple[list[list], list[str]]:
    """Noise, denoise and score one mesh under every noise condition.

    Args:
      path: mesh file.
      bundle: the DMD-Net `ModelBundle`.
      conditions: `protocol.NoiseCondition`s (kind and level in mean edge lengths,
        along the vertex normals).
      methods: method ids (default `protocol.benchmark_methods()`).
      mesh_set: the set's name, the first CSV column.
      cached: `{(set, mesh, noise, level, seed, method): row}` of earlier rows to reuse
        instead of rerunning (classic methods are deterministic; DMD-Net rows are never
        cached; a CAD mesh's row without its crease/flat split is rerun).
      max_faces: crop a larger mesh to a connected patch of this many faces
        (`protocol.crop`); 0 keeps every mesh whole.
      echo: progress output.

    Returns:
      `(rows, notes)`: CSV rows in `CSV_HEADER` order (one per level and method, the
      noisy input first) and notes on the input (polygons triangulated on load).
    """
    from dmd_jax.io import load_mesh

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
    rows = evaluate_arrays(
        path.name,
        clean,
        faces,
        bundle,
        conditions,
        methods,
        mesh_set=mesh_set,
        cached=cached,
        echo=echo,
    )
    return rows, notes


def evaluate_arrays(
    mesh_name: str,
    clean,
    faces,
    bundle,
    conditions=CONDITIONS,
    methods=None,
    *,
    mesh_set="shared",
    cached=None,
    echo=print,
) -> list[list]:
    """`evaluate_mesh` for a mesh in memory (a generated stress shape, a crop).

    Each condition's clean mesh, noisy input and faces come from
    `protocol.condition_mesh` (a `scan` condition scores the scan's own triangulation
    against its ground truth, whose sizes, CAD flag and creases the rows then record).

    Returns:
      CSV rows in `CSV_HEADER` order, one per condition and method, the noisy input
      first.
    """
    from dmd_jax.metrics import face_normal_errors_deg, mesh_metrics

    methods = protocol.benchmark_methods() if methods is None else tuple(methods)
    cached = cached or {}
    clean = np.asarray(clean, np.float64)
    faces = np.asarray(faces)
    regions_of = {}  # per scored mesh: (cad, crease faces)
    rows = []
    for condition in conditions:
        level = condition.level
        seed = protocol.condition_seed(mesh_name, condition)
        target, noisy, tri = protocol.condition_mesh(clean, faces, condition, seed)
        which = condition if condition.kind == protocol.SCAN_KIND else None
        if which not in regions_of:
            regions_of[which] = (
                comparison.is_cad(target, tri),
                comparison.crease_faces(target, tri),
            )
        cad, crease = regions_of[which]
        block = []
        for name in ("noisy", *methods):
            key = (mesh_set, mesh_name, condition.kind, float(level), int(seed), name)
            hit = cached.get(key)
            if hit is not None and not name.startswith("dmd"):
                if not cad or np.isfinite(hit[COL["normal_crease_deg"]]):
                    block.append([*hit[: COL["cad"]], cad, *hit[COL["cad"] + 1 :]])
                    continue
            start = time.perf_counter()
            v = noisy if name == "noisy" else _runner(name, tri, bundle)(noisy)
            seconds = 0.0 if name == "noisy" else time.perf_counter() - start
            v = np.asarray(v, np.float64)
            m = mesh_metrics(v, target, tri)
            regions = comparison.region_errors(
                face_normal_errors_deg(v, target, tri, undefined=np.nan), crease
            )
            block.append(
                [
                    mesh_set,
                    mesh_name,
                    len(target),
                    len(tri),
                    float(level),
                    int(seed),
                    name,
                    m["normal_deg"],
                    m["vertex"],
                    m["chamfer"],
                    seconds,
                    condition.kind,
                    cad,
                    *regions,
                ]
            )
        rows += block
        errors = "  ".join(f"{_label(r[6])} {r[7]:.2f}°" for r in block)
        echo(f"  {mesh_name} {condition.label}: {errors}")
    return rows


def _weights_description(bundle, weights) -> dict[str, str]:
    from dmd_jax.checkpoints import pretrained_path
    from dmd_jax.model import param_count

    path = pretrained_path() if weights is None else Path(weights)
    info = {
        "weights": ("bundled " if weights is None else "") + str(path),
        "model": f"preset {bundle.config.name}, {param_count(bundle.config.model):,} parameters",
        "policy": bundle.policy.describe("="),
    }
    if path.is_file():
        info["weights sha256"] = file_sha256(path, 16)
    for key, value in bundle.meta.items():
        info[f"weights meta: {key}"] = str(value)
    return info


def _case(row) -> tuple:
    """A row's case: set, mesh, noise kind and level (every method of it)."""
    return (row[COL["set"]], row[COL["mesh"]], row[COL["noise"]], float(row[COL["level"]]))


def read_cached(csv_path) -> dict[tuple, list]:
    """Rows of an earlier report, keyed `(set, mesh, noise, level, seed, method)`.

    Reports of the old layout (`OLD_CSV_HEADER`) give Gaussian rows without a
    crease/flat split (NaN), which `evaluate_mesh` reruns for CAD meshes.
    """
    import csv

    csv_path = Path(csv_path)
    if not csv_path.is_file():
        return {}
    out = {}
    with open(csv_path) as fh:
        for r in csv.DictReader(fh):
            if list(r) not in (list(CSV_HEADER), list(OLD_CSV_HEADER)):
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
                r.get("noise", "gaussian"),
                r.get("cad") == "True",
                float(r.get("normal_crease_deg", "nan") or "nan"),
                float(r.get("normal_flat_deg", "nan") or "nan"),
            ]
            out[(row[0], row[1], row[COL["noise"]], row[4], row[5], row[6])] = row
    return out


def run(
    mesh_dir=DEFAULT_MESH_DIR,
    *,
    val_dir=DEFAULT_VAL_DIR,
    weights=None,
    conditions=CONDITIONS,
    skip=(),
    only=(),
    methods=None,
    name: str = "sota_lite",
    out_dir=RESULTS_DIR,
    reuse: bool = False,
    reuse_from=(),
    sets=SETS,
    max_faces: int = MAX_FACES,
    stress_conditions=STRESS_CONDITIONS,
    max_meshes: int = 0,
    merge: bool = False,
    echo=print,
) -> tuple[Path, Path]:
    """Runs the comparison and writes `<out_dir>/<name>.md` and `.csv`.

    Args:
      mesh_dir: folder of test meshes (every file, set `shared`).
      val_dir: folder of real training meshes whose fixed validation split
        (`dmd_jax.data.real`) is the second set, `val`; None leaves it out.
      weights: DMD-Net weights (default: bundled).
      conditions: the noise conditions (`protocol.QUALITY_CONDITIONS`).
      skip: file names of `mesh_dir` to leave out.
      only: file names of `mesh_dir` to run, none other (empty: every file).
      methods: method ids (default `protocol.benchmark_methods()`).
      name, out_dir: report file stem and folder.
      reuse: take rows of classic methods from an existing `<name>.csv` (same mesh,
        level, seed and method) instead of recomputing them.
      reuse_from: more CSV files to take such rows from (e.g. the sets run separately).
      sets: which sets to run (`shared`, `val`, `stress`).
      max_faces: meshes above this many faces are cropped to a connected patch of it
        (`protocol.crop`); 0 runs whole meshes.
      stress_conditions: the conditions of the `stress` set (`STRESS_CONDITIONS`: clean
        and light Gaussian noise); `conditions` are the other sets'.
      max_meshes: run only the first this many meshes of each set (0: all), e.g. to
        check new conditions end to end.
      merge: keep in the report every row of the reused CSVs (`reuse`, `reuse_from`)
        whose case (set, mesh, condition) this run does not compute, so a run of a few
        conditions or sets updates a full report instead of replacing it.
    """
    from dmd_jax.baselines import REGISTRY
    from dmd_jax.checkpoints import load_model

    methods = protocol.benchmark_methods() if methods is None else tuple(methods)
    known = {*REFERENCE, *REGISTRY, "cnr", "dmd", "dmd_x2"}
    unknown = sorted(set(methods) - known)
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(known)}")
    unknown_sets = sorted(set(sets) - set(SETS))
    if unknown_sets or not sets:
        raise ValueError(f"unknown mesh sets {unknown_sets}; choose from {', '.join(SETS)}")
    if isinstance(max_meshes, bool) or int(max_meshes) != max_meshes or max_meshes < 0:
        raise ValueError(f"max_meshes must be an integer >= 0, got {max_meshes!r}")
    wanted, sets = sets, {}
    if "shared" in wanted:
        sets["shared"] = protocol.mesh_files(mesh_dir, skip)
        missing = sorted(set(only) - {p.name for p in sets["shared"]})
        if missing:
            raise ValueError(f"{mesh_dir}: no such mesh file(s) {missing} (--only)")
        sets["shared"] = [p for p in sets["shared"] if not only or p.name in only]
        if not sets["shared"]:
            raise ValueError(f"{mesh_dir}: no {', '.join(MESH_SUFFIXES)} files")
    if val_dir is not None and "val" in wanted:
        sets["val"] = protocol.validation_files(val_dir)
    if "stress" in wanted:
        from dmd_jax.data.stress import STRESS_SHAPES

        sets["stress"] = list(STRESS_SHAPES)
    if not sets:
        raise ValueError("no mesh set to run (--no-val with --sets val)")
    if max_meshes:
        sets = {k: files[: int(max_meshes)] for k, files in sets.items()}
    bundle = load_model(weights)
    env = environment(
        packages=("dmd_jax", "jax", "jaxlib", "flax", "numpy", "pymeshlab", "trimesh")
    )
    env.update(_weights_description(bundle, weights))
    out_dir = Path(out_dir)
    cached = {}
    for csv_file in ([out_dir / f"{name}.csv"] if reuse else []) + [Path(p) for p in reuse_from]:
        cached.update(read_cached(csv_file))
    earlier = list(cached.values())  # the reused reports' rows, for `merge`
    start = time.perf_counter()
    rows, notes = [], []
    total = sum(len(files) for files in sets.values())
    i = 0
    for mesh_set, files in sets.items():
        for path in files:
            i += 1
            if mesh_set == "stress":
                from dmd_jax.data.stress import stress_shape

                echo(f"[{i}/{total}] {mesh_set}: {path}")
                rows += evaluate_arrays(
                    path,
                    *stress_shape(path),
                    bundle,
                    stress_conditions,
                    methods,
                    mesh_set=mesh_set,
                    cached=cached,
                    echo=echo,
                )
                continue
            echo(f"[{i}/{total}] {mesh_set}: {path.name}")
            mesh_rows, mesh_notes = evaluate_mesh(
                path,
                bundle,
                conditions,
                methods,
                mesh_set=mesh_set,
                cached=cached,
                max_faces=max_faces,
                echo=echo,
            )
            rows += mesh_rows
            notes += mesh_notes
    if merge:
        done = {_case(r) for r in rows}
        kept = [r for r in earlier if _case(r) not in done]
        echo(f"kept {len(kept)} rows of the reused reports (cases not rerun)")
        rows = kept + rows
    env["wall time"] = f"{time.perf_counter() - start:.0f} s" + (
        " (classic rows reused from the previous report)" if cached else ""
    )
    detail, means, timing = tables(rows)
    shapes, regions = per_shape_table(rows), region_table(rows)
    csv_path = write_csv(out_dir / f"{name}.csv", CSV_HEADER, rows)
    intro = (
        "normal (°): mean angle between corresponding face normals (lower is better) after "
        "noise along the vertex normals in units of the mesh's mean edge length: Gaussian "
        "of σ = 0.1, 0.2, 0.3 (the benchmark protocol of CNR and GCN-Denoiser) and 0.6, "
        "and impulsive (`impulse 0.6`: 15 % of the vertices moved out by 0.6 edges, 15 % "
        "in; `dmd_jax.protocol.QUALITY_CONDITIONS`); scanner noise (`scanner L`: rms L "
        "edges along one view drawn from the seed, spatially correlated, grown at grazing "
        "angles, quantised in depth: `dmd_jax.noise.ScannerModel`); simulated depth scans "
        f"(`scan L`: `dmd_jax.simulate_scan` at {protocol.SCAN_RESOLUTION}² from a view "
        "drawn from the seed, depth noise of rms L of the scan's mean edges; every method "
        "denoises the range-image mesh, scored against its exact ground truth; `faces` is "
        "the scan's); `clean` (no noise: do no harm). Sets: `shared` = every file of "
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
        + "; `stress` = the generated CAD shapes of `dmd_jax.data.stress` (pyramid, cube, "
        "star prism, sharp cone, fan disc of valence 100, cylinder, chamfered box, thin "
        "plate), clean and at Gaussian 0.1 along the normals"
        + ". `best` names the library denoiser with the lowest error; MeshLab Taubin and "
        "two-step are pymeshlab's filters (`dmd_jax.baselines.meshlab.PYMESHLAB_FILTERS`), "
        "shown as a reference and never counted as best; every other column is "
        "`dmd_jax.baselines` "
        "with its defaults (CNR with its bundled weights). `DMD-Net margin` = DMD-Net "
        "minus the best other library denoiser (negative: DMD-Net wins). Noise seeds: "
        "CRC32 of `<file>|<σ>` (impulsive: `<file>|impulse|<level>`; column `seed` of the "
        "CSV, which also holds vertex and chamfer errors, run times and the crease/flat "
        "split). Per shape: DMD-Net's error over the best other library denoiser's, per "
        "mesh (`dmd_jax.comparison`): geometric mean and the worst ratio with its mesh "
        f"(errors below {comparison.RATIO_FLOOR_DEG:g}° count as {comparison.RATIO_FLOOR_DEG:g}°, "
        "so a clean mesh every method leaves alone rates 1). Crease faces: faces with an "
        "edge whose dihedral "
        f"angle is at least {comparison.CREASE_ANGLE:g}° on the clean mesh; CAD meshes: "
        f"at least {comparison.CAD_MIN_FLAT_SHARE:.0%} of the edges flat (within "
        f"{comparison.FLAT_ANGLE:g}°) and {comparison.CAD_MIN_CREASE_SHARE:.1%} on creases."
    )
    sections = [
        ("Means over meshes", means),
        ("Per shape: DMD-Net against the best other library denoiser", shapes),
        ("CAD meshes: crease faces and flat faces", regions),
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
    parser.add_argument(
        "--conditions",
        nargs="+",
        default=[c.label for c in CONDITIONS],
        metavar="CONDITION",
        help="noise conditions of the shared and val sets: a number is Gaussian σ along "
        "the normals in mean edges, 'impulse:L' impulsive noise of amplitude L mean edges, "
        "'scanner:L' scanner noise of rms L edges, 'scan:L' a simulated scan at rms L, "
        "'clean' no noise",
    )
    parser.add_argument(
        "--stress-conditions",
        nargs="+",
        default=[c.label for c in STRESS_CONDITIONS],
        metavar="CONDITION",
        help="noise conditions of the stress set (default: clean and 0.1)",
    )
    parser.add_argument(
        "--levels",
        type=float,
        nargs="+",
        default=None,
        help="Gaussian levels only (the benchmark's own conditions), instead of --conditions",
    )
    parser.add_argument("--skip", nargs="*", default=[], help="file names to leave out")
    parser.add_argument("--only", nargs="+", default=[], help="file names to run, none other")
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
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    parser.add_argument(
        "--max-meshes",
        type=int,
        default=0,
        help="only the first N meshes of each set (0: all), to check conditions end to end",
    )
    parser.add_argument(
        "--merge",
        action="store_true",
        help="keep the reused reports' rows of every case this run does not compute "
        "(with --reuse / --reuse-from: run a few conditions or sets into a full report)",
    )
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
            conditions=(
                tuple(protocol.parse_condition(c) for c in args.conditions)
                if args.levels is None
                else tuple(protocol.NoiseCondition(protocol.NOISE_KIND, lv) for lv in args.levels)
            ),
            skip=tuple(args.skip),
            only=tuple(args.only),
            methods=None if args.methods is None else tuple(args.methods),
            name=args.name,
            out_dir=args.out_dir,
            reuse=args.reuse,
            reuse_from=tuple(args.reuse_from),
            sets=tuple(args.sets),
            max_faces=args.max_faces,
            stress_conditions=tuple(protocol.parse_condition(c) for c in args.stress_conditions),
            max_meshes=args.max_meshes,
            merge=args.merge,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"sota_lite: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
