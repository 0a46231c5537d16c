#!/usr/bin/env bash
# Issue 19: waits for a run's model.pt in /work/runs and keeps it in the repository at once (weights in
# models/weights/issue19/, config and loss log in docs/training/issue19/), so a lost machine loses no finished seed.
#   keep_run.sh RUN   (e.g. fused_v3fair_w4_s1)
set -u
R=$1
until [ -f /work/runs/$R/model.pt ]; do sleep 20; done
sleep 10  # the trainer writes model.pt, then its last metrics
cd /work/main
cp /work/runs/$R/model.pt models/weights/issue19/$R.pt
cp /work/runs/$R/config.json docs/training/issue19/${R}_config.json
cp /work/runs/$R/metrics.jsonl docs/training/issue19/${R}_metrics.jsonl
for i in $(seq 30); do  # another commit may hold the index lock
  git add models/weights/issue19/$R.pt docs/training/issue19/${R}_config.json docs/training/issue19/${R}_metrics.jsonl \
    && git commit -qm "issue 19: $R finished (6000 steps of the fair schedule), kept in models/weights/issue19/" \
      -- models/weights/issue19/$R.pt docs/training/issue19/${R}_config.json docs/training/issue19/${R}_metrics.jsonl \
    && break
  sleep 10
done
echo "kept $R"
