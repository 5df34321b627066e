"""Folders of mesh files as datasets: indexed lazily, or converted to the on-disk format.

A folder is laid out as `category/*.obj|off|ply|stl` (ShapeNetCore's
`category/<id>/models/model_normalized.obj` included). `load_mesh_folder` indexes it
(each mesh is read, cleaned and optionally remeshed when loaded); `convert_folder`
writes it once in the format of `dmd_jax.data.store`, with the same splits.
`dmd_jax.data.dataset` re-exports the public names defined here.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dmd_jax.data.shapes import (
    category_key,
    clean_mesh,
    remesh,
)
from dmd_jax.data.store import (
    _SPLIT_STREAM,
    MANIFEST_FORMAT,
    MANIFEST_VERSION,
    Dataset,
    MeshRecord,
    _assign_splits,
    _check_test_inter,
    _digest,
    _finish_dataset,
    _prepare_out_dir,
    _run_jobs,
    _write_npz,
)
from dmd_jax.io import SUPPORTED_EXTENSIONS, load_mesh
from dmd_jax.mesh import canonical_frame

# --------------------------------------------------------------------------------------
# Folders of meshes (ShapeNetCore layout included)
# --------------------------------------------------------------------------------------

_SHAPENET_NAMES = ("model_normalized", "model")


def _scan_category(cat_dir: Path) -> list[tuple[str, Path]]:
    """`(instance id, file)` pairs of one category directory, sorted by id.

    Flat files `cat/<name>.<ext>` give id `<name>`. Files nested below an instance folder
    (`cat/<id>/models/model_normalized.obj` in ShapeNetCore v2, `cat/<id>/model.obj` in
    v1) give id `<id>`; a folder holding several meshes and none of those names gives one
    instance per file, `<id>/<name>`.
    """
    flat, nested = [], {}
    for p in sorted(cat_dir.rglob("*")):
        if (
            not p.is_file()
            or p.suffix.lower() not in SUPPORTED_EXTENSIONS
            or p.name.startswith(".")
        ):
            continue
        rel = p.relative_to(cat_dir)
        if len(rel.parts) == 1:
            flat.append((p.stem, p))
        else:
            nested.setdefault(rel.parts[0], []).append(p)
    out = list(flat)
    for inst, files in nested.items():
        if len(files) == 1:
            out.append((inst, files[0]))
            continue
        preferred = [f for name in _SHAPENET_NAMES for f in files if f.stem == name]
        if preferred:
            out.append((inst, preferred[0]))
        else:
            out += [
                (f"{inst}/{f.relative_to(cat_dir / inst).with_suffix('').as_posix()}", f)
                for f in files
            ]
    ids = [i for i, _ in out]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ValueError(f"{cat_dir}: several files give the same instance ids {dup[:5]}")
    return sorted(out)


def process_mesh(
    vertices,
    faces,
    *,
    remesh_to: tuple[int, int] | None = None,
    seed: int = 0,
    key: str = "",
    normalize: bool = True,
    feature_angle: float = 30.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Cleans a mesh (and optionally remeshes it) the way datasets store meshes.

    Args:
      vertices: `[n, 3]`.
      faces: `[f, 3]`.
      remesh_to: `(min_vertices, max_vertices)` to remesh isotropically into, or `None`.
      seed, key: seed the target vertex count (drawn in the range) per mesh.
      normalize: map to the canonical frame (centred, longest side 1).
      feature_angle: crease angle kept by remeshing, degrees.

    Returns:
      `(vertices float64 [n', 3], faces int32 [f', 3])`.
    """
    from dmd_jax.data.shapes import _target_vertices

    v, f = clean_mesh(vertices, faces)
    if remesh_to is not None:
        lo, hi = remesh_to
        rng = np.random.default_rng([int(seed), _SPLIT_STREAM + 1, category_key(key)])
        v, f = remesh(
            v,
            f,
            min_vertices=lo,
            max_vertices=hi,
            target_vertices=_target_vertices(rng, lo, hi),
            feature_angle=feature_angle,
        )
    if normalize:
        v = canonical_frame(v).apply(v)
    return v, f


def _load_folder_mesh(path: str, remesh_to, seed: int, key: str, normalize: bool):
    v, f = load_mesh(path)
    try:
        return process_mesh(v, f, remesh_to=remesh_to, seed=seed, key=key, normalize=normalize)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


def load_mesh_folder(
    root,
    *,
    test_inter: Sequence[str] | None = None,
    seed: int = 0,
    intra_fraction: float = 0.2,
    remesh: bool = False,
    min_vertices: int = 1000,
    max_vertices: int = 6000,
    normalize: bool = True,
) -> Dataset:
    """Indexes a folder laid out as `category/*.obj|off|ply|stl` (or ShapeNetCore's layout).

    Files are read lazily: each `record.load()` reads the file with
    `dmd_jax.mesh.load_mesh`, cleans it (merges duplicate vertices, drops duplicate,
    zero-area and unreferenced elements), remeshes it into `[min_vertices, max_vertices]`
    when `remesh` is true, and maps it to the canonical frame when `normalize` is true.
    That work is redone on every load; for training, write the folder once with
    `convert_folder` (or `dmd-jax make-dataset --from-folder`) and use `load_dataset`.

    Args:
      root: the folder; each subdirectory is a category.
      test_inter: categories held out whole (default: none).
      seed: seeds the test-intra draw and remeshing targets.
      intra_fraction: share of every other category's instances in test-intra.
      remesh: remesh isotropically into the vertex range.
      min_vertices, max_vertices: the vertex range used when remeshing.
      normalize: centre and scale to the canonical frame.

    Raises:
      FileNotFoundError: `root` is not a directory.
      ValueError: no category holds a mesh file, unknown test-inter categories.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    items = {}
    for d in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        found = _scan_category(d)
        if found:
            items[d.name] = found
    if not items:
        raise ValueError(
            f"{root}: no mesh files found; expected category/<name>.obj|off|ply|stl or "
            "category/<id>/models/model_normalized.obj"
        )
    test_inter = _check_test_inter(test_inter, tuple(items))
    if remesh and not 4 <= min_vertices <= max_vertices:
        raise ValueError(
            f"need 4 <= min_vertices <= max_vertices, got {min_vertices}, {max_vertices}"
        )
    splits = _assign_splits(items, test_inter=test_inter, seed=seed, intra_fraction=intra_fraction)
    remesh_to = (int(min_vertices), int(max_vertices)) if remesh else None
    records = []
    for cat, found in items.items():
        for i, (inst, path) in enumerate(found):
            rid = f"{cat}/{inst}"
            records.append(
                MeshRecord(
                    id=rid,
                    category=cat,
                    instance=inst,
                    split=splits[(cat, i)],
                    n_vertex=None,
                    n_face=None,
                    source=str(path),
                    loader=functools.partial(
                        _load_folder_mesh, str(path), remesh_to, int(seed), rid, normalize
                    ),
                )
            )
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "source": "folder",
        "seed": int(seed),
        "folder": {
            "root": str(root),
            "remesh": bool(remesh),
            "min_vertices": int(min_vertices),
            "max_vertices": int(max_vertices),
            "normalize": bool(normalize),
        },
        "test_inter": list(test_inter),
        "intra_fraction": float(intra_fraction),
    }
    return Dataset(root, manifest, records)


def _convert_job(
    out_dir: str, rel: str, source: str, remesh_to, seed: int, key: str, normalize: bool
) -> dict:
    """Worker: one folder mesh, cleaned (and remeshed), to one npz file."""
    start = time.process_time()
    try:
        v, f = _load_folder_mesh(source, remesh_to, seed, key, normalize)
    except (ValueError, FileNotFoundError) as exc:
        return {"error": str(exc)}
    v32, f32 = v.astype(np.float32), f.astype(np.int32)
    _write_npz(Path(out_dir) / rel, v32, f32)
    return {
        "file": rel,
        "n_vertex": int(v.shape[0]),
        "n_face": int(f.shape[0]),
        "sha256": _digest(v32, f32),
        "cpu_seconds": time.process_time() - start,
    }


def _safe_name(text: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in text)


def convert_folder(
    root,
    out_dir,
    *,
    test_inter: Sequence[str] | None = None,
    seed: int = 0,
    intra_fraction: float = 0.2,
    remesh: bool = False,
    min_vertices: int = 1000,
    max_vertices: int = 6000,
    normalize: bool = True,
    workers: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> Dataset:
    """Writes a mesh folder (see `load_mesh_folder`) in the on-disk dataset format.

    Meshes that cannot be read or processed are skipped with a warning and listed under
    `"skipped"` in the manifest. Arguments as in `load_mesh_folder` and `make_dataset`.
    """
    source = load_mesh_folder(
        root,
        test_inter=test_inter,
        seed=seed,
        intra_fraction=intra_fraction,
        remesh=remesh,
        min_vertices=min_vertices,
        max_vertices=max_vertices,
        normalize=normalize,
    )
    out_dir = Path(out_dir)
    if (
        out_dir.resolve() == Path(root).resolve()
        or Path(root).resolve() in out_dir.resolve().parents
    ):
        raise ValueError(f"{out_dir}: the output must lie outside the input folder {root}")
    _prepare_out_dir(out_dir, overwrite)
    remesh_to = (int(min_vertices), int(max_vertices)) if remesh else None
    rels = [
        f"meshes/{_safe_name(r.category)}/{_safe_name(str(r.instance))}.npz" for r in source.records
    ]
    if len(set(rels)) != len(rels):
        raise ValueError("instance names collide after making them file-name safe")
    jobs = [
        (str(out_dir), rel, r.source, remesh_to, int(seed), r.id, normalize)
        for rel, r in zip(rels, source.records, strict=True)
    ]
    start = time.perf_counter()
    results = _run_jobs(_convert_job, jobs, workers=workers, progress=progress, desc="convert")
    wall = time.perf_counter() - start
    meshes, skipped = [], []
    for r, res in zip(source.records, results, strict=True):
        if "error" in res:
            skipped.append({"id": r.id, "error": res["error"]})
            continue
        meshes.append(
            {
                "id": r.id,
                "category": r.category,
                "instance": r.instance,
                "split": r.split,
                "n_vertex": res["n_vertex"],
                "n_face": res["n_face"],
                "file": res["file"],
                "sha256": res["sha256"],
                "source_file": Path(r.source).relative_to(Path(root)).as_posix(),
            }
        )
    if skipped:
        warnings.warn(f"{len(skipped)} meshes were skipped: {skipped[:3]}", stacklevel=2)
    return _finish_dataset(
        out_dir, source.manifest, wall=wall, results=results, meshes=meshes, skipped=skipped
    )
