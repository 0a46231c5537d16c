#!/usr/bin/env bash
# Does a change to the camera renderer keep every output byte? (issue 18's speed work must.)
#
#   benchmarks/synth_render_identity.sh [BASE_REVISION]
#
# Copies the working tree's package into a scratch folder (others may keep editing the world meanwhile), then
# generates the same 2-scene dataset (20 key frames, 480x270, 1 worker) twice against that copy: once with the
# renderer files (data/synth_render*.py) of BASE_REVISION (default HEAD), once with the working tree's, and compares
# the SHA-256 of every file written (images, masks, LiDAR, tables). Prints IDENTICAL or the differing files and
# exits 1 on a difference. Both runs print their CPU seconds per key frame (one pair: not a benchmark).
set -euo pipefail
BASE=${1:-HEAD}
ROOT=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
PY=${PYTHON:-$ROOT/.venv/bin/python}
SCRATCH=$(mktemp -d)
trap 'rm -rf "$SCRATCH"' EXIT

snapshot() {  # $1: folder -> a PYTHONPATH folder holding a copy of the working tree's streamdet package
  mkdir -p "$1/src" "$1/pkg"
  cp -r "$ROOT/toplevel" "$1/pkg/streamdet"  # the package root's folder (pyproject.toml maps it to streamdet)
  for d in calibration core models export runtime_ort benchmarks data training evaluation studies bag replay; do
    if [ -d "$ROOT/$d" ]; then cp -r "$ROOT/$d" "$1/src/$d"; ln -s "$1/src/$d" "$1/pkg/streamdet/$d"; fi
  done
}
snapshot "$SCRATCH/new"
snapshot "$SCRATCH/base"
rm -f "$SCRATCH"/base/src/data/synth_render*.py
for f in $(git -C "$ROOT" ls-tree --name-only "$BASE" data/ | grep '^data/synth_render.*\.py$'); do
  git -C "$ROOT" show "$BASE:$f" > "$SCRATCH/base/src/$f"
done

GEN='
import hashlib, json, pathlib, sys, time
from streamdet.data.synth_writer import SynthConfig, generate_dataset
out = pathlib.Path(sys.argv[1])
cpu = time.process_time()
s = generate_dataset(out, SynthConfig(num_scenes=2, seed=7, resolution=(480, 270)))
cpu = (time.process_time() - cpu) / s.num_samples
hashes = {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.rglob("*")) if p.is_file()}
(out.parent / (out.name + ".json")).write_text(json.dumps(hashes, indent=0))
print(f"{sys.argv[2]}: {len(hashes)} files, CPU {cpu:.3f} s per key frame")
'
for which in base new; do
  (cd "$SCRATCH" && PYTHONPATH="$SCRATCH/$which/pkg" "$PY" -c "$GEN" "$SCRATCH/out-$which" "$which")
done
"$PY" - "$SCRATCH/out-base.json" "$SCRATCH/out-new.json" <<'EOF'
import json, sys
base, new = (json.load(open(p)) for p in sys.argv[1:3])
differ = sorted(k for k in base.keys() | new.keys() if base.get(k) != new.get(k))
if differ:
    print(f"DIFFERENT: {len(differ)} of {len(base)} files, e.g. {differ[:5]}")
    sys.exit(1)
print(f"IDENTICAL: all {len(base)} files")
EOF
