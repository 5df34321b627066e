"""What a training run trains and evaluates on, assembled from its `DataConfig`.

The host-side half of the input pipeline (Flax's `input_pipeline.py`): which meshes, read
from disk once. `dmd_jax.pipeline` is the other half, turning these meshes into the
padded, noisy, rotated batches of every step.

A run's meshes come from two places:

* a dataset directory written by `dmd-jax make-dataset` (`DataConfig.dataset_dir`):
  every mesh of its `train` split, and the first `eval_meshes_per_split` meshes of its
  `test_intra` and `test_inter` splits as evaluation sets;
* optionally a folder of real meshes (`DataConfig.real_root`, `dmd_jax.data.real`):
  connected patches of its training split join the training set, and patches of its
  fixed validation split form the `val` evaluation set.

Two kinds of generated training meshes can join (`DataConfig.stress_copies`,
`DataConfig.scan_views`): the stress family of simple CAD shapes (`dmd_jax.data.stress`:
sharp apices, high valences, thin plates, which a denoiser must leave alone when clean),
and simulated scans of the training meshes (`dmd_jax.scan.simulate_scan`): range-image
triangulations with open boundaries and holes, each kept with its view so that the
pipeline draws scanner noise along it (`pipeline.MeshExample.view`).

Every mesh is `(vertices [n_vertex, 3] float, faces [n_face, 3] int)` in its file's own
coordinates; the pipeline moves each into the model's frame per step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from dmd_jax.data import real
from dmd_jax.data.dataset import load_dataset

if TYPE_CHECKING:  # the config module imports Flax; reading meshes needs neither
    from dmd_jax.config import DataConfig

# The dataset splits evaluated during training, in the order they are logged.
TEST_SPLITS = ("test_intra", "test_inter")
# The evaluation set of the real meshes' validation split; when present it picks the
# best checkpoint (`train.train`).
REAL_VAL = "val"
# With real meshes and simulated scans in training (`DataConfig.scan_views`), the same
# validation patches are also evaluated under scanner noise along a view of each patch
# (`val_scanner`) and as simulated scans of them (`val_scan`); both carry their view, so
# the pipeline gives them scanner noise (`pipeline.MeshExample.view`).
REAL_VAL_SCANNER = "val_scanner"
REAL_VAL_SCAN = "val_scan"

Mesh = tuple[np.ndarray, np.ndarray]
# A training mesh, or a simulated scan with its `[3]` view.
TrainMesh = tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]
# A scan keeps only pixels of this many faces at least (a sliver of a view trains nothing).
MIN_SCAN_FACES = 200


class TrainingSets(NamedTuple):
    """A run's meshes.

    Attributes:
      train: the training meshes: dataset meshes, real-mesh patches, stress shapes, then
        simulated scans `(clean vertices, faces, view)`.
      evals: `{name: meshes}` per evaluation set: `test_intra`, `test_inter` and, with a
        real-mesh folder, `val`, and with scans in training too `val_scanner` and
        `val_scan` (`(vertices, faces, view)` triples); a set may be empty.
    """

    train: list[TrainMesh]
    evals: dict[str, list[TrainMesh]]


def training_sets(d: DataConfig, *, seed: int) -> TrainingSets:
    """Reads the training and evaluation meshes a `DataConfig` names.

    Args:
      d: the run's `cfg.data`; `d.dataset_dir` must be set.
      seed: the seed of the real-mesh patch centres (runs use `cfg.train.seed`).

    Returns:
      The training set and the evaluation sets (see `TrainingSets`).

    Raises:
      ValueError: no `dataset_dir`, or not a dataset (`load_dataset`).
      FileNotFoundError: a missing dataset or real-mesh folder.
    """
    if d.dataset_dir is None:
        raise ValueError(
            "the config names no dataset: set data.dataset_dir to a directory written by "
            "`dmd-jax make-dataset` (`dmd-jax train --data DIR`)"
        )
    data = load_dataset(d.dataset_dir)
    train = data.arrays("train")
    evals = {
        split: [r.load() for r in data.split(split)[: d.eval_meshes_per_split]]
        for split in TEST_SPLITS
    }
    if d.real_root is not None:
        train += real.load_real_patches(
            d.real_root,
            "train",
            max_faces=d.real_patch_faces,
            faces_per_patch=d.real_faces_per_patch,
            max_patches=d.real_patches_per_mesh,
            seed=seed,
        )
        if d.real_coarse_faces:
            train += real.coarse_copies(d.real_root, "train", face_counts=d.real_coarse_faces)
        evals[REAL_VAL] = real.load_real_patches(
            d.real_root,
            "val",
            max_faces=d.real_val_patch_faces,
            faces_per_patch=d.real_faces_per_patch,
            max_patches=d.real_val_patches_per_mesh,
            seed=seed,
        )
    train += stress_meshes(d.stress_copies)
    train += scan_meshes(train, d.scan_views, resolution=d.scan_resolution, seed=seed)
    if d.real_root is not None and d.scan_views > 0:
        evals.update(scan_validation(evals[REAL_VAL], resolution=d.scan_resolution, seed=seed))
    return TrainingSets(train, evals)


def scan_validation(
    meshes: list[Mesh], *, resolution: int, seed: int
) -> dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """The scanner and scan validation splits of the validation patches.

    Each patch gets one view, drawn from `(seed, patch index)` and turned to the patch's
    front (`dmd_jax.scan.facing_view`): `val_scanner` is the patch itself with that view
    (scanner noise on the patch's own mesh), `val_scan` its noise-free simulated scan
    from that view (a patch that leaves no scan is left out of `val_scan`).

    Returns:
      `{REAL_VAL_SCANNER: [(vertices, faces, view)], REAL_VAL_SCAN: [(clean, faces, view)]}`.
    """
    from dmd_jax.noise import random_view
    from dmd_jax.scan import facing_view, simulate_scan

    scanner, scans = [], []
    for i, (v, f) in enumerate(meshes):
        view = facing_view(random_view(np.random.default_rng([seed, i, 0x5CA9])), v, f)
        scanner.append((v, f, view))
        try:
            scan = simulate_scan(0, v, f, view=view, resolution=resolution, level=0.0)
        except ValueError:  # no surface in view
            continue
        scans.append((scan.clean, scan.faces, scan.view))
    return {REAL_VAL_SCANNER: scanner, REAL_VAL_SCAN: scans}


def stress_meshes(copies: int) -> list[Mesh]:
    """`copies` of every stress shape (`data.stress.STRESS_SHAPES` order), clean."""
    if copies <= 0:
        return []
    from dmd_jax.data.stress import stress_shapes

    shapes = list(stress_shapes().values())
    return [shape for _ in range(copies) for shape in shapes]


def scan_meshes(
    meshes: list[TrainMesh], views: int, *, resolution: int, seed: int
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`views` simulated scans of every mesh: `(clean scan vertices, faces, view)`.

    The scans are noise-free (the pipeline adds scanner noise along `view` per step);
    views are drawn from `(seed, mesh index, view index)`. A view that keeps fewer than
    `MIN_SCAN_FACES` faces is skipped.

    Args:
      meshes: `(vertices, faces[, view])` training meshes (a view is ignored).
      views: scans per mesh; 0 gives none.
      resolution: pixels on the longer side of each depth map.
      seed: the run's seed.

    Returns:
      The scans, in mesh order then view order.
    """
    if views <= 0:
        return []
    from dmd_jax.scan import simulate_scan

    out = []
    for i, mesh in enumerate(meshes):
        for k in range(views):
            # Not `noise.random_view`: simulate_scan normalises the view itself, and a
            # second normalisation would move the views of existing runs by an ulp.
            view = np.random.default_rng([seed, i, k, 0x5CA7]).normal(size=3)
            try:
                # Noise-free with a given view: the seed draws nothing.
                scan = simulate_scan(
                    0, mesh[0], mesh[1], view=view, resolution=resolution, level=0.0
                )
            except ValueError:  # no surface in view
                continue
            if scan.faces.shape[0] >= MIN_SCAN_FACES:
                out.append((scan.clean, scan.faces, scan.view))
    return out
