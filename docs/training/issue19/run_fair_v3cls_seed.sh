#!/usr/bin/env bash
# Issue 19, one fused seed of the fair schedule: small_v3 + the image class loss (weight 0.5), image encoder from
# pre_v3_w4_s0 (the image pretraining on data60w4), cameras on from the first step, then its scoring on all 600
# val60w4 samples (8 and 32 slices, the image-use gate, the probe on 600 samples). Resumes when rerun.
#   [THREADS=N] run_fair_v3cls_seed.sh SEED   (N torch / onnxruntime threads; default 1)
set -euo pipefail
s=$1
cd /work/runs
export OMP_NUM_THREADS=${THREADS:-1} PATH=/work/main/.venv/bin:$PATH
OUT=fused_v3fair_w4_s$s
if [ ! -f pre_v3_w4_s0/encoder.pt ]; then  # a new machine: the pretraining's encoder is kept in the repository
  mkdir -p pre_v3_w4_s0 && cp /work/main/models/weights/issue19/pre_v3_w4_s0_encoder.pt pre_v3_w4_s0/encoder.pt
fi
COMMON="--data data60w4 --preset small_v3 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200 --seed $s --out $OUT --image-class-weight 0.5"
KEPT=/work/main/models/weights/issue19/$OUT.pt  # a finished seed kept in the repository (its config and loss in docs)
if [ ! -f "$OUT/model.pt" ] && [ -f "$KEPT" ]; then
  mkdir -p "$OUT" && cp "$KEPT" "$OUT/model.pt"
  cp "/work/main/docs/training/issue19/${OUT}_config.json" "$OUT/config.json"
  cp "/work/main/docs/training/issue19/${OUT}_metrics.jsonl" "$OUT/metrics.jsonl"
fi
if [ ! -f "$OUT/model.pt" ]; then
  if [ -f "$OUT/last.pt" ]; then
    streamdet-train $COMMON --resume "$OUT/last.pt"
  else
    streamdet-train $COMMON --init pre_v3_w4_s0/encoder.pt
  fi
fi
E=eval_$OUT; mkdir -p $E
[ -f "$E/export/manifest.json" ] || streamdet-export --checkpoint "$OUT/model.pt" --out "$E/export"
for n in 8 32; do
  [ -f "$E/eval_$n.json" ] || streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices $n --save-results "$E/res_$n" --json "$E/eval_$n.json"
done
[ -f "$E/probe600.json" ] || python -m streamdet.benchmarks.image_bev_probe --checkpoint "$OUT/model.pt" --data val60w4 --split all --max-samples 600 --json "$E/probe600.json"
[ -f "$E/gate_drop_cameras.json" ] || streamdet-study drop-camera --export-dir "$E/export" --data val60w4 --split all --slices 8 --no-cameras --json "$E/gate_drop_cameras.json"
[ -f "$E/gate_calib_noise.json" ] || streamdet-study calib-noise --export-dir "$E/export" --data val60w4 --split all --slices 8 --level 5,50 --json "$E/gate_calib_noise.json"
echo "scored $OUT"
