"""The CPU as this process's kernels see it: the model name and SIMD flags of /proc/cpuinfo, less what a CPUID mask hides.

onnxruntime, numpy and OpenCV pick their kernels from the CPUID instruction, not from /proc/cpuinfo (which always
shows the silicon). ``benchmarks/avx2_only.sh`` runs a command with a CPUID mask (``benchmarks/cpuid_mask/``,
LD_PRELOAD): the instruction reports an AVX2-only CPU (no AVX-512, AVX-VNNI or AMX), so every library takes its AVX2
code path, and the mask writes its name into ``STREAMDET_CPUID_MASK``. Reports read the flags here, so a run under
the mask names the instruction set its kernels used.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

CPUID_MASK_ENV = "STREAMDET_CPUID_MASK"  # set by the mask itself (its constructor), inherited by child processes
CPUINFO = Path("/proc/cpuinfo")
# /proc/cpuinfo flags above x86-64-v3 (AVX2, FMA) that the "avx2" mask hides: the CPUID bits benchmarks/cpuid_mask
# clears, by the names Linux gives them
_ABOVE_AVX2 = ("avx_vnni", "avx_ifma", "avx_vnni_int8", "avx_ne_convert", "avx_vnni_int16")


def _hidden_by_avx2(flag: str) -> bool:
    return flag.startswith(("avx512", "amx", "avx10")) or flag in _ABOVE_AVX2


MASKS = {"avx2": _hidden_by_avx2}  # mask name -> which /proc/cpuinfo flags it hides


def cpuid_mask(environ: dict[str, str] | None = None) -> str | None:
    """The CPUID mask this process runs under (``"avx2"``), None without one; an unknown name raises."""
    name = (os.environ if environ is None else environ).get(CPUID_MASK_ENV, "")
    if not name:
        return None
    if name not in MASKS:
        raise ValueError(f"{CPUID_MASK_ENV}={name!r} names no known CPUID mask (known: {', '.join(sorted(MASKS))})")
    return name


def read_cpuinfo(path: str | Path = CPUINFO) -> tuple[str | None, frozenset[str]]:
    """(model name, flags) of the first processor in a /proc/cpuinfo text; (None, empty) where it cannot be read."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return None, frozenset()
    model, flags = None, None
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            continue
        key = key.strip()
        if key == "model name" and model is None and value.strip():
            model = value.strip()
        elif key == "flags" and flags is None:
            flags = frozenset(value.split())
    return model, flags or frozenset()


def cpu_model(path: str | Path = CPUINFO) -> str:
    """The CPU's model name (platform.processor() where /proc/cpuinfo has none)."""
    model, _ = read_cpuinfo(path)
    return model or platform.processor() or platform.machine() or "unknown CPU"


def cpu_flags(path: str | Path = CPUINFO, environ: dict[str, str] | None = None) -> frozenset[str]:
    """The /proc/cpuinfo flags the kernels of this process can see: those of the silicon less the CPUID mask's."""
    _, flags = read_cpuinfo(path)
    mask = cpuid_mask(environ)
    if mask is None:
        return flags
    hidden = MASKS[mask]
    return frozenset(f for f in flags if not hidden(f))


# The SIMD flags that decide which kernels numpy, OpenCV, onnxruntime and PyTorch pick, in the order reports list them.
KERNEL_FLAGS = ("avx", "avx2", "fma", "f16c", "avx512f", "avx512_bf16", "avx512_fp16", "avx512_vnni", "avx_vnni", "amx_tile")


def kernel_flags(path: str | Path = CPUINFO, environ: dict[str, str] | None = None) -> tuple[str, ...]:
    """Those of ``KERNEL_FLAGS`` the kernels of this process can see (``cpu_flags``), in that order."""
    visible = cpu_flags(path, environ)
    return tuple(f for f in KERNEL_FLAGS if f in visible)
