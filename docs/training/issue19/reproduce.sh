#!/usr/bin/env bash
# Issue 19's comparison from scratch: the commands behind docs/training/issue19_plan.md, the README's decision table
# and models/weights/small.pt / small_lidar_only.pt. About 6 hours of one CPU thread per fused seed's training and
# evaluation together, 25 minutes per LiDAR-only seed: run two at a time with OMP_NUM_THREADS=1 (two one-thread runs
# use a 2-core machine best). Every training resumes: rerun a line with --resume RUN/last.pt after an interruption.
set -euo pipefail
export OMP_NUM_THREADS=1

# The worlds: world 4 (commit 2f1b4c5 or later) for training (seed 7) and evaluation (seed 8, never trained on).
streamdet-synth --out data60w4 --scenes 60 --seed 7 --resolution 480x270 --workers 2
streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270 --workers 2

# The image pretraining (item 1) ran on a world-2 set of the same recipe (streamdet-synth at commit c4dd090, seed 7);
# it was stopped at step 4000 of 6000 (val mIoU 0.608 within 30 m). Its encoder.pt starts every fused seed.
streamdet-train-image --data data60w2 --preset small_v2 --out pre_s0 --steps 6000 --batch-size 8 --eval-every 500 \
    --seed 0 --stop-at-step 4000

# The fair schedule (item 4): the same steps, data, slice counts, crop and learning rate for both sides, cameras on
# from the first step, three seeds each; one LiDAR-only run without the quadrant crop.
COMMON="--data data60w4 --preset small_v2 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8
        --lr 2e-3 --image-warmup 0 --checkpoint-every 200"
for s in 0 1 2; do
    streamdet-train $COMMON --seed $s --out fused_w4_s$s --init pre_s0/encoder.pt
    streamdet-train $COMMON --seed $s --out lidar_w4_s$s --no-image
done
streamdet-train $COMMON --seed 0 --out lidar_nocrop_w4_s0 --no-image --no-crop

# Scoring (items 5 and 6): export, 1 / 8 / 32 slices on all 600 samples, the image-use gate for fused runs.
for run in fused_w4_s0 fused_w4_s1 fused_w4_s2 lidar_w4_s0 lidar_w4_s1 lidar_w4_s2 lidar_nocrop_w4_s0; do
    scripts/issue19_eval.sh $run val60w4 eval_$run
done
for s in 0 1 2; do
    python -m streamdet.benchmarks.image_bev_probe --checkpoint fused_w4_s$s/model.pt --data val60w4 --split all \
        --max-samples 120 --json eval_fused_w4_s$s/probe.json
done

# The decision: three seeds a side, a two-level paired bootstrap over the 60 val scenes and the seeds.
for n in 8 32; do
    streamdet-eval --compare eval_lidar_w4_s0/res_$n,eval_lidar_w4_s1/res_$n,eval_lidar_w4_s2/res_$n \
        eval_fused_w4_s0/res_$n,eval_fused_w4_s1/res_$n,eval_fused_w4_s2/res_$n --bootstrap 1000 --json compare3_$n.json
done
gates=()
for s in 0 1 2; do
    gates+=(--gate-drop eval_fused_w4_s$s/gate_drop_cameras.json --gate-noise eval_fused_w4_s$s/gate_calib_noise.json
            --probe eval_fused_w4_s$s/probe.json)
done
python -m streamdet.benchmarks.camera_claim --compare8 compare3_8.json --compare32 compare3_32.json "${gates[@]}" \
    --json camera_claim.json
