"""Mesh datasets on disk: procedural generation, folder conversion, manifest, splits.

On-disk layout (no pickle anywhere; every array file reads with `allow_pickle=False`)::

    DIR/manifest.json                       what is there, how it was made, the splits
    DIR/meshes/<category>/<id>.npz          vertices float32 [n, 3], faces int32 [f, 3]

The manifest is written last, atomically: a directory without one is an unfinished run.

Splits follow the paper's protocol (section 4): whole *test-inter* categories are held out;
every other category is split by instance into *train* and *test-intra* (80/20 by
default). The instances that go to test-intra are a deterministic function of
`(seed, category name)` and the number of instances, independent of any worker order.
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import json
import multiprocessing
import os
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from dmd_jax.data.shapes import (
    CATEGORIES,
    GENERATOR_VERSION,
    category_key,
    clean_mesh,
    generate_shape,
    remesh,
)
from dmd_jax.io import SUPPORTED_EXTENSIONS, atomic_write, load_mesh
from dmd_jax.mesh import canonical_frame, validate_mesh

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "dmd_jax-mesh-dataset"
MANIFEST_VERSION = 1
SPLITS = ("train", "test_intra", "test_inter")
DEFAULT_TEST_INTER = ("fastener", "bottle", "metaballs")
_SPLIT_STREAM = 0x5B117  # keeps split draws apart from shape draws of the same seed


# --------------------------------------------------------------------------------------
# Records and datasets
# --------------------------------------------------------------------------------------


class MeshRecord:
    """One mesh of a dataset; its arrays are read (or built) when asked for, not kept.

    Attributes:
      id: unique id, `"<category>/<instance id>"`.
      category: category name.
      instance: instance id within the category (an int for procedural shapes, the file or
        folder name for mesh folders).
      split: `"train"`, `"test_intra"` or `"test_inter"`.
      n_vertex, n_face: sizes when known without loading (stored datasets), else `None`.
      source: the file the arrays come from.
    """

    __slots__ = ("id", "category", "instance", "split", "n_vertex", "n_face", "source", "_loader")

    def __init__(self, id, category, instance, split, n_vertex, n_face, source, loader):
        self.id = id
        self.category = category
        self.instance = instance
        self.split = split
        self.n_vertex = n_vertex
        self.n_face = n_face
        self.source = source
        self._loader = loader

    def load(self) -> tuple[np.ndarray, np.ndarray]:
        """`(vertices float64 [n, 3], faces int32 [f, 3])`, read afresh on every call."""
        return self._loader()

    @property
    def vertices(self) -> np.ndarray:
        """`[n, 3]` float64 (reads the file; use `load()` to get both arrays at once)."""
        return self.load()[0]

    @property
    def faces(self) -> np.ndarray:
        """`[f, 3]` int32 (reads the file; use `load()` to get both arrays at once)."""
        return self.load()[1]

    def __repr__(self) -> str:
        return (
            f"MeshRecord(id={self.id!r}, split={self.split!r}, n_vertex={self.n_vertex}, "
            f"n_face={self.n_face})"
        )


class Dataset:
    """An indexed collection of `MeshRecord`s with train / test-intra / test-inter splits.

    Attributes:
      root: the dataset directory (stored datasets) or mesh folder.
      manifest: the manifest dictionary (for mesh folders, an equivalent built in memory).
      records: every record, in manifest order (category order, then instance).
    """

    def __init__(self, root: Path, manifest: dict, records: Sequence[MeshRecord]):
        self.root = Path(root)
        self.manifest = manifest
        self.records = tuple(records)

    def __len__(self) -> int:
        return len(self.records)

    @property
    def categories(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(r.category for r in self.records))

    @property
    def test_inter_categories(self) -> tuple[str, ...]:
        return tuple(self.manifest.get("test_inter", ()))

    def split(self, name: str) -> list[MeshRecord]:
        """The records of one split: `"train"`, `"test_intra"` or `"test_inter"`."""
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r}; use one of {', '.join(SPLITS)}")
        return [r for r in self.records if r.split == name]

    def arrays(self, name: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """All `(vertices, faces)` pairs of a split, loaded now (for `make_examples`)."""
        return [r.load() for r in self.split(name)]

    def counts(self) -> dict[str, int]:
        """Number of meshes per split."""
        return {s: sum(r.split == s for r in self.records) for s in SPLITS}

    def verify(self) -> list[str]:
        """Re-hashes every stored file; returns the ids whose arrays changed or are unreadable."""
        bad = []
        by_id = {m["id"]: m for m in self.manifest.get("meshes", [])}
        for r in self.records:
            expected = by_id.get(r.id, {}).get("sha256")
            if expected is None:
                continue
            try:
                v, f = _read_npz(r.source)
            except (OSError, ValueError):
                bad.append(r.id)
                continue
            if _digest(v, f) != expected:
                bad.append(r.id)
        return bad

    def __repr__(self) -> str:
        c = self.counts()
        return (
            f"Dataset({str(self.root)!r}, {len(self.categories)} categories, "
            f"train={c['train']}, test_intra={c['test_intra']}, test_inter={c['test_inter']})"
        )


# --------------------------------------------------------------------------------------
# Splits
# --------------------------------------------------------------------------------------


def intra_test_indices(
    n_instance: int, *, category: str, seed: int, intra_fraction: float
) -> set[int]:
    """Which of `n_instance` instances of a category go to test-intra.

    `round(intra_fraction * n_instance)` indices (at least one when `intra_fraction > 0`
    and there are two instances or more, so small datasets still have a test-intra set)
    drawn without replacement from a generator seeded by `(seed, crc32(category))`: the
    same on any machine and in any worker order.
    """
    if not 0.0 <= intra_fraction < 1.0:
        raise ValueError(f"intra_fraction must lie in [0, 1), got {intra_fraction}")
    n_test = int(round(intra_fraction * n_instance))
    if intra_fraction > 0 and n_instance >= 2:
        n_test = max(n_test, 1)
    rng = np.random.default_rng([int(seed), _SPLIT_STREAM, category_key(category)])
    return {int(i) for i in rng.permutation(n_instance)[:n_test]}


def _assign_splits(
    items: dict[str, list], *, test_inter: Iterable[str], seed: int, intra_fraction: float
) -> dict[tuple[str, int], str]:
    """Split of every `(category, index)` for per-category item lists."""
    test_inter = set(test_inter)
    out = {}
    for cat, lst in items.items():
        test = intra_test_indices(len(lst), category=cat, seed=seed, intra_fraction=intra_fraction)
        for i in range(len(lst)):
            if cat in test_inter:
                out[(cat, i)] = "test_inter"
            else:
                out[(cat, i)] = "test_intra" if i in test else "train"
    return out


def _check_test_inter(test_inter, categories: Sequence[str]) -> tuple[str, ...]:
    test_inter = tuple(dict.fromkeys(test_inter or ()))
    unknown = [c for c in test_inter if c not in categories]
    if unknown:
        raise ValueError(
            f"test-inter categories {unknown} are not among the categories: {', '.join(categories)}"
        )
    if len(test_inter) >= len(categories):
        raise ValueError("test-inter holds out every category; nothing would be left to train on")
    return test_inter


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def _digest(vertices: np.ndarray, faces: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i4").tobytes())
    return h.hexdigest()


def _write_npz(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.ascontiguousarray(faces, dtype="<i4")

    def write(tmp):
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, vertices=v, faces=f)

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write, overwrite=True)


def _read_npz(path) -> tuple[np.ndarray, np.ndarray]:
    """Raw stored arrays `(vertices float32, faces int32)` of one mesh file."""
    with np.load(path, allow_pickle=False) as data:
        missing = {"vertices", "faces"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: mesh file lacks arrays {sorted(missing)}")
        return data["vertices"], data["faces"]


def _load_stored(path: str) -> tuple[np.ndarray, np.ndarray]:
    v, f = _read_npz(path)
    return validate_mesh(v, f, name=str(path))


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Refuses a non-empty directory unless `overwrite`; then removes the old dataset's files."""
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"{out_dir}: exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{out_dir}: directory is not empty (pass --overwrite / overwrite=True)"
            )
        old = out_dir / MANIFEST_NAME
        if old.is_file():
            try:
                entries = json.loads(old.read_text()).get("meshes", [])
            except (ValueError, AttributeError):
                entries = []
            root = out_dir.resolve()
            for m in entries:
                p = (out_dir / str(m.get("file", ""))).resolve()
                # Only files of the old dataset, inside the directory, are removed.
                if p.is_file() and root in p.parents and p.suffix == ".npz":
                    p.unlink()
            old.unlink()
    out_dir.mkdir(parents=True, exist_ok=True)


def _software_versions() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for name in ("numpy", "scipy", "pymeshlab", "manifold3d", "trimesh", "scikit-image"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    text = json.dumps(manifest, indent=1, sort_keys=False) + "\n"

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(out_dir / MANIFEST_NAME, write, overwrite=True)


# --------------------------------------------------------------------------------------
# Parallel jobs
# --------------------------------------------------------------------------------------


def _run_jobs(
    fn: Callable[..., dict],
    jobs: Sequence[tuple],
    *,
    workers: int | None,
    progress: bool,
    desc: str,
) -> list[dict]:
    """Runs `fn(*job)` for every job, in a process pool when `workers > 1`.

    Results come back in job order whatever order the workers finish in. Processes are
    spawned, not forked, so a parent that already started JAX's threads is safe.
    """
    from tqdm.auto import tqdm

    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    workers = min(workers, max(len(jobs), 1))
    results: list[dict | None] = [None] * len(jobs)
    with tqdm(total=len(jobs), desc=desc, unit="mesh", disable=not progress) as bar:
        if workers == 1:
            for i, job in enumerate(jobs):
                results[i] = fn(*job)
                bar.update(1)
        else:
            ctx = multiprocessing.get_context("spawn")
            with concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx) as pool:
                futures = {pool.submit(fn, *job): i for i, job in enumerate(jobs)}
                try:
                    for fut in concurrent.futures.as_completed(futures):
                        results[futures[fut]] = fut.result()
                        bar.update(1)
                except BaseException:
                    for fut in futures:
                        fut.cancel()
                    raise
    return results  # type: ignore[return-value]


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
    cpu = [r["cpu_seconds"] for r in results.values() if "cpu_seconds" in r]
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
        "software": _software_versions(),
        "timing": {
            "wall_seconds": round(wall, 2),
            "cpu_seconds_total": round(float(np.sum(cpu)), 2),
        },
        "meshes": meshes,
        "skipped": skipped,
    }
    _write_manifest(out_dir, manifest)
    return load_dataset(out_dir)


# --------------------------------------------------------------------------------------
# Reading stored datasets
# --------------------------------------------------------------------------------------

_ENTRY_KEYS = {
    "id": str,
    "category": str,
    "split": str,
    "n_vertex": int,
    "n_face": int,
    "file": str,
}


def load_dataset(root) -> Dataset:
    """Reads a dataset written by `make_dataset` or `convert_folder` (arrays load lazily).

    Raises:
      FileNotFoundError: no directory, no manifest (an unfinished run), or a listed mesh
        file is missing.
      ValueError: the manifest is not valid JSON, is of another format or version, or an
        entry is malformed.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such dataset directory")
    path = root / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: missing; not a dataset written by make_dataset, or an unfinished run"
        )
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{path}: not a {MANIFEST_FORMAT} manifest")
    version = manifest.get("version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise ValueError(f"{path}: manifest version must be an integer, got {version!r}")
    if version != MANIFEST_VERSION:
        raise ValueError(
            f"{path}: manifest version {version}; this dmd_jax reads version {MANIFEST_VERSION} "
            "(regenerate the dataset with `dmd-jax make-dataset`)"
        )
    entries = manifest.get("meshes")
    if not isinstance(entries, list):
        raise ValueError(f"{path}: 'meshes' must be a list")
    records, seen = [], set()
    for k, m in enumerate(entries):
        if not isinstance(m, dict):
            raise ValueError(f"{path}: mesh entry {k} is not an object")
        for key, typ in _ENTRY_KEYS.items():
            if not isinstance(m.get(key), typ) or isinstance(m.get(key), bool):
                raise ValueError(f"{path}: mesh entry {k} has no valid {key!r} ({typ.__name__})")
        if m["split"] not in SPLITS:
            raise ValueError(f"{path}: mesh {m['id']!r} has unknown split {m['split']!r}")
        if m["id"] in seen:
            raise ValueError(f"{path}: mesh id {m['id']!r} appears twice")
        seen.add(m["id"])
        file = root / m["file"]
        if not file.is_file():
            raise FileNotFoundError(f"{file}: listed in the manifest but missing")
        records.append(
            MeshRecord(
                id=m["id"],
                category=m["category"],
                instance=m.get("instance"),
                split=m["split"],
                n_vertex=m["n_vertex"],
                n_face=m["n_face"],
                source=str(file),
                loader=functools.partial(_load_stored, str(file)),
            )
        )
    return Dataset(root, manifest, records)


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
    cpu = [r["cpu_seconds"] for r in results if "cpu_seconds" in r]
    manifest = dict(source.manifest)
    manifest.update(
        {
            "software": _software_versions(),
            "timing": {
                "wall_seconds": round(wall, 2),
                "cpu_seconds_total": round(float(np.sum(cpu)), 2),
            },
            "meshes": meshes,
            "skipped": skipped,
        }
    )
    _write_manifest(out_dir, manifest)
    return load_dataset(out_dir)


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
