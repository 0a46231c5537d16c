#!/usr/bin/env bash
# Issue 22's lighter image lane: preset small_v3_lite (small_v3 with a quarter-width ResNet-18 at 320 x 180) trained
# with issue 19's recipe (docs/training/issue19/reproduce_v3.sh: the same data, steps, slices, crop, learning rate,
# image-side class loss and image pretraining), then scored like issue 19's runs and compared with them (paired
# bootstrap over the 60 val scenes and the seeds): against the LiDAR-only seeds (do these cameras still pay?) and
# against the fused small_v3 seeds (what the lighter lane costs). Needs data60w4 / val60w4 and issue 19's
# eval_lidar_w4_s{0,1,2} / eval_fused_v3fair_w4_s{0,1,2} (reproduce_v3.sh). Measured cost on the 2-core machine:
# the image pretraining 10 min, one fused seed about 80 min on one thread beside another (two at a time), scoring
# about 8 min per seed at 8 slices. Every training resumes: rerun a line with --resume RUN/last.pt.
set -euo pipefail
export OMP_NUM_THREADS=1

streamdet-train-image --data data60w4 --preset small_v3_lite --out pre_lite_s0 --steps 2500 --batch-size 8 \
    --eval-every 500 --seed 0

COMMON="--data data60w4 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3
        --image-warmup 0 --checkpoint-every 200"
for s in 0 1 2; do
    streamdet-train $COMMON --preset small_v3_lite --image-class-weight 0.5 --seed $s --out fused_lite_s$s \
        --init pre_lite_s0/encoder.pt
    E=eval_fused_lite_s$s
    streamdet-export --checkpoint fused_lite_s$s/model.pt --out $E/export
    streamdet-eval --data val60w4 --split all --export-dir $E/export --slices 8 --save-results $E/res_8 --json $E/eval_8.json
done

lite=eval_fused_lite_s0/res_8,eval_fused_lite_s1/res_8,eval_fused_lite_s2/res_8
streamdet-eval --compare eval_lidar_w4_s0/res_8,eval_lidar_w4_s1/res_8,eval_lidar_w4_s2/res_8 $lite \
    --bootstrap 1000 --json compare_lite_vs_lidar_8.json
streamdet-eval --compare eval_fused_v3fair_w4_s0/res_8,eval_fused_v3fair_w4_s1/res_8,eval_fused_v3fair_w4_s2/res_8 $lite \
    --bootstrap 1000 --json compare_lite_vs_v3_8.json
