#!/usr/bin/env bash
# Issue 22's thinner slice net: preset small_v3_thin (small_v3_lite with half the BEV encoder's widths and 8-channel
# head branches) started from the shipped small_lite.pt's camera lane and pillar net (streamdet-train --init takes
# the parts of another preset configured alike; the BEV encoder and head start from the seed), trained on world 4
# with issue 19's recipe (balanced sampling, slices 8,8,32, the image-side class loss) over a fixed wall-time budget
# (the one-cycle schedule spread over --max-minutes: how the shipped run was made, on a 2-vCPU Zen 3 guest with AVX2
# only, 2 torch threads), then scored on all 600 val60w4 samples at 8 slices beside small_v3_lite and compared with it
# (paired bootstrap over the 60 val scenes). Needs data60w4 / val60w4 (reproduce_lite.sh's data recipe).
set -euo pipefail

streamdet-train --data data60w4 --max-minutes 80 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 \
    --image-warmup 0 --checkpoint-every 200 --preset small_v3_thin --image-class-weight 0.5 --seed 2 \
    --init models/weights/small_lite.pt --out thin_s2

for run in thin:thin_s2/model.pt lite:models/weights/small_lite.pt; do
    E=eval_${run%%:*}
    streamdet-export --checkpoint "${run#*:}" --out $E/export
    streamdet-eval --data val60w4 --split all --export-dir $E/export --slices 8 --save-results $E/res_8 --json $E/eval_8.json
done
streamdet-eval --compare eval_lite/res_8 eval_thin/res_8 --bootstrap 1000 --json compare_thin_vs_lite_8.json
