"""Mesh datasets on disk: procedural generation, and the one entry point of both writers.

The format itself (records, manifest, splits, reading) is `dmd_jax.data.store`; folders of
mesh files are `dmd_jax.data.folders`. Their public names are re-exported here, where they
have always been imported from.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

# Re-exported: the format's and the folders' names have always been read from here.
from dmd_jax.data.folders import (
    convert_folder,
    load_mesh_folder,  # noqa: F401 (re-exported)
    process_mesh,  # noqa: F401 (re-exported)
)
from dmd_jax.data.shapes import (
    CATEGORIES,
    GENERATOR_VERSION,
    generate_shape,
)
from dmd_jax.data.store import (
    DEFAULT_TEST_INTER,
    MANIFEST_FORMAT,
    MANIFEST_NAME,  # noqa: F401 (re-exported)
    MANIFEST_VERSION,
    SPLITS,  # noqa: F401 (re-exported)
    Dataset,
    MeshRecord,  # noqa: F401 (re-exported)
    _assign_splits,
    _check_test_inter,
    _digest,
    _finish_dataset,
    _prepare_out_dir,
    _run_jobs,
    _write_npz,
    intra_test_indices,  # noqa: F401 (re-exported)
    load_dataset,  # noqa: F401 (re-exported)
)


def _generate_job(
    out_dir: str, category: str, seed: int, instance: int, min_v: int, max_v: int
) -> dict:
    """Worker: one procedural shape to one npz file."""
    start = time.process_time()
    rel = f"meshes/{category}/{category}_{instance:05d}.npz"
    try:
        v, f = generate_shape(category, seed, instance, min_vertices=min_v, max_vertices=max_v)
    except Exception as exc:  # one odd shape must not end a long run; it is reported
        return {"error": f"{type(exc).__name__}: {exc}"}
    v32, f32 = v.astype(np.float32), f.astype(np.int32)
    _write_npz(Path(out_dir) / rel, v32, f32)
    return {
        "file": rel,
        "n_vertex": int(v.shape[0]),
        "n_face": int(f.shape[0]),
        "sha256": _digest(v32, f32),
        "cpu_seconds": time.process_time() - start,
    }


# --------------------------------------------------------------------------------------
# Procedural datasets
# --------------------------------------------------------------------------------------


def make_dataset(
    out_dir,
    *,
    per_category: int,
    seed: int = 0,
    categories: Sequence[str] | None = None,
    test_inter: Sequence[str] = DEFAULT_TEST_INTER,
    intra_fraction: float = 0.2,
    workers: int | None = None,
    min_vertices: int = 1000,
    max_vertices: int = 6000,
    progress: bool = True,
    overwrite: bool = False,
) -> Dataset:
    """Generates `per_category` procedural shapes of every category into `out_dir`.

    Args:
      out_dir: target directory; created if missing, must be empty unless `overwrite`.
      per_category: instances per category (instance numbers `0 .. per_category - 1`).
      seed: dataset seed; shapes and splits are pure functions of it.
      categories: which categories (default: all of `CATEGORIES`, in that order).
      test_inter: categories held out whole as test-inter.
      intra_fraction: share of each remaining category's instances in test-intra.
      workers: processes (default `os.cpu_count()`; 1 runs in this process). Workers
        are spawned, so a script calling this with `workers > 1` needs the usual
        `if __name__ == "__main__":` guard.
      min_vertices, max_vertices: vertex range of every mesh.
      progress: show a tqdm progress bar.
      overwrite: allow a non-empty `out_dir` (the files of a previous dataset there,
        as listed by its manifest, are removed first; nothing else is touched).

    A shape that cannot be generated (see `generate_shape`) is left out with a warning
    and listed under `"skipped"` in the manifest.

    Returns:
      The written dataset, as `load_dataset(out_dir)` would read it.

    Raises:
      ValueError: bad arguments (unknown or too many held-out categories, ranges).
      FileExistsError: `out_dir` is not empty and `overwrite` is false.
    """
    categories = tuple(CATEGORIES if categories is None else categories)
    unknown = [c for c in categories if c not in CATEGORIES]
    if unknown or not categories:
        raise ValueError(f"unknown categories {unknown}; known: {', '.join(CATEGORIES)}")
    if len(set(categories)) != len(categories):
        raise ValueError(f"categories repeat: {list(categories)}")
    test_inter = _check_test_inter(test_inter, categories)
    if int(per_category) != per_category or per_category < 1:
        raise ValueError(f"per_category must be a positive integer, got {per_category}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    if not 4 <= min_vertices <= max_vertices:
        raise ValueError(
            f"need 4 <= min_vertices <= max_vertices, got {min_vertices}, {max_vertices}"
        )
    if not 0.0 <= intra_fraction < 1.0:
        raise ValueError(f"intra_fraction must lie in [0, 1), got {intra_fraction}")
    out_dir = Path(out_dir)
    _prepare_out_dir(out_dir, overwrite)

    items = {c: list(range(per_category)) for c in categories}
    splits = _assign_splits(items, test_inter=test_inter, seed=seed, intra_fraction=intra_fraction)
    # Instance-major order spreads every category over the run (even progress, early
    # failures surface early); results are re-sorted into category order below.
    order = [(c, i) for i in range(per_category) for c in categories]
    jobs = [(str(out_dir), c, int(seed), i, int(min_vertices), int(max_vertices)) for c, i in order]
    start = time.perf_counter()
    results = dict(
        zip(
            order,
            _run_jobs(_generate_job, jobs, workers=workers, progress=progress, desc="make-dataset"),
            strict=True,
        )
    )
    wall = time.perf_counter() - start

    meshes, skipped = [], []
    for c in categories:
        for i in range(per_category):
            res = results[(c, i)]
            entry_id = f"{c}/{c}_{i:05d}"
            if "error" in res:
                skipped.append({"id": entry_id, "error": res["error"]})
                continue
            meshes.append(
                {
                    "id": entry_id,
                    "category": c,
                    "instance": i,
                    "split": splits[(c, i)],
                    "n_vertex": res["n_vertex"],
                    "n_face": res["n_face"],
                    "file": res["file"],
                    "sha256": res["sha256"],
                }
            )
    if skipped:
        warnings.warn(f"{len(skipped)} shapes could not be generated: {skipped[:3]}", stacklevel=2)
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "source": "procedural",
        "seed": int(seed),
        "generator": {
            "version": GENERATOR_VERSION,
            "categories": list(categories),
            "per_category": int(per_category),
            "min_vertices": int(min_vertices),
            "max_vertices": int(max_vertices),
        },
        "test_inter": list(test_inter),
        "intra_fraction": float(intra_fraction),
    }
    return _finish_dataset(
        out_dir, manifest, wall=wall, results=results.values(), meshes=meshes, skipped=skipped
    )


def build_dataset(
    out_dir,
    *,
    from_folder=None,
    per_category: int | None = None,
    categories: Sequence[str] | None = None,
    test_inter: Sequence[str] | None = None,
    remesh: bool = False,
    **common,
) -> Dataset:
    """`dmd-jax make-dataset`: procedural shapes (`make_dataset`) or a converted mesh
    folder (`convert_folder`), whichever the arguments name.

    Args:
      out_dir: the dataset directory to write.
      from_folder: a `category/*.obj|off|ply` folder to convert; None: procedural.
      per_category: procedural shapes per category (required without `from_folder`).
      categories: procedural categories (None or empty: all).
      test_inter: categories held out whole; None: `DEFAULT_TEST_INTER` for procedural
        data, none for a folder; `()` holds out nothing.
      remesh: remesh folder meshes into the vertex range.
      **common: `seed`, `intra_fraction`, `workers`, `min_vertices`, `max_vertices`,
        `progress`, `overwrite` of both writers.

    Raises:
      ValueError: procedural-only arguments with `from_folder`, or no `per_category`
        without it.
    """
    if from_folder:
        if per_category is not None or categories:
            raise ValueError(
                "--per-category and --categories apply to procedural data, not --from-folder"
            )
        return convert_folder(from_folder, out_dir, test_inter=test_inter, remesh=remesh, **common)
    if per_category is None:
        raise ValueError("--per-category is required (or give --from-folder)")
    return make_dataset(
        out_dir,
        per_category=per_category,
        categories=categories or None,
        test_inter=DEFAULT_TEST_INTER if test_inter is None else test_inter,
        **common,
    )
