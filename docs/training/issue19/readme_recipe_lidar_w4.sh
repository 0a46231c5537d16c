#!/usr/bin/env bash
# Issue 18 item 10 with the README recipe's schedule: the LiDAR-only baseline of docs/training/RESULTS.md (the same two
# stages and step counts as the shipped model: 12,872 steps at lr 2e-3, then 4,348 at 5e-4 from its weights) on the
# README recipe's dataset of world 4, scored at 1 slice on all 600 samples of val60w4 and on the recipe's own val split.
set -euo pipefail
cd /work/runs
B=/work/main/.venv/bin
export OMP_NUM_THREADS=2
A="--data /work/runs/data60w4 --preset small --no-image --balanced --num-slices 8,8,32 --max-slices-per-sample 8"
# (run with --image-warmup 0.5 at first, which a --no-image run ignored and streamdet-train now refuses)
[ -f rr_lidar_w4/model.pt ] || $B/streamdet-train $A --out rr_lidar_w4 --steps 12872 --lr 2e-3 > rr_lidar_w4.log 2>&1
[ -f rr2_lidar_w4/model.pt ] || $B/streamdet-train $A --out rr2_lidar_w4 --init rr_lidar_w4/model.pt --steps 4348 --image-warmup 0 --lr 5e-4 > rr2_lidar_w4.log 2>&1
$B/streamdet-export --checkpoint rr2_lidar_w4/model.pt --out rr2_lidar_w4_export > rr2_eval.log 2>&1
$B/streamdet-eval --data val60w4 --split all --export-dir rr2_lidar_w4_export --slices 1 --json rr2_eval_val60w4_1.json >> rr2_eval.log 2>&1
$B/streamdet-eval --data data60w4 --split val --export-dir rr2_lidar_w4_export --slices 1 --json rr2_eval_recipeval_1.json >> rr2_eval.log 2>&1
touch rr_done
