#!/usr/bin/env bash
# Issue 22's thinner slice net distilled from small_lite.pt: preset small_v3_thin with small_lite.pt's camera lane
# and pillar net (--init of another preset), the camera lane frozen (--freeze-camera-lane: no gradient, BatchNorm
# statistics fixed, so its weights stay small_lite.pt's and one lift per step serves the teacher too), and
# small_lite.pt as the teacher (--teacher: its heatmap probabilities and boxes as soft targets beside the labels,
# training/distill.py, weight 1). The rest is reproduce_thin.sh's run (balanced sampling, slices 8,8,32, seed 2, the
# one-cycle schedule over a wall-time budget) without the image-side class loss (the camera lane it would train is
# frozen). Then scored on all 600 val60w4 samples at 8 slices beside small_lite.pt (paired bootstrap over the 60 val
# scenes). Needs data60w4 / val60w4 (reproduce_lite.sh's data recipe). Measured on a 2-vCPU Zen 3 guest (AVX2 only,
# 2 torch threads): docs/training/RESULTS.md, "small_v3_thin distilled".
set -euo pipefail

W=models/weights/small_lite.pt
streamdet-train --data data60w4 --max-minutes 70 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 \
    --image-warmup 0 --checkpoint-every 200 --preset small_v3_thin --seed 2 \
    --init $W --teacher $W --freeze-camera-lane --out thin_kd

for run in kd:thin_kd/model.pt lite:$W; do
    E=eval_${run%%:*}
    streamdet-export --checkpoint "${run#*:}" --out $E/export
    streamdet-eval --data val60w4 --split all --export-dir $E/export --slices 8 --save-results $E/res_8 --json $E/eval_8.json
done
streamdet-eval --compare eval_lite/res_8 eval_kd/res_8 --bootstrap 1000 --json compare_kd_vs_lite_8.json
