#!/usr/bin/env bash
# Issue 19, the fair schedule of small_v3 + the image class loss, chain A (one CPU thread):
# the image pretraining on the training world itself (data60w4), then fused seed 0 from its encoder, then its scoring.
# Every step resumes: rerun the script after an interruption.
set -euo pipefail
cd /work/runs
export OMP_NUM_THREADS=1 PATH=/work/main/.venv/bin:$PATH
PRE=pre_v3_w4_s0
if ! grep -q '"finished": true' "$PRE/result.json" 2>/dev/null; then
  args=(--data data60w4 --preset small_v3 --out $PRE --steps 2500 --batch-size 8 --eval-every 500 --seed 0)
  if [ -f "$PRE/last.pt" ]; then streamdet-train-image "${args[@]}" --resume "$PRE/last.pt"; else streamdet-train-image "${args[@]}"; fi
fi
bash /work/main/docs/training/issue19/run_fair_v3cls_seed.sh 0
