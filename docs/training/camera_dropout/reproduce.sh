#!/usr/bin/env bash
# Camera dropout against a control (docs/training/RESULTS.md, "Camera dropout"): both fine-tuned from the then shipped
# small_v3_swift.pt (models/weights/issue22/small_v3_swift_v1.pt since the dropout run replaced it) with the same
# recipe, 58 minutes of wall time each, run side by side on the 2-vCPU guest with one torch thread each (seed 5, peak
# lr 3e-4, balanced sampling, slices 8,8,32, the image-side class loss at 0.5, no teacher); one with --camera-dropout
# 0.3, one without. Then each export is scored on all 600 val60w4
# samples with cameras missing (measure.py), and paired bootstrap intervals over the 60 scenes per variant.
# Run from the repository root with the datasets beside it (streamdet-synth --out data60w4 --scenes 60 --seed 7
# --resolution 480x270; the same with --out val60w4 --seed 8).
set -euo pipefail
HERE=$(dirname "$0")
train() {  # $1: out folder, $2: --camera-dropout, $3: --seed
  OMP_NUM_THREADS=1 streamdet-train --data data60w4 --preset small_v3_swift --init models/weights/issue22/small_v3_swift_v1.pt \
    --out "$1" --max-minutes ${MINUTES:-58} --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 3e-4 \
    --image-warmup 0 --image-class-weight 0.5 --checkpoint-every 100 --seed "$3" --camera-dropout "$2"
}
train drop30 0.3 5 & sleep 15; train ctrl00 0 5 & wait
for t in swift:models/weights/issue22/small_v3_swift_v1.pt ctrl00:ctrl00/model.pt drop30:drop30/model.pt; do
  streamdet-export --checkpoint "${t#*:}" --out "exp_${t%%:*}"
  python "$HERE/measure.py" "exp_${t%%:*}" val60w4 all "meas_${t%%:*}"
done
streamdet-export --checkpoint models/weights/small_lidar_only.pt --out exp_lidar
streamdet-eval --data val60w4 --split all --export-dir exp_lidar --slices 8 --json eval_lidar_only.json
for v in all front_dead back_dead all_dark; do
  for a in ctrl00 swift; do
    streamdet-eval --compare "meas_$a/$v" "meas_drop30/$v" --bootstrap 1000 --json "cmp_${a}_vs_drop30_$v.json"
  done
done
# The second seed (thirty-fifth session): the same pair with seed 6, then extrinsic noise (5 deg, 50 cm, 3 seeds) on
# its dropout run and both controls (the shipped run's own: ship.sh's gate).
train drop30s6 0.3 6 & sleep 15; train ctrl00s6 0 6 & wait
for t in drop30s6 ctrl00s6; do
  streamdet-export --checkpoint "$t/model.pt" --out "exp_$t"
  python "$HERE/measure.py" "exp_$t" val60w4 all "meas_$t"
done
for v in all front_dead back_dead all_dark; do
  streamdet-eval --compare "meas_ctrl00s6/$v" "meas_drop30s6/$v" --bootstrap 1000 --json "cmp_ctrl00s6_vs_drop30s6_$v.json"
done
for t in ctrl00 ctrl00s6 drop30s6; do
  streamdet-study calib-noise --export-dir "exp_$t" --data val60w4 --split all --slices 8 --level 5,50 --json "cn_$t.json"
done
