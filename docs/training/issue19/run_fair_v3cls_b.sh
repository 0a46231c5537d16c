#!/usr/bin/env bash
# Issue 19, chain B (one CPU thread): the LiDAR-only seeds 1 and 2 of the fair schedule retrained (their runs were
# lost with an earlier machine; seed 0 is the shipped small_lidar_only.pt's run) and scored at 8 and 32 slices,
# then fused seed 1 once chain A's pretraining has written its encoder. Resumes when rerun.
set -euo pipefail
cd /work/runs
export OMP_NUM_THREADS=1 PATH=/work/main/.venv/bin:$PATH
E=eval_lidar_w4_s0; mkdir -p $E  # seed 0: the shipped weights are its model.pt
[ -f "$E/export/manifest.json" ] || streamdet-export --checkpoint /work/main/models/weights/small_lidar_only.pt --out "$E/export"
for n in 8 32; do
  [ -f "$E/eval_$n.json" ] || streamdet-eval --data val60w4 --split all --export-dir "$E/export" --slices $n --save-results "$E/res_$n" --json "$E/eval_$n.json"
done
for s in 1 2; do bash /work/main/docs/training/issue19/run_lidar_seed.sh $s; done  # trained (or restored) and scored
# then the fused seeds not trained yet (run_fair_v3cls_seed.sh restores the pretraining's encoder from the repository)
for s in 1 2; do
  [ -f "/work/main/models/weights/issue19/fused_v3fair_w4_s$s.pt" ] || bash /work/main/docs/training/issue19/run_fair_v3cls_seed.sh $s
done
