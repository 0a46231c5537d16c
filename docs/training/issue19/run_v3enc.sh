#!/usr/bin/env bash
# usage: run_v3enc.sh PRESET SEED OUT   (fused, init = the shipped small_v2 image encoder; resumes from OUT/last.pt)
set -euo pipefail
cd /work/runs
export OMP_NUM_THREADS=1
P=$1; S=$2; OUT=$3
COMMON="--data data60w4 --preset $P --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200 --seed $S --out $OUT"
if [ -f "$OUT/last.pt" ]; then
  /work/main/.venv/bin/streamdet-train $COMMON --resume "$OUT/last.pt"
else
  /work/main/.venv/bin/streamdet-train $COMMON --init /work/runs/small_v2_shipped_encoder.pt
fi
PATH=/work/main/.venv/bin:$PATH bash /work/main/scripts/issue19_eval.sh "$OUT" val60w4 "eval_$OUT"
/work/main/.venv/bin/python -m streamdet.benchmarks.image_bev_probe --checkpoint "$OUT/model.pt" --data val60w4 --split all --max-samples 120 --json "eval_$OUT/probe.json"
