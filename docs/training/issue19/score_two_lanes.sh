#!/usr/bin/env bash
# Scores one finished run of run_fair_v3cls_seed.sh on two cores: the same outputs as its scoring part (export, 8 and 32
# slices, the 600-sample probe, the image-use gate), two one-thread jobs at a time. Resumes: finished outputs are kept.
#   score_two_lanes.sh RUN   (e.g. fused_v3fair_w4_s0, in /work/runs)
set -euo pipefail
OUT=$1
cd /work/runs
export OMP_NUM_THREADS=1 PATH=/work/main/.venv/bin:$PATH
E=eval_$OUT; mkdir -p $E
[ -f "$E/export/manifest.json" ] || streamdet-export --checkpoint "$OUT/model.pt" --out "$E/export"
job() {  # NAME OUTPUT COMMAND...: run unless OUTPUT exists
  local out=$2; shift 2
  [ -f "$out" ] || "$@"
}
job eval8 "$E/eval_8.json" streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices 8 --save-results "$E/res_8" --json "$E/eval_8.json" &
a=$!
job eval32 "$E/eval_32.json" streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices 32 --save-results "$E/res_32" --json "$E/eval_32.json" &
b=$!
wait $a; wait $b
job drop "$E/gate_drop_cameras.json" streamdet-study drop-camera --export-dir "$E/export" --data val60w4 --split all --slices 8 --no-cameras --json "$E/gate_drop_cameras.json" &
a=$!
job noise "$E/gate_calib_noise.json" streamdet-study calib-noise --export-dir "$E/export" --data val60w4 --split all --slices 8 --level 5,50 --json "$E/gate_calib_noise.json" &
b=$!
wait $a; wait $b
job probe "$E/probe600.json" python -m streamdet.benchmarks.image_bev_probe --checkpoint "$OUT/model.pt" --data val60w4 --split all --max-samples 600 --json "$E/probe600.json"
echo "scored $OUT"
