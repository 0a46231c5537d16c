#!/usr/bin/env bash
# Run a command as on an AVX2-only x86-64 CPU: CPUID reports no AVX-512, AVX-VNNI or AMX to it and to every process
# it starts, so onnxruntime, numpy and OpenCV take their AVX2 kernels (benchmarks/cpuid_mask/avx2_only.c says how
# and what it leaves out). The instruction set is the AVX2 part's; the clock, caches and execution units stay this
# machine's, so speeds are not an AVX2 part's speeds.
#   benchmarks/avx2_only.sh COMMAND [ARGS...]
# e.g. DATA=out/r21/synth20 benchmarks/avx2_only.sh benchmarks/replay_ab.sh out/avx2 3 1 full=EXP,full,on,,int8
# Python's faulthandler must stay off under the mask (PYTHONFAULTHANDLER is cleared; pytest: -p no:faulthandler).
# Needs Linux on x86-64 with CPUID faulting (/proc/cpuinfo lists cpuid_fault) and a C compiler (CC, default cc); the
# mask is built once into STREAMDET_CACHE (default ${XDG_CACHE_HOME:-~/.cache}/streamdet) and rebuilt when its
# source changes. Reports name the mask (streamdet.core.cpu: STREAMDET_CPUID_MASK=avx2).
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: $0 COMMAND [ARGS...]" >&2; exit 2; }
[ "$(uname -s)" = Linux ] || {
  echo "$0: CPUID masks need Linux (CPUID faulting through arch_prctl ARCH_SET_CPUID), this is $(uname -s)" >&2; exit 2; }
[ "$(uname -m)" = x86_64 ] || { echo "$0: CPUID masks need an x86-64 CPU, this is $(uname -m)" >&2; exit 2; }
grep -qw cpuid_fault /proc/cpuinfo || {
  echo "$0: this CPU or hypervisor offers no CPUID faulting (no cpuid_fault in /proc/cpuinfo): cannot mask" >&2; exit 2; }
SRC="$(cd "$(dirname "$0")" && pwd)/cpuid_mask/avx2_only.c"
CACHE=${STREAMDET_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/streamdet}
LIB="$CACHE/cpuid_mask_avx2_$(cksum < "$SRC" | cut -d' ' -f1).so"  # named by the source: an edit builds afresh
if [ ! -f "$LIB" ]; then
  mkdir -p "$CACHE"
  CC=${CC:-cc}
  command -v "$CC" > /dev/null || { echo "$0: no C compiler ($CC) to build $SRC" >&2; exit 2; }
  "$CC" -O2 -Wall -Wextra -Werror -shared -fPIC -o "$LIB.tmp.$$" "$SRC"
  mv "$LIB.tmp.$$" "$LIB"
fi
# Python's faulthandler installs its own SIGSEGV handler, which then receives the CPUID faults and kills the process
# (exit 139): PYTHONFAULTHANDLER is cleared here; pytest enables faulthandler itself, so run it with -p no:faulthandler.
if [ -n "${PYTHONFAULTHANDLER:-}" ]; then
  echo "$0: PYTHONFAULTHANDLER unset (faulthandler would take the CPUID faults the mask answers)" >&2
  unset PYTHONFAULTHANDLER
fi
prev=""
for arg in "$@"; do
  case "$prev $arg" in
    "-X faulthandler"*|"-X dev"|*" -Xfaulthandler"*|*" -Xdev")
      echo "$0: '$prev $arg' enables Python's faulthandler, which takes the CPUID faults the mask answers: drop it" >&2
      exit 2 ;;
  esac
  prev=$arg
done
export LD_PRELOAD="$LIB${LD_PRELOAD:+:$LD_PRELOAD}"
exec "$@"
