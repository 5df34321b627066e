#!/usr/bin/env bash
# The learned-second-pass experiment of issue 29 (docs/history.md, 2026-12-02, "A learned
# second pass"): two cascade fine-tunes of the bundled weights (train.passes=2), each
# exported with two passes and the bundled pre-smoothing rule, then scored on the
# validation split (sota-lite, DMD-Net rows only; the other methods' rows reused from
# benchmarks/results/sota_lite.csv) and on clean meshes (no_harm). About 55 + 30 min of
# training and 10 min of scoring on 2 cores; each training command resumes its workdir.
#
#   scripts/train_cascade.sh [OUT]    # OUT (default runs/cascade) gets runs, weights, reports
#
# Nothing in the repository is replaced. Needs ../shared/meshes/train and the dataset of
# scripts/train_bundled.sh (DATA, default data/gen_v2, made here if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/cascade}
mkdir -p "$OUT"
source scripts/recipe_common.sh  # BIN, REAL, DATA (made if missing), TRAIN, score_run
COMMON=(train.passes=2 train.warmup_steps=50 train.seed=5 loss.normal=3.0 loss.face_normal=3.0
  noise.p_normal=0.8 model.filter_iterations=120)
BENCH='noise.edge_levels=[0.05,0.1,0.1,0.15,0.2,0.2,0.25,0.3,0.3,0.4,0.5,0.6,0.8,1.0]'
LIGHT='noise.edge_levels=[0.05,0.05,0.1,0.1,0.1,0.15,0.2,0.2,0.25,0.3,0.3,0.4,0.5,0.6,0.8,1.0]'

# 1. 2,800 steps of the cascade from the bundled weights, its last fine-tune's noise (55 min).
"${TRAIN[@]}" --workdir "$OUT/cascade2" --init-from dmd_jax/weights/dmd_small.msgpack \
  --set train.steps=2800 train.lr=1.5e-4 "${COMMON[@]}" "$BENCH"
# 2. 1,500 more with light noise and clean meshes drawn more often (30 min).
"${TRAIN[@]}" --workdir "$OUT/cascade2_light" --init-from "$OUT/cascade2/checkpoints/best" \
  --set train.steps=1500 train.lr=1e-4 noise.p_clean=0.25 "${COMMON[@]}" "$LIGHT"

for run in cascade2 cascade2_light; do
  # The trained policy (two passes, no tolerance) plus the bundled pre-smoothing rule.
  score_run "$OUT" "$run" --presmooth 27 4.5
done
echo "reports in $OUT: val_*.md (compare with benchmarks/results/sota_lite.md, set val), no_harm_*.md"
