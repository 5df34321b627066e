#!/usr/bin/env bash
# A milestone of the long run scored with the smoothing controller trained for its network
# (issue 62 item 5: "bundled, the smoothing controller retrained for it"; issue 63). The
# bundled policy's rules were fitted to the bundled network; a milestone judged through them
# loses where they no longer fit it (milestone 30,000: impulse noise, where the rules run its
# solve update and its best is Jacobi, benchmarks/results/controller_design_bounds.md).
#
#   make train-long-milestone STEP=30000   # first: the plain milestone (exports its weights
#                                          # and scores the bundled ones)
#   make train-long-candidate STEP=30000   # then this
#
# 1. The controller's set (SET, default data/smoothing: `make controller-data`) searched again
#    for the milestone's network into SET_mNNNNNN (`smoothing_set --network`; two processes,
#    one from each end, one core each: 55 min for 2,000 examples on 2 cores with the long run
#    beside them at nice 19). Resumable. Without SET (a fresh machine: `data/` is not
#    committed), the same examples are built for the milestone's network directly
#    (`make controller-data` with `NETWORK`: `smoothing_set --network` without `--from`).
# 2. The controller trained on it (`scripts/train_controller.py`, chosen on its generated
#    validation split; never the real validation meshes) -> DIR/controller/controller.npz
#    and its report controller.md.
# 3. The milestone's weights exported with it, switched on (`--controller-default on`).
# 4. Scored as a milestone against the bundled weights (`scripts/train_long_milestone.py`,
#    the bundled rows reused from DIR/score/), the section appended to
#    benchmarks/results/train_long.md (NO_APPEND=1: not).
# The long run keeps running at nice 19; this runs at nice 10.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/long}
BIN=${BIN:-.venv/bin}
STEP=${STEP:?STEP=N names the milestone (make train-long-candidate STEP=30000)}
DIR="$OUT/ft/milestones/step_$(printf '%06d' "$STEP")"
SET=${SET:-data/smoothing}
SEARCHED="${SET}_m$(printf '%06d' "$STEP")"
CAND="$DIR/controller"
REPORT=${REPORT:-benchmarks/results/train_long.md}
for need in "$DIR/weights.msgpack" "$DIR/score/val_noise_bundled.csv"; do
  if [ ! -f "$need" ]; then
    echo "error: $need is missing (make train-long-milestone STEP=$STEP)" >&2
    exit 2
  fi
done
read -r MILESTONE EXACT < <("$BIN/python" -c "import json,sys; m=json.load(open(sys.argv[1])); \
print(m['milestone'], m['step'])" "$DIR/milestone.json")
export XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
SEARCH=("$BIN/python" -m dmd_jax.data.smoothing_set --out "$SEARCHED" --network "$DIR/weights.msgpack")
if [ -f "$SET/manifest.json" ]; then
  nice -n 10 "${SEARCH[@]}" --from "$SET" &
  nice -n 10 "${SEARCH[@]}" --from "$SET" --reverse
  wait
else
  echo "no $SET: building $SEARCHED for the milestone's network"
  nice -n 10 make --no-print-directory controller-data BIN="$BIN" SMOOTHING_SET="$SEARCHED" \
    NETWORK="$DIR/weights.msgpack"
fi
mkdir -p "$CAND/score"
nice -n 10 "$BIN/python" scripts/train_controller.py "$SEARCHED" --out "$CAND/controller.npz" \
  --report "$CAND/controller.md"
"$BIN/dmd-jax" export-weights "$DIR/weights.msgpack" -o "$CAND/weights.msgpack" \
  --controller "$CAND/controller.npz" --controller-default on --overwrite
cp -n "$DIR"/score/*_bundled.* "$CAND/score/"
APPEND=(--append "$REPORT")
if [ -n "${NO_APPEND:-}" ]; then APPEND=(); fi
exec nice -n 10 "$BIN/python" scripts/train_long_milestone.py \
  --weights "$CAND/weights.msgpack" --baseline dmd_jax/weights/dmd_small.msgpack \
  --step "$EXACT" --milestone "$MILESTONE" --out "$CAND/score" "${APPEND[@]}" \
  --command "make train-long-candidate STEP=$STEP  # $0 $OUT: set $SEARCHED, controller $CAND"
