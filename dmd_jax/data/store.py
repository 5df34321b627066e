"""The on-disk dataset format: records, manifest, splits, mesh files, reading.

On-disk layout (no pickle anywhere; every array file reads with `allow_pickle=False`)::

    DIR/manifest.json                       what is there, how it was made, the splits
    DIR/meshes/<category>/<id>.npz          vertices float32 [n, 3], faces int32 [f, 3]

The manifest is written last, atomically: a directory without one is an unfinished run.

Splits follow the paper's protocol (section 4): whole *test-inter* categories are held out;
every other category is split by instance into *train* and *test-intra* (80/20 by
default). The instances that go to test-intra are a deterministic function of
`(seed, category name)` and the number of instances, independent of any worker order.

The writers are `dmd_jax.data.dataset` (procedural shapes) and `dmd_jax.data.folders`
(folders of mesh files); `dmd_jax.data.dataset` re-exports the public names defined here.
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import json
import multiprocessing
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from dmd_jax.data.shapes import (
    category_key,
)
from dmd_jax.io import atomic_write
from dmd_jax.mesh import validate_mesh

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


def _finish_dataset(
    out_dir: Path, manifest: dict, *, wall: float, results, meshes: list, skipped: list
) -> Dataset:
    """What every builder ends with: the manifest completed with the software versions,
    the timing (`wall` seconds; each job result's `cpu_seconds`), the meshes and the
    skipped entries, written last, and the dataset loaded back."""
    cpu = [r["cpu_seconds"] for r in results if "cpu_seconds" in r]
    manifest = {
        **manifest,
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
