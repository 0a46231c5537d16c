#!/usr/bin/env bash
# Issue 19's decision from scratch: the fair small_v3 + image-class-loss comparison behind the README's table,
# docs/training/issue19_plan.md ("Eighth session") and the shipped models/weights/small.pt (fused seed 2) /
# small_lidar_only.pt (LiDAR-only seed 0). Measured cost on the 2-core machine: about 140 min per fused seed and
# 45 min per LiDAR-only seed on one thread beside another run, the image pretraining 36 min, scoring about 25 min per
# fused seed (8 + 32 slices, probe, gates) on one thread: run two jobs at a time with OMP_NUM_THREADS=1. Every
# training resumes: rerun a line with --resume RUN/last.pt after an interruption. The session scripts that ran it
# piecewise: run_fair_v3cls_{a,b,seed,lanes,decide}.sh, run_lidar_seed.sh, ship_v3.sh.
set -euo pipefail
export OMP_NUM_THREADS=1

# The worlds: world 4 for training (seed 7) and evaluation (seed 8, never trained on).
streamdet-synth --out data60w4 --scenes 60 --seed 7 --resolution 480x270 --workers 2
streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270 --workers 2

# Item 1: the image pretraining on the training world's masks (val mIoU 0.509 within 30 m at step 2500).
streamdet-train-image --data data60w4 --preset small_v3 --out pre_v3_w4_s0 --steps 2500 --batch-size 8 \
    --eval-every 500 --seed 0

# Item 4: the same steps, data, slice counts, crop and learning rate for both sides, cameras on from the first step.
COMMON="--data data60w4 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3
        --image-warmup 0 --checkpoint-every 200"
for s in 0 1 2; do
    streamdet-train $COMMON --preset small_v3 --image-class-weight 0.5 --seed $s --out fused_v3fair_w4_s$s \
        --init pre_v3_w4_s0/encoder.pt
    streamdet-train $COMMON --preset small_v2 --seed $s --out lidar_w4_s$s --no-image
done

# Items 5 and 6: every run on all 600 val samples at 8 and 32 slices (kept for the paired bootstrap); for the fused
# runs the 600-sample probe and the image-use gate.
for run in fused_v3fair_w4_s0 fused_v3fair_w4_s1 fused_v3fair_w4_s2 lidar_w4_s0 lidar_w4_s1 lidar_w4_s2; do
    E=eval_$run
    streamdet-export --checkpoint $run/model.pt --out $E/export
    for n in 8 32; do
        streamdet-eval --data val60w4 --split all --export-dir $E/export --slices $n --save-results $E/res_$n \
            --json $E/eval_$n.json
    done
done
for s in 0 1 2; do
    E=eval_fused_v3fair_w4_s$s
    python -m streamdet.benchmarks.image_bev_probe --checkpoint fused_v3fair_w4_s$s/model.pt --data val60w4 \
        --split all --max-samples 600 --json $E/probe600.json
    streamdet-study drop-camera --export-dir $E/export --data val60w4 --split all --slices 8 --no-cameras \
        --json $E/gate_drop_cameras.json
    streamdet-study calib-noise --export-dir $E/export --data val60w4 --split all --slices 8 --level 5,50 \
        --json $E/gate_calib_noise.json
done
# Item 3: the LUT's own-footprint coverage on the evaluation world.
python -m streamdet.benchmarks.lut_coverage val60w4 --preset small_v3 --heights 1,2,3,4 --json lut_coverage.json

# The decision: three seeds a side, a two-level paired bootstrap over the 60 val scenes and the seeds.
for n in 8 32; do
    streamdet-eval --compare eval_lidar_w4_s0/res_$n,eval_lidar_w4_s1/res_$n,eval_lidar_w4_s2/res_$n \
        eval_fused_v3fair_w4_s0/res_$n,eval_fused_v3fair_w4_s1/res_$n,eval_fused_v3fair_w4_s2/res_$n \
        --bootstrap 1000 --json compare3_$n.json
done
gates=()
for s in 0 1 2; do
    E=eval_fused_v3fair_w4_s$s
    gates+=(--gate-drop $E/gate_drop_cameras.json --gate-noise $E/gate_calib_noise.json --probe $E/probe600.json)
done
python -m streamdet.benchmarks.camera_claim --compare8 compare3_8.json --compare32 compare3_32.json "${gates[@]}" \
    --json camera_claim.json --plot camera_claim.png
