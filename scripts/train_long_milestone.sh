#!/usr/bin/env bash
# Scores a milestone of the long run (issue 62 item 5) and appends the verdict to
# benchmarks/results/train_long.md. A milestone is the run's checkpoint at a multiple of
# 10,000 steps, kept by the run in OUT/ft/milestones/step_NNNNNN/ (dmd_jax/long_run.py
# `keep_milestone`: the Orbax checkpoint, the state file, milestone.json with its exact
# step). This script exports its weights with the bundled model's policy (as
# `score_run` of recipe_common.sh does), then scripts/train_long_milestone.py scores them
# and the bundled weights per shape on the validation split under every condition family
# and on clean meshes, and applies the rule (bundle when better in every family and no
# worse on clean meshes). It never replaces the bundled weights: that is a decision to
# take on the report (and the smoothing controller is retrained for new weights).
#
#   make train-long-milestone            # the latest milestone (STEP=10000: that one)
#   MAX_MESHES=1 NO_APPEND=1 ...         # an end-to-end check on one mesh per set
#
# Runs at nice 10 on one core (CORE=1 picks it; the long run and other work keep the
# rest). The scores land in the milestone's folder (score/, reused on a rerun: delete a
# CSV to recompute it). The long run keeps running; nothing here touches it.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/long}
BIN=${BIN:-.venv/bin}
BUNDLED=dmd_jax/weights/dmd_small.msgpack
REPORT=${REPORT:-benchmarks/results/train_long.md}
ROOT="$OUT/ft/milestones"
if [ -n "${STEP:-}" ]; then
  DIR="$ROOT/step_$(printf '%06d' "$STEP")"
else
  DIR=$(find "$ROOT" -mindepth 1 -maxdepth 1 -name 'step_[0-9]*' ! -name '*.tmp' 2>/dev/null | sort | tail -1)
fi
if [ -z "$DIR" ] || [ ! -f "$DIR/milestone.json" ]; then
  echo "error: no milestone ${STEP:+$STEP }in $ROOT (the run keeps one at every 10,000 steps)" >&2
  exit 2
fi
read -r MILESTONE EXACT < <("$BIN/python" -c "import json,sys; m=json.load(open(sys.argv[1])); \
print(m['milestone'], m['step'])" "$DIR/milestone.json")
echo "milestone $MILESTONE (the run's step $EXACT) in $DIR"
"$BIN/dmd-jax" export-weights "$DIR/checkpoint" -o "$DIR/weights.msgpack" \
  --policy-from "$BUNDLED" --overwrite \
  --meta "{\"long_run_milestone\": $MILESTONE, \"long_run_step\": $EXACT}"
# One core: XLA's and the BLAS thread pools held to one thread, the process pinned.
export XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
PIN=()
if command -v taskset > /dev/null; then PIN=(taskset -c "${CORE:-1}"); fi
APPEND=(--append "$REPORT")
if [ -n "${NO_APPEND:-}" ]; then APPEND=(); fi
exec nice -n 10 "${PIN[@]}" "$BIN/python" scripts/train_long_milestone.py \
  --weights "$DIR/weights.msgpack" --baseline "$BUNDLED" --step "$EXACT" \
  --milestone "$MILESTONE" --out "$DIR/score${MAX_MESHES:+_check}" \
  --max-meshes "${MAX_MESHES:-0}" "${APPEND[@]}" \
  --command "make train-long-milestone${STEP:+ STEP=$STEP}  # $0 $OUT, milestone $MILESTONE"
