#!/usr/bin/env bash
# Stops the long run cleanly (OUT/ft/STOP: it checkpoints after the running step and
# exits), then commits its state and learning curve (dmd_jax/long_run.py `save`: refuses
# a state the run did not grow from), exports its weights to OUT/latest.msgpack and
# redraws benchmarks/results/train_long.png from the committed curve.
#
#   make train-long-save     # NO_COMMIT=1: everything but the git commit
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/long}
STATE=${STATE:-training/long_run.msgpack}
CURVE=${CURVE:-training/long_run_curve.csv}
BIN=${BIN:-.venv/bin}
if [ -f "$OUT/ft/pid" ] && kill -0 "$(cat "$OUT/ft/pid")" 2>/dev/null; then
  pid=$(cat "$OUT/ft/pid")
  touch "$OUT/ft/STOP"
  echo "asked the long run (pid $pid) to stop; waiting for its checkpoint"
  for _ in $(seq 1200); do
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.5
  done
  if kill -0 "$pid" 2>/dev/null; then
    echo "error: the run (pid $pid) did not stop within 10 minutes; nothing saved" >&2
    exit 2
  fi
fi
"$BIN/python" -m dmd_jax.long_run save --workdir "$OUT/ft" --state "$STATE" --curve "$CURVE"
"$BIN/dmd-jax" export-weights "$OUT/ft/checkpoints/latest" -o "$OUT/latest.msgpack" \
  --policy-from dmd_jax/weights/dmd_small.msgpack --overwrite
"$BIN/python" scripts/train_long_report.py "$CURVE" --out benchmarks/results/train_long.png
if [ -z "${NO_COMMIT:-}" ]; then
  step=$("$BIN/python" -m dmd_jax.long_run status --workdir "$OUT/ft" --state "$STATE" | sed 's/;.*//')
  git add "$STATE" "$CURVE" benchmarks/results/train_long.png
  git commit -m "long run: $step saved ($STATE, $CURVE)" -- "$STATE" "$CURVE" benchmarks/results/train_long.png
fi
