#!/usr/bin/env bash
# Issue 19, after the three fused seeds of run_fair_v3cls_seed.sh and the three LiDAR-only seeds are scored:
# the three-seed comparison at 8 and 32 slices, the verdict (camera_claim, with each seed's gate and 600-sample
# probe), then the best fused seed (mean of its 8- and 32-slice mAP) scored in fp16 / int8 / int8 image lane, ready
# for scripts/ship_weights.py. Writes /work/runs/cmp3v3/. Resumes: finished outputs are kept.
set -euo pipefail
cd /work/runs
export OMP_NUM_THREADS=1 PATH=/work/main/.venv/bin:$PATH
O=cmp3v3; mkdir -p $O
F=fused_v3fair_w4_s
for s in 0 1 2; do
  for f in eval_8.json eval_32.json probe600.json gate_drop_cameras.json gate_calib_noise.json; do
    [ -f eval_$F$s/$f ] || { echo "$0: eval_$F$s/$f missing: run run_fair_v3cls_seed.sh $s first" >&2; exit 1; }
  done
done
pids=()
for n in 8 32; do
  if [ ! -f $O/compare3_$n.json ]; then
    streamdet-eval --compare eval_lidar_w4_s0/res_$n,eval_lidar_w4_s1/res_$n,eval_lidar_w4_s2/res_$n \
      eval_${F}0/res_$n,eval_${F}1/res_$n,eval_${F}2/res_$n --bootstrap 1000 --json $O/compare3_$n.json > $O/compare3_$n.txt &
    pids+=($!)
  fi
done
for p in "${pids[@]}"; do wait "$p"; done
gates=()
for s in 0 1 2; do
  gates+=(--gate-drop eval_$F$s/gate_drop_cameras.json --gate-noise eval_$F$s/gate_calib_noise.json --probe eval_$F$s/probe600.json)
done
python -m streamdet.benchmarks.camera_claim --compare8 $O/compare3_8.json --compare32 $O/compare3_32.json "${gates[@]}" \
  --json $O/camera_claim.json | tee $O/camera_claim.txt
best=$(python - <<'PY'
import json
scores = {s: sum(json.load(open(f"eval_fused_v3fair_w4_s{s}/eval_{n}.json"))["mAP"] for n in (8, 32)) / 2 for s in (0, 1, 2)}
print(max(scores, key=scores.get))
PY
)
echo "best fused seed: $best"; echo $best > $O/best_seed
E=eval_$F$best
[ -f $O/export_q/manifest.json ] || streamdet-export --checkpoint $F$best/model.pt --out $O/export_q --fp16 --int8 --calibration-data data60w4
[ -f $O/eval8_fp16.json ] || streamdet-eval --data val60w4 --split all --export-dir $O/export_q --slices 8 --precision fp16 --json $O/eval8_fp16.json
[ -f $O/eval8_int8.json ] || streamdet-eval --data val60w4 --split all --export-dir $O/export_q --slices 8 --precision int8 --json $O/eval8_int8.json
[ -f $O/eval8_int8lane.json ] || streamdet-eval --data val60w4 --split all --export-dir $O/export_q --slices 8 --image-precision int8 --json $O/eval8_int8lane.json
echo "decided; ship with ship_v3.sh"
