"""CNR: Wang, Liu & Tong, "Mesh denoising via cascaded normal regression", SIGGRAPH Asia 2016.

The learned baseline of the paper's comparison tables. Each cascade stage computes a
per-face *filtered facet normal descriptor* (FND) of the current mesh, regresses the
clean face normal from it, and moves the vertices onto the regressed normals with Sun et
al.'s update (`fit_vertices_to_normals`, the one BNF and GNF use). This module's version:

* **FND.** Bilateral normal filtering (Zheng et al. 2011, local scheme, as `bnf`) of the
  face normals of the current mesh over the vertex 1-ring (faces sharing a vertex, the
  face itself included), weight `A_j · exp(−|c_i − c_j|² / 2σ_s²) · exp(−|n_i − n_j|² /
  2σ_r²)`, for every pair of σ_s ∈ {1, 2} × d̄ (d̄ the mean distance between the
  centroids of edge-adjacent faces, re-measured on each stage's mesh) and σ_r ∈ {0.1,
  0.2, 0.35, 0.5, ∞}, each read after 1, 3 and 8 iterations: 30 filtered normals plus
  the unfiltered one, 93 numbers per face (`CNRConfig` holds the sets).
* **Rotation invariance.** Every normal of the descriptor is written in a local frame
  per face: z is the most smoothed normal (σ_s = 2d̄, σ_r = ∞, 8 iterations); x is the
  principal direction, in the plane ⟂ z, of the area-weighted normal tensor
  `Σ_j A_j m_j m_jᵀ` over the 1-ring of the feature-preserving filtered normals m
  (σ_s = d̄, σ_r = 0.35, 3 iterations); its sign makes `x · m_i ≥ 0` (the face's own
  filtered normal leans to +x: at a crease that is the face's side); y = z × x. The
  paper aligns the descriptor with the eigenvectors of a normal tensor too; this frame
  is that idea made unique (sign and in-plane angle fixed) wherever the tensor's two
  tangent eigenvalues differ. The regressed normal is predicted in this frame and
  rotated back.
* **Regressor.** The paper clusters the descriptors and trains one single-hidden-layer
  network per cluster; here one MLP per stage (hidden widths `CNRConfig.hidden`, ReLU)
  predicts a correction added to the feature-preserving filtered normal (in the local
  frame), normalised. Zero-initialised output layer: an untrained stage is one
  bilateral-filter step.
* **Cascade.** Two stages by default (the paper uses 2–4); each stage's vertex update
  runs `vertex_iterations` Jacobi passes.

Training (`train_cnr`, or `dmd-jax train-cnr --data data/gen_v1 --out FILE`)
corrupts the clean training meshes the way `dmd_jax.pipeline.corrupt` does (random
rotation, mixed noise of four kinds with canonical and edge-relative levels), samples
faces, fits stage 1 with Adam on the squared distance between unit normals, runs stage
1 on every training mesh, fits stage 2 on the stage-1 outputs, and so on. Weights are
one msgpack file (`flax.serialization`, no pickle) holding the params of every stage and
the `CNRConfig` as JSON; `cnr_small.msgpack` ships in `dmd_jax/weights/`.

All computation runs in the mesh's canonical frame (like the classic baselines), so
`cnr` is translation and scale equivariant. Host-side index arrays are padded to bucketed
sizes so that meshes of similar size share one compiled program.

Modules, by job: `config` (`CNRConfig`), `features` (padded neighbourhoods and the
filtered facet normal descriptor, `fnd`), `model` (the per-stage regressor, the cascade,
the weights file and `cnr` itself), `train` (`train_cnr` and the `dmd-jax train-cnr`
command, `train_main`). Every public name is importable from this package.
"""

from __future__ import annotations

from dmd_jax.baselines.cascaded_regression.config import CNRConfig
from dmd_jax.baselines.cascaded_regression.features import MeshArrays, fnd, prepare_mesh
from dmd_jax.baselines.cascaded_regression.model import (
    BUNDLED_NAME,
    WEIGHTS_FORMAT,
    WEIGHTS_VERSION,
    CNRRegressor,
    CNRWeights,
    bundled_weights_path,
    cnr,
    load_bundled_cnr,
    load_cnr_weights,
    save_cnr_weights,
)
from dmd_jax.baselines.cascaded_regression.train import (
    StageSamples,
    fit_stage,
    stage_loss,
    stage_samples,
    train_cnr,
    train_main,
)

__all__ = [
    "BUNDLED_NAME",
    "CNRConfig",
    "CNRRegressor",
    "CNRWeights",
    "MeshArrays",
    "StageSamples",
    "WEIGHTS_FORMAT",
    "WEIGHTS_VERSION",
    "bundled_weights_path",
    "cnr",
    "fit_stage",
    "fnd",
    "load_bundled_cnr",
    "load_cnr_weights",
    "prepare_mesh",
    "save_cnr_weights",
    "stage_loss",
    "stage_samples",
    "train_cnr",
    "train_main",
]
