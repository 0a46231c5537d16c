#!/usr/bin/env bash
# Device run: the issue-22 replay A/B (full vs phase-locked, int8 image lane and slices, nuScenes rates) pinned to
# two cores of the device host's CPU. The drives and the installed package go to $WORK (/tmp); $OUT gets cpu.txt,
# run.log-worthy output on stdout and ab.tar.gz: every replay's outputs, packed after the A/B ends or after AB_LIMIT_S
# seconds (default 480), whichever comes first, so a call leaves time to pack what it finished (a device call brings
# back only a few files: one archive, not the A/B's folder). The drives stay in $WORK: a second call on the still-warm
# machine can skip them (SKIP_SYNTH=1).
set -uo pipefail
export PYTHONUNBUFFERED=1 PYTHONSAFEPATH=1  # the checkout's streamdet/ folder must not shadow the installed package
PY=${PY:-python3}; SCENES=${SCENES:-8}; ROUNDS=${ROUNDS:-2}; WORK=${WORK:-/tmp/dev}
mkdir -p "$WORK/bin" "$OUT"
{ lscpu; grep -m1 flags /proc/cpuinfo; nproc; $PY -c "import onnxruntime,numpy,cv2,click;print('ort',onnxruntime.__version__,'numpy',numpy.__version__,'cv2',cv2.__version__)"; } > "$OUT/cpu.txt" 2>&1
$PY -m pip install -q --no-deps --no-build-isolation --no-compile --target "$WORK/sd" . > "$WORK/install.log" 2>&1 || { cat "$WORK/install.log"; exit 1; }
export PYTHONPATH="$WORK/sd"
rm -f "$WORK/bin/python"; printf '#!/bin/sh\nexec %s "$@"\n' "$(command -v $PY)" > "$WORK/bin/python"; chmod +x "$WORK/bin/python"  # a link would lose a venv's site-packages
for s in streamdet-replay streamdet-synth; do ln -sf "$WORK/sd/bin/$s" "$WORK/bin/$s"; done
sed -i "1s|.*|#!$(command -v $PY)|" "$WORK"/sd/bin/streamdet-*
# two logical CPUs on different physical cores: cpu0 and the first CPU that is not its SMT sibling
SIB=$(cat /sys/devices/system/cpu/cpu0/topology/thread_siblings_list)
SECOND=$($PY -c "
import sys
def expand(s):
    out=set()
    for part in s.split(','):
        a,_,b=part.partition('-'); out.update(range(int(a),int(b or a)+1))
    return out
sib=expand('$SIB'); import os
print(min(c for c in os.sched_getaffinity(0) if c not in sib))")
CPUS="0,$SECOND"; echo "pinned to CPUs $CPUS (cpu0 siblings: $SIB)" | tee -a "$OUT/cpu.txt"
if [ "${SKIP_SYNTH:-0}" != 1 ] || [ ! -d "$WORK/synth20" ]; then
  date; time "$WORK/bin/streamdet-synth" generate --out "$WORK/synth20" --scenes "$SCENES" --seed 11 --resolution 480x270 --sweeps-per-sample 10 --workers "$SCENES" --overwrite > "$WORK/synth.log" 2>&1 || { tail "$WORK/synth.log"; exit 1; }
fi
rm -rf "$WORK/ab"
date; DATA="$WORK/synth20" BIN="$WORK/bin" timeout "${AB_LIMIT_S:-480}" taskset -c "$CPUS" benchmarks/replay_ab.sh "$WORK/ab" "$ROUNDS" "1" \
  ${VARIANTS:-lite_full=.dev/export_lite,full,on,,int8 lite_pl=.dev/export_lite,phase-locked,on,,int8}
date; cat "$WORK/ab/table.md" 2>/dev/null || "$WORK/bin/python" -m streamdet.benchmarks.replay_table "$WORK/ab"
tar czf "$OUT/ab.tar.gz" -C "$WORK" ab
