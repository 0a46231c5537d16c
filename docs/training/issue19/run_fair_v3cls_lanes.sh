#!/usr/bin/env bash
# Issue 19, eighth session: the rest of run_fair_v3cls_rest.sh in two lanes instead of one. Started while
# LiDAR-only seed 2 trains (run_lidar_seed.sh 2, its own lane) and fused seeds 1 / 2 finish their gates
# (run_fair_v3cls_seed.sh 1 / 2): once seed 1's gates are done its core scores fused seed 0 at 8 / 32 slices;
# once everything is scored, the decision (run_fair_v3cls_decide.sh). Resumes when rerun.
set -euo pipefail
D=/work/main/docs/training/issue19
cd /work/runs
until [ -f eval_fused_v3fair_w4_s1/gate_calib_noise.json ]; do sleep 30; done
THREADS=1 bash $D/run_fair_v3cls_seed.sh 0
for f in eval_fused_v3fair_w4_s2/gate_calib_noise.json eval_lidar_w4_s2/eval_32.json; do
  until [ -f $f ]; do sleep 30; done
done
bash $D/run_fair_v3cls_decide.sh
