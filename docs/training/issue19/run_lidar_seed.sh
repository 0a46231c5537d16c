#!/usr/bin/env bash
# Issue 19, one LiDAR-only seed of the fair schedule (small_v2 without the image lane, same steps, data and crop as
# the fused seeds) and its scoring at 8 and 32 slices on all 600 val60w4 samples. Resumes when rerun; a seed kept in
# models/weights/issue19/ is restored instead of retrained.
#   [THREADS=N] run_lidar_seed.sh SEED
set -euo pipefail
s=$1
cd /work/runs
export OMP_NUM_THREADS=${THREADS:-1} PATH=/work/main/.venv/bin:$PATH
COMMON="--data data60w4 --preset small_v2 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200"
OUT=lidar_w4_s$s
KEPT=/work/main/models/weights/issue19/$OUT.pt
if [ ! -f "$OUT/model.pt" ] && [ -f "$KEPT" ]; then mkdir -p "$OUT" && cp "$KEPT" "$OUT/model.pt"; fi
if [ ! -f "$OUT/model.pt" ]; then
  if [ -f "$OUT/last.pt" ]; then streamdet-train $COMMON --seed $s --out $OUT --no-image --resume "$OUT/last.pt"
  else streamdet-train $COMMON --seed $s --out $OUT --no-image; fi
fi
E=eval_$OUT; mkdir -p $E
[ -f "$E/export/manifest.json" ] || streamdet-export --checkpoint "$OUT/model.pt" --out "$E/export"
for n in 8 32; do
  [ -f "$E/eval_$n.json" ] || streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices $n --save-results "$E/res_$n" --json "$E/eval_$n.json"
done
echo "scored $OUT"
