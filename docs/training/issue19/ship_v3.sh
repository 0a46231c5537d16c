#!/usr/bin/env bash
# Issue 19: ships the fair small_v3 + class-loss comparison once run_fair_v3cls_decide.sh has run: the best fused seed
# as models/weights/small.pt, the LiDAR-only seed 0 (unchanged weights) with the new evidence (the image pretraining's
# encoder is kept in models/weights/issue19/). Then set core/constants.py
# DEFAULT_PRESET = "small_v3" (the shipped file names its preset), rerun benchmarks/studies.sh, update the README.
set -euo pipefail
cd /work/main
P=.venv/bin/python
R=/work/runs
O=$R/cmp3v3
best=$(cat $O/best_seed)
DATA="training: streamdet-synth --out data60w4 --scenes 60 --seed 7 --resolution 480x270 (world 4; 48 scenes / 480 samples of its 'train' split, 2880 images for the image pretraining); evaluation: streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270 (all 600 samples, never trained on)"
PRE="streamdet-train-image --data data60w4 --preset small_v3 --out pre_v3_w4_s0 --steps 2500 --batch-size 8 --eval-every 500 --seed 0"
COMMON='streamdet-train --data data60w4 --steps 6000 --balanced --num-slices 8,8,32 --max-slices-per-sample 8 --lr 2e-3 --image-warmup 0 --checkpoint-every 200'
$P scripts/ship_weights.py --run $R/fused_v3fair_w4_s$best --eval $R/eval_fused_v3fair_w4_s$best --out models/weights/small.pt \
  --data-recipe "$DATA" \
  --recipe "$PRE; $COMMON --preset small_v3 --image-class-weight 0.5 --seed $best --init pre_v3_w4_s0/encoder.pt (docs/training/issue19/run_fair_v3cls_*.sh)" \
  --note "the best of issue 19's three fused seeds (0, 1, 2) of the fair small_v3 + image-class-loss schedule by the mean of its 8- and 32-slice mAP on val60w4" \
  --note "the comparison of the two sides uses all three seeds of each (evidence.compare_8_slices / compare_32_slices, the verdict in evidence.camera_claim), not this pair" \
  --note "without cameras this model does not fall back to LiDAR-only accuracy (see gates.gate_drop_cameras): on camera failure run small_lidar_only.pt" \
  --attach probe=$R/eval_fused_v3fair_w4_s$best/probe600.json \
  --attach compare_8_slices=$O/compare3_8.json --attach compare_32_slices=$O/compare3_32.json \
  --attach camera_claim=$O/camera_claim.json --attach eval_fp16_8_slices=$O/eval8_fp16.json \
  --attach eval_int8_8_slices=$O/eval8_int8.json --attach eval_int8_image_lane_8_slices=$O/eval8_int8lane.json
# the LiDAR-only weights are unchanged (their run folder is gone with an earlier machine): only the evidence of the
# comparison in its JSON is replaced by the new one
$P - "$O" <<'PY'
import json, sys
from pathlib import Path
o = Path(sys.argv[1])
p = Path("models/weights/small_lidar_only.json")
doc = json.loads(p.read_text())
doc.setdefault("evidence", {})
for key, name in (("compare_8_slices", "compare3_8.json"), ("compare_32_slices", "compare3_32.json"), ("camera_claim", "camera_claim.json")):
    doc["evidence"][key] = json.loads((o / name).read_text())
doc["notes"] = [n for n in doc.get("notes", []) if "compar" not in n] + [
    "evidence: issue 19's three-seed comparison against the fair small_v3 + image-class-loss fused seeds (small.pt's recipe)"]
p.write_text(json.dumps(doc, indent=1) + "\n")
PY
