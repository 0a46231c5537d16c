#!/usr/bin/env bash
# Issue 19, the third lane of the seventh session: once fused seed 1 has finished training (so that no more than
# three jobs share the two cores), LiDAR-only seed 2 (trained and scored), fused seed 0's scoring at 8 and 32 slices
# (its gates and probe are done), then, once run_fair_v3cls_seed.sh 1 and 2 have scored their seeds, the decision
# (run_fair_v3cls_decide.sh). Resumes when rerun.
set -euo pipefail
D=/work/main/docs/training/issue19
cd /work/runs
until [ -f fused_v3fair_w4_s1/model.pt ]; do sleep 30; done
THREADS=1 bash $D/run_lidar_seed.sh 2
THREADS=1 bash $D/run_fair_v3cls_seed.sh 0
for s in 1 2; do
  until [ -f eval_fused_v3fair_w4_s$s/gate_calib_noise.json ]; do sleep 30; done
done
bash $D/run_fair_v3cls_decide.sh
