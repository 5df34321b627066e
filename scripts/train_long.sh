#!/usr/bin/env bash
# The long training run of the learned model, which outlives sessions (issue 62,
# dmd_jax/long_run.py): the bundled network fine-tuned through the converged vertex
# update (model.vertex_update=solve) on the paper's noise plus scanner noise (a quarter
# of the draws), simulated scans of every training mesh and the stress family. The
# parameter-free candidate fields are computed once per noisy draw and each draw trained
# on 4 times (train.candidate_pool: 2.1x the steps per CPU-second of the recipe without,
# benchmarks/results/train_long_speed.md).
#
#   make train-long          # resume from training/long_run.msgpack, nice 19, background
#   make train-long-status   # one line: step, steps/h, last validation figures
#   make train-long-save     # stop cleanly, commit state and curve (scripts/train_long_save.sh)
#
# Its whole state (params, optimiser, step; batches are a function of (seed, step)) is
# the committed file STATE; a checkpoint every <= 10 minutes is exported to
# OUT/ft/state.msgpack; OUT/ft/STOP or SIGTERM stops it after the running step.
# FOREGROUND=1 runs it in the foreground. Needs ../shared/meshes/train; makes the
# procedural dataset if missing.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/long}
STATE=${STATE:-training/long_run.msgpack}
# The run's length is part of its recipe (the cosine schedule): changing it is another run.
STEPS=100000
mkdir -p "$OUT/ft"
source scripts/recipe_common.sh  # BIN, REAL, DATA (made if missing), TRAIN, LAST_FINETUNE
if [ -f "$OUT/ft/pid" ] && kill -0 "$(cat "$OUT/ft/pid")" 2>/dev/null; then
  echo "the long run is already running (pid $(cat "$OUT/ft/pid")); make train-long-status"
  exit 0
fi
WIDE='noise.edge_levels=[0.05,0.1,0.1,0.15,0.2,0.2,0.25,0.3,0.3,0.4,0.5,0.6,0.8,1.0]'
CMD=("${TRAIN[@]}" --workdir "$OUT/ft" --init-from dmd_jax/weights/dmd_small.msgpack
  --long-run "$STATE" --checkpoint-minutes 10 --no-progress
  --set train.steps="$STEPS" train.lr=2e-4 train.eval_every=500 train.ckpt_every=100
  "${LAST_FINETUNE[@]}" train.seed=11 "$WIDE" model.vertex_update=solve
  model.vertex_tangent_weight=0.1
  noise.p_scanner=0.25 data.stress_copies=2 data.scan_views=1 data.scan_resolution=64
  train.candidate_pool=1 train.candidate_uses=4)
if [ -n "${FOREGROUND:-}" ]; then
  exec nice -n 19 "${CMD[@]}"
fi
nohup nice -n 19 "${CMD[@]}" >> "$OUT/ft/train.out" 2>&1 < /dev/null &
echo "long run started in the background (pid $!), log $OUT/ft/train.out; make train-long-status"
