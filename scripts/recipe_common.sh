# Sourced by the training recipes (train_bundled.sh, train_cascade.sh) from the repository
# root: the tools, the real meshes, the procedural dataset of the bundled recipe (made here
# if missing) and the `small` training command both recipes start from.
BIN=${BIN:-.venv/bin}
REAL=${REAL:-../shared/meshes/train}
DATA=${DATA:-data/gen_v2}

# 190 procedural meshes: 19 categories x 10, seed 2 (128 train, 32 test-intra, 30 test-inter).
if [ ! -f "$DATA/manifest.json" ]; then
  "$BIN/python" -c "from dmd_jax.data.dataset import make_dataset; \
    make_dataset('$DATA', per_category=10, seed=2, workers=2, min_vertices=1000, max_vertices=4000)"
fi

TRAIN=("$BIN/dmd-jax" train --data "$DATA" --preset small --eval-meshes 8 --real-meshes "$REAL")
# The bundled weights' last fine-tune (losses, filter passes, normal share, clean draws),
# the settings the fine-tunes of them (train_heavy.sh, train_light.sh) start from.
LAST_FINETUNE=(train.warmup_steps=50 train.seed=7 loss.normal=3.0 loss.face_normal=3.0
  noise.p_normal=0.8 noise.p_clean=0.1 model.filter_iterations=120)

# score_run OUT RUN [export-weights options...]: exports OUT/RUN/checkpoints/best to
# OUT/RUN.msgpack with those options (the policy to run it with), then scores it on the
# validation split (sota-lite, DMD-Net rows only; the other methods' rows reused from
# benchmarks/results/sota_lite.csv) into OUT/val_RUN.md and on clean meshes into
# OUT/no_harm_RUN.md.
score_run() {
  local out=$1 run=$2
  shift 2
  "$BIN/dmd-jax" export-weights "$out/$run/checkpoints/best" -o "$out/$run.msgpack" "$@" \
    --overwrite
  "$BIN/python" benchmarks/quality/sota_lite.py --sets val --weights "$out/$run.msgpack" \
    --reuse-from benchmarks/results/sota_lite.csv --name "val_$run" --out-dir "$out"
  "$BIN/python" benchmarks/quality/no_harm.py --weights "$out/$run.msgpack" \
    --out "$out/no_harm_$run.md"
}
