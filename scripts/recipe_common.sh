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
