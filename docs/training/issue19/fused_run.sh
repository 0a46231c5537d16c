#!/usr/bin/env bash
# issue 19: one fused seed on world 4 (small_v2 = flat lifter since 6a749d5), image encoder from the image
# pretraining (pre_s0 step 4000, val mIoU 0.608), everything else from the seed. Resumes when last.pt exists.
#   fused_run.sh SEED THREADS [MAX_MINUTES]
set -uo pipefail
seed=$1; threads=$2; mm=${3:-600}
cd /work/main
source /work/runs/COMMON_w4.sh
export OMP_NUM_THREADS=$threads PATH=/work/main/.venv/bin:$PATH
name=fused_w4_s$seed
[ -f /work/runs/$name/model.pt ] && { echo "$name done"; exit 0; }
if [ -f /work/runs/$name/last.pt ]; then start=(--resume /work/runs/$name/last.pt)
else start=(--init /work/runs/pre_s0_step4000/encoder.pt); fi
echo "== $name start $(date) threads $threads ${start[*]}" >> /work/runs/$name.log
streamdet-train $COMMON --seed $seed --out /work/runs/$name "${start[@]}" --max-minutes $mm >> /work/runs/$name.log 2>&1
echo "== $name end $(date) rc=$?" >> /work/runs/$name.log
