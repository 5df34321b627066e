#!/usr/bin/env bash
# Issue 64: a fine-tune of the bundled weights with half the bilateral pre-filter passes
# (model.filter_iterations=60 instead of 120), then scored like train_light.sh
# (validation split of sota-lite, DMD-Net rows only, and clean meshes, with the bundled
# policy). Why: the pre-filters are about half of the network program and the default
# call at 100k faces is 1.06-1.23x BNF; the bundled network run at 60 passes without
# retraining is 0.89x BNF but 0.35 % worse per shape on validation, worst 1.18x
# (docs/cold-start.md). This asks whether 1,500 steps at 60 passes win that back, as
# 1,500 steps at 120 passes once won over 60 (docs/design-decisions.md). They do not:
# benchmarks/results/fast_prefilters.md (not adopted). The training command resumes its
# workdir.
#
#   scripts/train_fast.sh [OUT]    # OUT (default runs/fast) gets runs, weights, reports
#
# Nothing in the repository is replaced. Needs ../shared/meshes/train and the dataset of
# scripts/train_bundled.sh (DATA, default data/gen_v2, made here if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/fast}
mkdir -p "$OUT"
# BIN, REAL, DATA (made if missing), TRAIN, LAST_FINETUNE, score_run
source scripts/recipe_common.sh
# The bundled weights' last fine-tune, its benchmark levels, at 60 pre-filter passes.
BENCH='noise.edge_levels=[0.05,0.1,0.1,0.15,0.2,0.2,0.25,0.3,0.3,0.4,0.5,0.6,0.8,1.0]'

"${TRAIN[@]}" --workdir "$OUT/fast" --init-from dmd_jax/weights/dmd_small.msgpack \
  --set train.steps=1500 train.lr=1e-4 "${LAST_FINETUNE[@]}" "$BENCH" \
  model.filter_iterations=60 ${EXTRA:-}

score_run "$OUT" fast --policy-from dmd_jax/weights/dmd_small.msgpack
echo "reports in $OUT: val_fast.md (compare with benchmarks/results/sota_lite.md, set val), no_harm_fast.md"
