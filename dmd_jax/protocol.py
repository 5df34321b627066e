"""The evaluation protocol: how every quality figure of the project is made.

One definition each, used by the quality scripts (`benchmarks/quality/`), the demo, the
notebooks and the tests:

* the benchmark noise (`benchmark_noise`, `NOISE_LEVELS`): Gaussian noise of σ = 0.1,
  0.2 and 0.3 × the mesh's mean edge length along the vertex normals, the protocol of
  CNR and GCN-Denoiser; `benchmark_noise_config` is the same noise as a `NoiseConfig`
  for the input pipeline (training's evaluation sets);
* its seeds (`noise_seed`): a CRC32 of `"<file name>|<level>"`, so a mesh's noise does
  not change when files are added or moved;
* the crop (`crop`, `MAX_FACES`): larger meshes shrink to the connected patch grown
  breadth-first from face 0, to keep the slowest classic filters within a CPU session;
* the mesh sets: the shared test meshes (`shared_meshes_dir`, `mesh_files`) and the
  fixed validation split of the real training meshes (`validation_dir`,
  `validation_files`; the split itself is `dmd_jax.data.real.is_validation`);
* the mesh suffixes the folders are read with (`MESH_SUFFIXES`, those `dmd_jax.io`
  reads);
* the methods and their display labels (`METHODS`, the names `dmd_jax.denoise_with`
  takes; `REFERENCE_METHODS`, pymeshlab's filters; `benchmark_methods`, `label`);
* the quality table's noise conditions (`NoiseCondition`, `condition_mesh`): the
  benchmark levels, heavier and impulsive noise (`QUALITY_CONDITIONS`), scanner noise
  (`SCANNER_CONDITIONS`), simulated depth scans (`SCAN_CONDITIONS`: the scan's own
  triangulation and ground truth), and the stress family's clean and lightly noised
  conditions (`STRESS_CONDITIONS`, on `dmd_jax.data.stress`'s shapes).

Host side: importing this module loads NumPy and no JAX (the noise imports JAX when it
is drawn).
"""

from __future__ import annotations

import os
import warnings
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

# `api` and `io` import only NumPy at module level, so this import stays light.
from dmd_jax.api import METHODS
from dmd_jax.io import SUPPORTED_EXTENSIONS as MESH_SUFFIXES

__all__ = [
    "LABELS",
    "MAX_FACES",
    "HEAVY_LEVEL",
    "IMPULSE_LEVEL",
    "MESH_SUFFIXES",
    "METHODS",
    "NOISE_DIRECTION",
    "NOISE_KIND",
    "NOISE_LEVELS",
    "NoiseCondition",
    "QUALITY_CONDITIONS",
    "SCANNER_CONDITIONS",
    "SCAN_CONDITIONS",
    "STRESS_CONDITIONS",
    "SCAN_RESOLUTION",
    "PAPER_LABELS",
    "REFERENCE_METHODS",
    "SHARED_MESHES_ENV",
    "benchmark_methods",
    "benchmark_noise",
    "benchmark_noise_config",
    "condition_mesh",
    "condition_noise",
    "condition_seed",
    "crop",
    "is_rival",
    "label",
    "mesh_files",
    "noise_seed",
    "parse_condition",
    "scan_view",
    "shared_meshes_dir",
    "validation_dir",
    "validation_files",
]

# The benchmark noise: Gaussian, σ in mean edge lengths, one draw per vertex along its
# vertex normal (CNR, GCN-Denoiser).
NOISE_KIND = "gaussian"
NOISE_DIRECTION = "normal"
NOISE_LEVELS = (0.1, 0.2, 0.3)

# Meshes above this many faces are cropped (`crop`): GNF and L0 take ~1 ms a face.
MAX_FACES = 15_000

# The folder of the project's shared test meshes (its `train/` holds the real training
# meshes). The old name still works, with a DeprecationWarning.
SHARED_MESHES_ENV = "DMD_JAX_SHARED_MESHES"
_DEPRECATED_SHARED_MESHES_ENV = "DMD_SHARED_MESHES"

# pymeshlab's filters (`dmd_jax.baselines.meshlab`): reference columns of the quality
# tables, not denoisers of this library (never counted as the best).
REFERENCE_METHODS = ("meshlab_taubin", "meshlab_two_step")


def is_rival(method: str) -> bool:
    """Whether DMD-Net is rated against `method` in the quality tables: a library
    denoiser, not the noisy input, MeshLab's references or DMD-Net itself (one pass or
    `dmd_x2`)."""
    return method not in ("noisy", "dmd", "dmd_x2", *REFERENCE_METHODS)


# Display labels of every method id (and of the noisy input) in reports and tables.
LABELS = {
    "noisy": "noisy",
    "meshlab_taubin": "MeshLab Taubin",
    "meshlab_two_step": "MeshLab two-step",
    "laplacian": "Laplacian",
    "taubin": "Taubin",
    "bmd": "BMD",
    "nifp": "NIFP",
    "fefp": "FEFP",
    "bnf": "BNF",
    "gnf": "GNF",
    "l0": "L0",
    "cnr": "CNR",
    "dmd": "DMD-Net",
    "dmd_x2": "DMD-Net ×2",
}
# The Table II runner's labels: the paper's column names (L0 minimisation is "L0M"
# there) and short MeshLab names for its wide table and figure.
PAPER_LABELS = {
    **LABELS,
    "noisy": "Noisy",
    "l0": "L0M",
    "meshlab_taubin": "ML Taubin",
    "meshlab_two_step": "ML two-step",
}


def label(method: str) -> str:
    """The display label of a method id (the id itself when it has none)."""
    return LABELS.get(method, method)


def benchmark_methods() -> tuple[str, ...]:
    """The methods of the quality table: MeshLab's two, every classic filter of
    `dmd_jax.baselines.REGISTRY`, CNR and DMD-Net, in table order."""
    from dmd_jax.baselines import REGISTRY

    return (*REFERENCE_METHODS, *REGISTRY, "cnr", "dmd")


def shared_meshes_dir() -> Path:
    """The shared test-mesh folder: `$DMD_JAX_SHARED_MESHES`, else `shared/meshes`
    beside the repository checkout (not part of the package).

    `$DMD_SHARED_MESHES`, the older name, is read when the new one is unset, with a
    `DeprecationWarning`.
    """
    folder = os.environ.get(SHARED_MESHES_ENV)
    if not folder and os.environ.get(_DEPRECATED_SHARED_MESHES_ENV):
        warnings.warn(
            f"{_DEPRECATED_SHARED_MESHES_ENV} is deprecated; set {SHARED_MESHES_ENV}",
            DeprecationWarning,
            stacklevel=2,
        )
        folder = os.environ[_DEPRECATED_SHARED_MESHES_ENV]
    if folder:
        return Path(folder)
    # dmd_jax/protocol.py -> the checkout -> its parent, which holds shared/.
    return Path(__file__).resolve().parents[2] / "shared" / "meshes"


def validation_dir() -> Path:
    """The folder of real training meshes whose validation split is the second set:
    `train/` of `shared_meshes_dir()`."""
    return shared_meshes_dir() / "train"


def noise_seed(mesh_name: str, level: float) -> int:
    """The noise seed of one mesh file and level: stable across folders and machines.

    Args:
      mesh_name: the file's base name, e.g. `"fandisk.off"`.
      level: σ in mean edge lengths.
    """
    return zlib.crc32(f"{mesh_name}|{level:g}".encode())


def benchmark_noise(
    vertices, faces, level: float, seed: int, direction: str = NOISE_DIRECTION
) -> np.ndarray:
    """`vertices` plus Gaussian noise of σ = `level` × mean edge length, in float64.

    By default one draw per vertex along its vertex normal (the benchmark protocol).
    The same draws as `dmd_jax.add_noise(seed, vertices, faces, "gaussian", level,
    units="edge", direction=direction)` and `dmd-jax add-noise --units edge --direction
    normal --seed SEED`: float32 unit draws from `jax.random`, so a seed gives the same
    noise whether or not JAX's float64 mode is on.

    Args:
      vertices: `[n_vertex, 3]` clean positions.
      faces: `[n_face, 3]` vertex indices.
      level: σ in mean edge lengths.
      seed: PRNG seed (`noise_seed` for a benchmark case).
      direction: `"normal"` (default) or `"isotropic"` (per coordinate).

    Returns:
      `[n_vertex, 3]` float64 noisy positions.
    """
    from dmd_jax.api import add_noise

    return add_noise(
        seed,
        np.asarray(vertices, np.float64),
        faces,
        NOISE_KIND,
        level,
        units="edge",
        direction=direction,
    )


def benchmark_noise_config():
    """The benchmark noise as a `NoiseConfig` for the input pipeline: every evaluation
    mesh of a training run gets one of `NOISE_LEVELS` along its normals (used to
    evaluate and to pick checkpoints, `train.train`)."""
    from dmd_jax.config import NoiseConfig

    return NoiseConfig(
        kinds=(NOISE_KIND,),
        edge_levels=NOISE_LEVELS,
        p_edge=1.0,
        p_normal=1.0 if NOISE_DIRECTION == "normal" else 0.0,
    )


def crop(vertices, faces, max_faces: int = MAX_FACES) -> tuple[np.ndarray, np.ndarray]:
    """The connected `max_faces`-face patch grown breadth-first from face 0, re-indexed.

    Deterministic, so every method and run sees the same patch; a mesh of at most
    `max_faces` faces, or any mesh when `max_faces` is 0, comes back as it is.

    Args:
      vertices: `[n_vertex, 3]` positions.
      faces: `[n_face, 3]` vertex indices.
      max_faces: the patch size; 0 keeps every mesh whole.

    Returns:
      `(vertices [m, 3], faces [k, 3])` with `k <= max_faces`.
    """
    from dmd_jax.data.real import patch_mesh

    if not max_faces or faces.shape[0] <= max_faces:
        return vertices, faces
    return patch_mesh(vertices, faces, 0, max_faces)


def mesh_files(folder=None, skip=()) -> list[Path]:
    """The mesh files (`MESH_SUFFIXES`) of a folder, sorted by name.

    Args:
      folder: the folder (default `shared_meshes_dir()`).
      skip: file names to leave out.

    Raises:
      FileNotFoundError: no such folder.
      ValueError: `skip` names a file that is not in the folder.
    """
    folder = shared_meshes_dir() if folder is None else Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(
            f"{folder}: no mesh folder (pass --meshes DIR or set {SHARED_MESHES_ENV})"
        )
    unknown = set(skip) - {p.name for p in folder.iterdir()}
    if unknown:
        raise ValueError(f"--skip names files not in {folder}: {', '.join(sorted(unknown))}")
    return sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in MESH_SUFFIXES and p.is_file() and p.name not in set(skip)
    )


def validation_files(folder=None) -> list[Path]:
    """The validation split of a folder of real training meshes, sorted by name.

    Args:
      folder: the folder (default `validation_dir()`); the split is fixed by file name
        (`dmd_jax.data.real.is_validation`), never trained on.
    """
    from dmd_jax.data.real import mesh_files as real_mesh_files

    return real_mesh_files(validation_dir() if folder is None else folder, "val")


# --------------------------------------------------------------------------------------
# The quality table's noise conditions: the benchmark levels, heavier noise and impulses.
# --------------------------------------------------------------------------------------

# Heavier noise than the benchmark's, where published learned denoisers are compared
# (GCN-Denoiser, ResGEM: up to 0.6 mean edges), and the paper's impulsive kind at the
# benchmark's edge scale along the normals: δ(0.15, 0.15), 15 % of the vertices moved
# out by the amplitude and 15 % in.
HEAVY_LEVEL = 0.6
IMPULSE_LEVEL = 0.6
IMPULSE_P = IMPULSE_Q = 0.15


# Scanner noise (issue 53, `dmd_jax.noise.ScannerModel`): along one view drawn from the
# seed, correlated over the surface, rms in mean edges. Measured on public depth-camera
# scans: 0.4-0.9; the three levels span it from below.
SCANNER_KIND = "scanner"
SCANNER_LEVELS = (0.3, 0.5, 0.8)
# Simulated depth scans (`dmd_jax.simulate_scan`): the mesh is replaced by its range-image
# mesh from one view, noise in depth of this rms in the scan's mean edges: 0.15 (a careful
# reconstruction, measured ~0.15: where every filter of the library made real meshes
# worse) and 0.5 (a depth camera). The resolution gives scans of a few thousand to ~12k
# vertices, the size of the benchmark's crops.
SCAN_KIND = "scan"
SCAN_LEVELS = (0.15, 0.5)
SCAN_RESOLUTION = 128
# The stress family (`dmd_jax.data.stress`): clean (do no harm) and light Gaussian noise
# along the normals (the benchmark's lightest level).
CLEAN_KIND = "clean"
STRESS_LEVEL = NOISE_LEVELS[0]
CONDITION_KINDS = (NOISE_KIND, "impulse", SCANNER_KIND, SCAN_KIND, CLEAN_KIND)


class NoiseCondition(NamedTuple):
    """One noise condition of the quality table: a kind and its level in mean edges.

    Kinds: `gaussian` (σ, along the vertex normals), `impulse` (amplitude, along the
    normals), `scanner` (rms along a view, `dmd_jax.noise`), `scan` (a simulated depth
    scan of the mesh at that rms, `condition_mesh`) and `clean` (level 0, no noise).
    """

    kind: str
    level: float

    @property
    def label(self) -> str:
        """`0.1` for Gaussian σ (the benchmark's own name for its levels), `impulse 0.6`,
        `scanner 0.5`, `scan 0.15`, `clean`."""
        if self.kind == CLEAN_KIND:
            return CLEAN_KIND
        return f"{self.level:g}" if self.kind == NOISE_KIND else f"{self.kind} {self.level:g}"


QUALITY_CONDITIONS = (
    *(NoiseCondition(NOISE_KIND, level) for level in (*NOISE_LEVELS, HEAVY_LEVEL)),
    NoiseCondition("impulse", IMPULSE_LEVEL),
)
SCANNER_CONDITIONS = tuple(NoiseCondition(SCANNER_KIND, level) for level in SCANNER_LEVELS)
SCAN_CONDITIONS = tuple(NoiseCondition(SCAN_KIND, level) for level in SCAN_LEVELS)
STRESS_CONDITIONS = (NoiseCondition(CLEAN_KIND, 0.0), NoiseCondition(NOISE_KIND, STRESS_LEVEL))


def parse_condition(text: str) -> NoiseCondition:
    """`"0.2"` (Gaussian σ), `"impulse:0.6"` / `"impulse 0.6"`, `"scanner:0.5"`,
    `"scan:0.15"` or `"clean"` as a `NoiseCondition`.

    Raises:
      ValueError: another kind, or a level that is not a positive number.
    """
    if str(text).strip() == CLEAN_KIND:
        return NoiseCondition(CLEAN_KIND, 0.0)
    kind, _, level = str(text).replace(" ", ":").rpartition(":")
    kind = kind or NOISE_KIND
    if kind not in CONDITION_KINDS or kind == CLEAN_KIND:
        raise ValueError(
            f"unknown noise condition {text!r}; write e.g. 0.2, impulse:0.6, scanner:0.5, "
            "scan:0.15 or clean"
        )
    try:
        value = float(level)
    except ValueError:
        raise ValueError(f"noise condition {text!r}: {level!r} is not a number") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"noise condition {text!r}: the level must be a positive number")
    return NoiseCondition(kind, value)


def condition_seed(mesh_name: str, condition: NoiseCondition) -> int:
    """The noise seed of one mesh and condition; a Gaussian one's is `noise_seed`'s."""
    if condition.kind == NOISE_KIND:
        return noise_seed(mesh_name, condition.level)
    return zlib.crc32(f"{mesh_name}|{condition.kind}|{condition.level:g}".encode())


def condition_noise(vertices, faces, condition: NoiseCondition, seed: int) -> np.ndarray:
    """`vertices` with the noise of `condition` (float64): along the vertex normals, along
    a view drawn from `seed` (scanner), or none (clean).

    Raises:
      ValueError: a `scan` condition, which changes the mesh: use `condition_mesh`.
    """
    if condition.kind == NOISE_KIND:
        return benchmark_noise(vertices, faces, condition.level, seed)
    from dmd_jax.api import add_noise

    if condition.kind == CLEAN_KIND:
        return np.array(vertices, np.float64)
    if condition.kind == SCAN_KIND:
        raise ValueError("a scan condition replaces the mesh: use protocol.condition_mesh")
    if condition.kind == SCANNER_KIND:
        return add_noise(
            seed,
            np.asarray(vertices, np.float64),
            faces,
            SCANNER_KIND,
            condition.level,
            units="edge",
        )

    return add_noise(
        seed,
        np.asarray(vertices, np.float64),
        faces,
        condition.kind,
        condition.level,
        units="edge",
        direction="normal",
        impulse_p=IMPULSE_P,
        impulse_q=IMPULSE_Q,
    )


def scan_view(vertices, faces, seed: int) -> np.ndarray:
    """The view of a `scan` condition: drawn from `seed`, turned to face an open mesh.

    A crop is an open patch that a view from behind or edge-on would barely see: the
    drawn view is turned to its front (`dmd_jax.scan.facing_view`); a closed mesh keeps
    any drawn view.
    """
    from dmd_jax.noise import random_view
    from dmd_jax.scan import facing_view

    return facing_view(random_view(np.random.default_rng([int(seed), 1])), vertices, faces)


def condition_mesh(
    vertices, faces, condition: NoiseCondition, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The `(clean, noisy, faces)` a method is scored on under `condition`.

    Every condition keeps the mesh except `scan`, which scans it
    (`dmd_jax.simulate_scan` from `scan_view`, `SCAN_RESOLUTION`, rms `condition.level`
    of the scan's mean edges): clean and noisy are then the scan's ground truth and its
    noisy vertices, on the scan's faces.
    """
    if condition.kind != SCAN_KIND:
        v = np.asarray(vertices, np.float64)
        return v, condition_noise(v, faces, condition, seed), np.asarray(faces)
    from dmd_jax.scan import simulate_scan

    scan = simulate_scan(
        seed,
        vertices,
        faces,
        view=scan_view(vertices, faces, seed),
        resolution=SCAN_RESOLUTION,
        level=condition.level,
    )
    return scan.clean, scan.noisy, scan.faces
