#!/usr/bin/env bash
# The second seed of the camera-dropout comparison (thirty-fifth session): reproduce.sh's recipe with --seed 6, both
# runs fine-tuned from the previous weights side by side (58 minutes of wall time each, one torch thread each), each
# export scored on all 600 val60w4 samples with cameras missing (measure.py), paired bootstrap per variant, then
# extrinsic noise (5 deg, 50 cm, 3 seeds) on the seed-6 dropout run and both controls (the shipped run's own:
# ship.sh's gate). Run from the repository root with the datasets and reproduce.sh's folders beside it.
set -euo pipefail
HERE=$(dirname "$0")
train() {  # $1: out folder, $2: --camera-dropout
  OMP_NUM_THREADS=1 streamdet-train --data data60w4 --preset small_v3_swift --init models/weights/issue22/small_v3_swift_v1.pt \
    --out "$1" --max-minutes ${MINUTES:-58} --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 3e-4 \
    --image-warmup 0 --image-class-weight 0.5 --checkpoint-every 100 --seed 6 --camera-dropout "$2"
}
train drop30s6 0.3 & sleep 15; train ctrl00s6 0 & wait
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
