#!/usr/bin/env bash
# Issue 22's lighter camera lane: preset small_v3_swift (small_v3_thin with 224 x 126 images and the flat lifter's
# residual conv factorised, models/presets.py), started from small_v3_thin_kd2.pt (every tensor of the same name and
# shape: init_swift.py; the factorised residual fresh) and trained end to end, camera lane included (the image encoder
# has to learn the smaller image scale), 65 minutes of wall time, peak lr 1e-3, with small_lite.pt as the teacher
# (--teacher: it runs its own camera lane on the same 224 x 126 images) and the image-side class loss of
# reproduce_lite.sh (weight 0.5). Then scored on all 600 val60w4 samples at 8 slices beside small_v3_thin_kd2.pt
# (paired bootstrap over the 60 val scenes; eval_kd2/ from reproduce_thin_kd2_continue.sh). Run where
# reproduce_thin_kd2_continue.sh ran. Measured: docs/training/RESULTS.md, "small_v3_swift".
set -euo pipefail
HERE=$(dirname "$0")
W=${WEIGHTS:-models/weights/small_lite.pt}
KD2=${KD2:-models/weights/issue22/small_v3_thin_kd2.pt}
mkdir -p swift
python "$HERE/init_swift.py" "$KD2" swift/init.pt
streamdet-train --data data60w4 --max-minutes ${MINUTES:-65} --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 1e-3 \
    --image-warmup 0 --checkpoint-every 200 --preset small_v3_swift --seed 4 --image-class-weight 0.5 \
    --init swift/init.pt --teacher $W --out swift/run
E=eval_swift
streamdet-export --checkpoint swift/run/model.pt --out $E/export
streamdet-eval --data val60w4 --split all --export-dir $E/export --slices 8 --save-results $E/res_8 --json $E/eval_8.json
streamdet-eval --compare eval_kd2/res_8 eval_swift/res_8 --bootstrap 1000 --json compare_swift_vs_kd2_8.json
