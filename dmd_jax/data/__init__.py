"""Training data: procedural shape categories and on-disk mesh datasets.

`shapes` generates the categories (the project's stand-in for ShapeNet, which cannot be
downloaded here); `repair` cleans, remeshes, decimates and checks meshes, for the
generator and for meshes read from disk; `store` is the on-disk format (manifest, the
paper's train / test-intra / test-inter splits, reading); `dataset` writes procedural
datasets and `folders` indexes or converts folders of meshes laid out as
`category/*.obj|off|ply` (ShapeNetCore's layout included).
"""

from dmd_jax.data.dataset import (
    DEFAULT_TEST_INTER,
    MANIFEST_VERSION,
    SPLITS,
    Dataset,
    MeshRecord,
    convert_folder,
    intra_test_indices,
    load_dataset,
    load_mesh_folder,
    make_dataset,
    process_mesh,
)
from dmd_jax.data.repair import clean_mesh, mesh_problems, remesh
from dmd_jax.data.shapes import CATEGORIES, CategoryInfo, category_info, generate_shape

__all__ = [
    "CATEGORIES",
    "DEFAULT_TEST_INTER",
    "MANIFEST_VERSION",
    "SPLITS",
    "CategoryInfo",
    "Dataset",
    "MeshRecord",
    "category_info",
    "clean_mesh",
    "convert_folder",
    "generate_shape",
    "intra_test_indices",
    "load_dataset",
    "load_mesh_folder",
    "make_dataset",
    "mesh_problems",
    "process_mesh",
    "remesh",
]
