#!/usr/bin/env bash
# small_v3, seed 2, init = the shipped small_v2 image encoder, + the image class loss (weight 0.5); probe first.
set -euo pipefail
cd /work/runs
export OMP_NUM_THREADS=1 PATH=/work/main/.venv/bin:$PATH
OUT=fused_v3cls_w4_s2
COMMON="--data data60w4 --preset small_v3 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200 --seed 2 --out $OUT --image-class-weight 0.5"
if [ -f "$OUT/last.pt" ]; then
  streamdet-train $COMMON --resume "$OUT/last.pt"
else
  streamdet-train $COMMON --init /work/runs/small_v2_shipped_encoder.pt
fi
E=eval_$OUT; mkdir -p $E
python -m streamdet.benchmarks.image_bev_probe --checkpoint "$OUT/model.pt" --data val60w4 --split all --max-samples 120 --json "$E/probe.json"
streamdet-export --checkpoint "$OUT/model.pt" --out "$E/export"
for n in 8 32; do
  streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices $n --save-results "$E/res_$n" --json "$E/eval_$n.json"
done
streamdet-study drop-camera --export-dir "$E/export" --data val60w4 --split all --slices 8 --no-cameras --json "$E/gate_drop_cameras.json"
streamdet-study calib-noise --export-dir "$E/export" --data val60w4 --split all --slices 8 --level 5,50 --json "$E/gate_calib_noise.json"
