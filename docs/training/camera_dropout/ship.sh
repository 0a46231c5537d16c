#!/usr/bin/env bash
# How the dropout run (reproduce.sh's drop30) became models/weights/small_v3_swift.pt (thirty-fourth session): the
# shipped models' full scoring on all 600 val60w4 samples (1, 8 and 32 slices, the two gates), the previous model at
# 32 slices for a paired comparison, then ship_weights.py with the evidence attached. Run where reproduce.sh ran (the
# run folders, val60w4, exp_swift), REPO pointing at the repository.
set -euo pipefail
REPO=${REPO:-.}
"$REPO/scripts/issue19_eval.sh" drop30 val60w4 ship_drop30
mkdir -p old32
streamdet-eval --data val60w4 --split all --export-dir exp_swift --slices 32 --save-results old32/res_32 \
    --json old32/eval_32.json
streamdet-eval --compare old32/res_32 ship_drop30/res_32 --bootstrap 1000 --json cmp_swift_vs_drop30_32.json
python "$REPO/scripts/ship_weights.py" --run drop30 --eval ship_drop30 --out "$REPO/models/weights/small_v3_swift.pt" \
    --data-recipe "training: streamdet-synth --out data60w4 --scenes 60 --seed 7 --resolution 480x270 (world 4; its 'train' split); evaluation: streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270 (all 600 samples, never trained on)" \
    --recipe "models/weights/issue22/small_v3_swift_v1.pt (docs/training/issue22/reproduce_swift.sh, its record small_v3_swift_v1.json), then fine-tuned: OMP_NUM_THREADS=1 streamdet-train --data data60w4 --preset small_v3_swift --init models/weights/issue22/small_v3_swift_v1.pt --out drop30 --max-minutes 58 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 3e-4 --image-warmup 0 --image-class-weight 0.5 --checkpoint-every 100 --seed 5 --camera-dropout 0.3 (docs/training/camera_dropout/reproduce.sh)" \
    --machine "2-vCPU Intel Xeon KVM guest (AVX-512 with VNNI, AMX), 1 torch thread beside the control run, fp32" \
    --note "issue 22's lighter camera lane (preset small_v3_swift: 224 x 126 images, a factorised flat-lifter residual, the thin slice net) fine-tuned with camera dropout 0.3: a share 0.3 of the steps drop k of J cameras (k uniform in 1..J), their features exactly zero before the lift, the camera lane and image-BEV norm on their stored statistics in those steps" \
    --note "against a control fine-tuned alike without dropout (paired scene bootstrap, 8 slices, 600 samples): mAP +1.17 [+0.77, +1.64] with all cameras, +3.77 [+2.94, +4.59] with CAM_FRONT dead, +6.23 [+5.60, +6.99] with the back three dead, +10.17 [+9.18, +11.32] with all dark (evidence.*_vs_control); against the previous small_v3_swift.pt at 32 slices +0.18 [-0.28, +0.70]" \
    --note "with every camera dark the LiDAR-only small_lidar_only.pt still scores higher (45.66 against 34.76 here): configure it as the runtime's fallback_export_dir" \
    --attach "all_vs_control=$REPO/docs/training/camera_dropout/runs/cmp_ctrl00_vs_drop30_all.json" \
    --attach "front_dead_vs_control=$REPO/docs/training/camera_dropout/runs/cmp_ctrl00_vs_drop30_front_dead.json" \
    --attach "back_dead_vs_control=$REPO/docs/training/camera_dropout/runs/cmp_ctrl00_vs_drop30_back_dead.json" \
    --attach "all_dark_vs_control=$REPO/docs/training/camera_dropout/runs/cmp_ctrl00_vs_drop30_all_dark.json" \
    --attach "all_vs_previous_8_slices=$REPO/docs/training/camera_dropout/runs/cmp_swift_vs_drop30_all.json" \
    --attach "all_vs_previous_32_slices=cmp_swift_vs_drop30_32.json" \
    --attach "cameras_missing_scores=$REPO/docs/training/camera_dropout/runs/scores_drop30.json"
