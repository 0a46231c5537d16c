#!/usr/bin/env bash
set -euo pipefail
cd /work/main
P=.venv/bin/python
DATA="training: streamdet-synth --out data60w4 --scenes 60 --seed 7 --resolution 480x270 (world 4, commit 2f1b4c5; 48 scenes / 480 samples of its 'train' split); evaluation: streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270 (all 600 samples, never trained on); image pretraining: the world-2 set of the same recipe (commit c4dd090)"
COMMON='streamdet-train --data data60w4 --preset small_v2 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200'
D=docs/training/issue19
$P scripts/ship_weights.py --run /work/runs/fused_w4_s2 --eval /work/runs/eval_fused_w4_s2 --out models/weights/small.pt \
  --data-recipe "$DATA" \
  --recipe "streamdet-train-image --data data60w2 --preset small_v2 --out pre_s0 --steps 6000 --batch-size 8 --eval-every 500 --seed 0 (stopped at step 4000: val mIoU 0.608 within 30 m); $COMMON --seed 2 --init pre_s0/encoder.pt (docs/training/issue19/reproduce.sh)" \
  --note "the best of issue 19's three fused seeds (0, 1, 2) by the mean of its 8- and 32-slice mAP on val60w4; the LiDAR-only baseline shipped beside it (small_lidar_only.pt) was chosen from its three seeds the same way" \
  --note "the comparison of the two sides uses all three seeds of each (evidence.compare_8_slices / compare_32_slices, the verdict in evidence.camera_claim), not this pair" \
  --attach probe=/work/runs/eval_fused_w4_s2/probe.json \
  --attach compare_8_slices=/work/runs/cmp3/compare3_8.json --attach compare_32_slices=/work/runs/cmp3/compare3_32.json \
  --attach camera_claim=$D/camera_claim.json --attach eval_fp16_8_slices=/work/runs/ship/eval8_fp16.json --attach eval_int8_8_slices=/work/runs/ship/eval8_int8.json --attach eval_int8_image_lane_8_slices=/work/runs/ship/eval8_int8lane.json
$P scripts/ship_weights.py --run /work/runs/lidar_w4_s0 --eval /work/runs/eval_lidar_w4_s0 --out models/weights/small_lidar_only.pt \
  --data-recipe "$DATA" \
  --recipe "$COMMON --seed 0 --no-image (docs/training/issue19/reproduce.sh)" \
  --note "issue 19's LiDAR-only streaming baseline: the same schedule, data, slices and quadrant crop as small.pt, no image lane; the best of its three seeds by the mean of its 8- and 32-slice mAP on val60w4, as small.pt was chosen" \
  --note "exports the slice graph only (no image input, no lut.npz): streamdet-export --checkpoint models/weights/small_lidar_only.pt"
