#!/usr/bin/env bash
# The long training run of the learned model (issue 54): the bundled network fine-tuned
# through the converged vertex update (model.vertex_update=solve, dmd_jax.vertex_update)
# on the paper's noise plus scanner noise (a quarter of the draws), simulated scans of
# every training mesh (range-image triangulations with holes and open boundaries) and the
# stress family of simple CAD shapes, clean or noisy.
#
#   scripts/train_long.sh [OUT]     # OUT defaults to runs/long; `make train-long`
#
# Stop it at any time (Ctrl-C, kill, end of session): rerunning the same command resumes
# from the last checkpoint (every 100 steps), bit-identically (batches are a function of
# (seed, step); `dmd_jax.train`). Progress: OUT/ft/log.jsonl and OUT/ft/loss_curve.png;
# the best checkpoint by validation error: OUT/ft/checkpoints/best. Needs the real meshes
# beside the repository (../shared/meshes/train); makes the procedural dataset if missing.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/long}
STEPS=${STEPS:-30000}
mkdir -p "$OUT"
source scripts/recipe_common.sh  # BIN, REAL, DATA (made if missing), TRAIN, LAST_FINETUNE
WIDE='noise.edge_levels=[0.05,0.1,0.1,0.15,0.2,0.2,0.25,0.3,0.3,0.4,0.5,0.6,0.8,1.0]'

"${TRAIN[@]}" --workdir "$OUT/ft" --init-from dmd_jax/weights/dmd_small.msgpack \
  --set train.steps="$STEPS" train.lr=2e-4 train.eval_every=500 train.ckpt_every=100 \
  "${LAST_FINETUNE[@]}" train.seed=11 "$WIDE" model.vertex_update=solve \
  model.vertex_tangent_weight=0.1 \
  noise.p_scanner=0.25 data.stress_copies=2 data.scan_views=1 data.scan_resolution=64
