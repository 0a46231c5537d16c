#!/usr/bin/env bash
# Issue 22's distilled thin net, continued: 50 more minutes from reproduce_thin_kd.sh's thin_kd/model.pt (--init of
# the same preset: every part), the same teacher and frozen camera lane, a fresh one-cycle schedule at a quarter of
# the peak learning rate (5e-4) and another seed. Then scored on all 600 val60w4 samples at 8 slices and compared
# with small_lite.pt and with the run it continues (paired bootstrap). Run where reproduce_thin_kd.sh ran (its
# thin_kd/, eval_lite/ and eval_kd/ folders). Measured: docs/training/RESULTS.md, "small_v3_thin distilled".
set -euo pipefail
W=${WEIGHTS:-models/weights/small_lite.pt}
streamdet-train --data data60w4 --max-minutes ${MINUTES:-50} --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 5e-4 \
    --image-warmup 0 --checkpoint-every 200 --preset small_v3_thin --seed 3 \
    --init thin_kd/model.pt --teacher $W --freeze-camera-lane --out thin_kd2
E=eval_kd2
streamdet-export --checkpoint thin_kd2/model.pt --out $E/export
streamdet-eval --data val60w4 --split all --export-dir $E/export --slices 8 --save-results $E/res_8 --json $E/eval_8.json
streamdet-eval --compare eval_lite/res_8 eval_kd2/res_8 --bootstrap 1000 --json compare_kd2_vs_lite_8.json
streamdet-eval --compare eval_kd/res_8 eval_kd2/res_8 --bootstrap 1000 --json compare_kd2_vs_kd_8.json
