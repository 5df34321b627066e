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

Mesh = tuple[np.ndarray, np.ndarray]


class TrainingSets(NamedTuple):
    """A run's meshes.

    Attributes:
      train: the training meshes, dataset meshes first, then real-mesh patches.
      evals: `{name: meshes}` per evaluation set: `test_intra`, `test_inter` and, with a
        real-mesh folder, `val` (a set may be empty).
    """

    train: list[Mesh]
    evals: dict[str, list[Mesh]]


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
    return TrainingSets(train, evals)
