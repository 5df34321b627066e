#!/usr/bin/env bash
# Bundling new weights (docs/training.md, "Milestones"): every measurement the README,
# the model card and the tests read from the bundled weights, rerun with the new file in
# place, in one resumable command. The prose is not edited here: the script ends with the
# list of what to rewrite from the new reports (tests/test_readme.py checks the figures).
#
#   make bundle WEIGHTS=training/candidate.msgpack   # ~2-2.5 h on 2 cores
#   STEPS="stress table2" make bundle WEIGHTS=...   # only these steps (names below)
#
# 1. WEIGHTS copied over dmd_jax/weights/dmd_small.msgpack (the old file kept as
#    out/bundle/previous.msgpack; a second run with the same WEIGHTS goes on).
# 2. Each step writes its report under benchmarks/results/ (or docs/img/, tests/data/),
#    the other methods' rows reused where the benchmark allows (`--reuse-from`), and
#    leaves out/bundle/<step>.done naming the weights' SHA-256: a rerun skips the steps
#    done for these weights. Timing steps (inference, cold) want idle cores: save the long
#    run first (make train-long-save) and resume it after.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=$(cd "${BIN:-.venv/bin}" && pwd)
PY="$BIN/python"
WEIGHTS=${WEIGHTS:?WEIGHTS=path names the weights to bundle (make bundle WEIGHTS=...)}
BUNDLED=dmd_jax/weights/dmd_small.msgpack
WORK=out/bundle
ALL="reference demo scan_picture stress table2 scan no_harm sota_lite inference_vs_bnf inference cold"
STEPS=${STEPS:-$ALL}
mkdir -p "$WORK" out/sota_parts
sha() { "$PY" -c "import sys; from dmd_jax.long_run import file_sha; print(file_sha(sys.argv[1]))" "$1"; }

want=$(sha "$WEIGHTS")
if [ "$(sha "$BUNDLED")" != "$want" ]; then
  if [ -f "$WORK/previous.msgpack" ]; then
    echo "error: $BUNDLED is neither $WEIGHTS nor the file $WORK/previous.msgpack was saved" \
      "from; restore it (git checkout $BUNDLED) and remove $WORK to start over" >&2
    exit 2
  fi
  cp "$BUNDLED" "$WORK/previous.msgpack"
  "$PY" -c "import dmd_jax, sys; dmd_jax.load_weights(sys.argv[1])" "$WEIGHTS"  # readable
  cp "$WEIGHTS" "$BUNDLED.tmp" && mv "$BUNDLED.tmp" "$BUNDLED"
  echo "bundled $WEIGHTS (SHA-256 ${want:0:12}); the previous file is $WORK/previous.msgpack"
fi

step() {  # step NAME COMMAND...: runs it unless done for these weights
  local name=$1
  shift
  case " $STEPS " in *" $name "*) ;; *) return 0 ;; esac
  if [ "$(cat "$WORK/$name.done" 2> /dev/null)" = "$want" ]; then
    echo "== $name: done for these weights"
    return 0
  fi
  echo "== $name ($(date -u +%H:%M))"
  local start=$SECONDS
  "$@"
  echo "$want" > "$WORK/$name.done"
  echo "== $name: $((SECONDS - start)) s"
}

reference() {  # the pinned outputs of tests/test_bundled_reference.py (one pass)
  "$PY" - << 'EOF'
import numpy as np
import dmd_jax
path = "tests/data/bundled_reference.npz"
data = dict(np.load(path))
bundle = dmd_jax.load_pretrained()
for aggregation in ("ell", "segment_sum"):
    data[aggregation] = dmd_jax.denoise(
        data["vertices"], data["faces"], bundle, aggregation=aggregation, iterations=1
    )
np.savez(path, **data)
EOF
}

demo() {
  "$BIN/dmd-jax" demo --out out/demo --overwrite
  cp out/demo/before_after.png docs/img/demo_before_after.png
}

scan_picture() {  # the README's "Denoising your scans" commands, drawn as docs/scans.md says
  local dir="$WORK/scan_nut"
  rm -rf "$dir" && mkdir -p "$dir"
  (
    cd "$dir"
    "$PY" - << 'EOF'
import dmd_jax
from dmd_jax.data import generate_shape
part, part_faces = generate_shape("fastener", 2024, 2)
scan = dmd_jax.simulate_scan(0, part, part_faces, view=(0.5, -0.6, -0.6), resolution=128, level=0.5)
dmd_jax.save_mesh("nut_scan.ply", scan.noisy, scan.faces)
dmd_jax.save_mesh("nut_scan_clean.ply", scan.clean, scan.faces)
vertices, faces = dmd_jax.load_mesh("nut_scan.ply")
dmd_jax.save_mesh("nut_scan_dmd.ply", dmd_jax.denoise(vertices, faces), faces)
EOF
    "$BIN/dmd-jax" render nut_scan.ply nut_scan_dmd.ply -o nut_scan.png \
      --gt nut_scan_clean.ply --view 0.5,-0.6,-0.6 --up z --panel-size 2.4
  )
  "$PY" -c "from PIL import Image; import sys; Image.open(sys.argv[1]).convert('RGB').quantize(128).save(sys.argv[2])" \
    "$dir/nut_scan.png" docs/img/scan_nut.png
}

sota() {  # sota NAME ARGS...: a sota_lite report, DMD-Net rerun, the rest reused
  local name=$1
  shift
  "$PY" benchmarks/quality/sota_lite.py "$@" --reuse-from "benchmarks/results/$name.csv" \
    --name "$name" --out-dir out/sota_parts
  cp "out/sota_parts/$name.md" "out/sota_parts/$name.csv" benchmarks/results/
}

step reference reference
step demo demo
step scan_picture scan_picture
step stress sota sota_lite_stress --sets stress
step table2 "$PY" benchmarks/quality/table2.py --table sota --dmd-passes 8
step scan sota sota_lite_scan --conditions scanner:0.3 scanner:0.5 scanner:0.8 scan:0.15 \
  scan:0.5 --sets shared val --max-faces 5000
step no_harm sh -c "'$PY' benchmarks/quality/no_harm.py --sets shared stress scan \
  --out out/sota_parts/no_harm.md && cp out/sota_parts/no_harm.md benchmarks/results/"
step sota_lite sota sota_lite --conditions 0.1 0.2 0.3 0.6 impulse:0.6 --sets shared val
HUGE=(env GLIBC_TUNABLES=glibc.malloc.hugetlb=1)
step inference_vs_bnf "${HUGE[@]}" "$PY" benchmarks/bench_inference.py --presets small \
  --faces 100000 --name inference_vs_bnf
step inference sh -c "${HUGE[*]} '$PY' benchmarks/bench_inference.py --presets small \
  --faces 1000 3000 10000 30000 100000 300000 --append && ${HUGE[*]} '$PY' \
  benchmarks/bench_inference.py --presets small --faces 1000000 --append"
step cold "$PY" benchmarks/bench_cold_start.py --repeat 2 --profile

cat << EOF

Measured with $WEIGHTS (SHA-256 ${want:0:12}). Now rewrite from the new reports (then
.venv/bin/python -m pytest tests/test_readme.py tests/test_policy.py and make test):
- README: the demo sentence, the scan table and its bullets, "What to expect" (Gaussian
  per-mesh counts and ratios, stress, Table II, clean meshes), "What denoise does by
  default" (the controller decides; the rules are the fallback), the quality table, the
  speed table and cold start, the file size (0.44 MB).
- docs/bundled-model.md: the SHA-256 (test_policy), size, recipe (the long run's milestone
  and its controller), validation, limits, speed.
- docs/studies.md / README "What the bundled model is": the head-zeroed study (candidate
  mean) is of the previous network.
- docs/controller.md, docs/architecture.md, docs/large-meshes.md, docs/history.md.
- notebooks 05-07 (make notebooks): figures of the previous network.
- Tests that read the controller's choices on fixed meshes: test_policy (the card's SHA,
  test_info_says_how_the_call_ran: what the controller chooses on the reference sphere),
  tests/test_sota.py (the Table II columns), notebooks 05-07's asserts.
EOF
