"""The CPU as this process's kernels see it: the model name and SIMD flags of /proc/cpuinfo, less what a CPUID mask hides.

onnxruntime, numpy and OpenCV pick their kernels from the CPUID instruction, not from /proc/cpuinfo (which always
shows the silicon). ``benchmarks/avx2_only.sh`` runs a command with a CPUID mask (``benchmarks/cpuid_mask/``,
LD_PRELOAD): the instruction reports an AVX2-only CPU (no AVX-512, AVX-VNNI or AMX), so every library takes its AVX2
code path, and the mask writes its name into ``STREAMDET_CPUID_MASK``. Reports read the flags here, so a run under
the mask names the instruction set its kernels used.

Also how many CPUs this process may use (``usable_cpus``: affinity and cgroup quota, the one count every default
thread count and every report's "usable" figure comes from) and the physical cores among them (``physical_cores``).
Standard library only: every package imports core.
"""

from __future__ import annotations

import os
import platform
import re
from collections.abc import Iterable
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


def _cpuinfo_fields(text: str):
    """(key, value) of each "key : value" line of a /proc/cpuinfo text, both stripped, in order."""
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            yield key.strip(), value.strip()


def read_cpuinfo(path: str | Path = CPUINFO) -> tuple[str | None, frozenset[str]]:
    """(model name, flags) of the first processor in a /proc/cpuinfo text; (None, empty) where it cannot be read."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return None, frozenset()
    model, flags = None, None
    for key, value in _cpuinfo_fields(text):
        if key == "model name" and model is None and value:
            model = value
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


# ---- how many CPUs this process may use ------------------------------------------------------------------------
CGROUP_ROOT = Path("/sys/fs/cgroup")  # the cgroup namespace's root: a container's own cgroup
_INTEGER = re.compile(r"-?[0-9]{1,19}")  # ASCII digits only (int() also takes "1_000" and other scripts' digits)


def _quota_cpus(quota: str, period: str) -> int | None:
    """ceil(quota / period), at least 1; None for no quota (a quota <= 0: cgroup v1's -1) or text that is no integer."""
    if _INTEGER.fullmatch(quota) is None or _INTEGER.fullmatch(period) is None:
        return None
    q, p = int(quota), int(period)
    if q <= 0 or p <= 0:
        return None
    return max(1, -(-q // p))


def cgroup_cpu_limit(cpu_max: str | None = None, cfs_quota_us: str | None = None, cfs_period_us: str | None = None) -> int | None:
    """The CPUs a cgroup CPU quota allows, from the files' texts: cgroup v2's ``cpu.max`` ("max 100000": no quota,
    "200000 100000": 2 CPUs) when given, else cgroup v1's ``cpu.cfs_quota_us`` and ``cpu.cfs_period_us``.
    ceil(quota / period), at least 1; None without a quota or for text that cannot be parsed (the quota is ignored)."""
    if cpu_max is not None:
        fields = cpu_max.split()
        if len(fields) != 2 or fields[0] == "max":
            return None
        return _quota_cpus(*fields)
    if cfs_quota_us is None or cfs_period_us is None:
        return None
    return _quota_cpus(cfs_quota_us.strip(), cfs_period_us.strip())


def _read(path: Path) -> str | None:
    try:
        return path.read_text(errors="replace")
    except (OSError, ValueError):
        return None


def read_cgroup_cpu_limit(root: str | Path | None = None) -> int | None:
    """``cgroup_cpu_limit`` of the cgroup files under ``root`` (v2 ``cpu.max``, else v1 ``cpu/cpu.cfs_*``); None where
    none can be read. ``root`` None: CGROUP_ROOT."""
    root = Path(CGROUP_ROOT if root is None else root)
    cpu_max = _read(root / "cpu.max")
    if cpu_max is not None:
        return cgroup_cpu_limit(cpu_max)
    v1 = root / "cpu"
    return cgroup_cpu_limit(None, _read(v1 / "cpu.cfs_quota_us"), _read(v1 / "cpu.cfs_period_us"))


def _scheduler_cpus() -> int:
    """The CPUs the scheduler lets this process run on: os.process_cpu_count() (Python 3.13+), else the affinity
    mask's size, else os.cpu_count(), else 1."""
    process_cpu_count = getattr(os, "process_cpu_count", None)
    if process_cpu_count is not None:
        n = process_cpu_count()
        if n:
            return n
    if hasattr(os, "sched_getaffinity"):
        try:
            n = len(os.sched_getaffinity(0))
        except OSError:
            n = 0
        if n:
            return n
    return os.cpu_count() or 1


def usable_cpus(cgroup_root: str | Path | None = None) -> int:
    """The CPUs this process may use: those the scheduler allows (affinity, ``_scheduler_cpus``), at most what a cgroup
    CPU quota allows (docker --cpus, a Kubernetes CPU limit); at least 1. The one count every default thread count and
    every report's "usable" figure comes from. ``cgroup_root`` None: CGROUP_ROOT."""
    cpus = _scheduler_cpus()
    limit = read_cgroup_cpu_limit(CGROUP_ROOT if cgroup_root is None else cgroup_root)
    return max(1, cpus if limit is None else min(cpus, limit))


# ---- physical cores and the CPU's vendor and family (the benchmark's peak estimate) ----------------------------
SYS_CPU = Path("/sys/devices/system/cpu")
MAX_CPU_ID = 1 << 16  # past any Linux CPU number (the kernel's NR_CPUS tops out at 8192); bounds a parsed range
_CPU_RANGE = re.compile(r"([0-9]+)(?:-([0-9]+))?")


def parse_cpu_list(text: str) -> frozenset[int] | None:
    """The CPUs of a Linux cpu list ("0-3,8,10-11", as in topology/thread_siblings_list); None for text that is
    not one (empty, a reversed or unbounded range, a negative number)."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        found = _CPU_RANGE.fullmatch(part.strip())
        if found is None:
            return None
        first = int(found[1])
        last = first if found[2] is None else int(found[2])
        if not first <= last < MAX_CPU_ID:
            return None
        cpus.update(range(first, last + 1))
    return frozenset(cpus)


def count_cores(sibling_lists: Iterable[str]) -> int | None:
    """Physical cores among logical CPUs given each one's topology/thread_siblings_list text: SMT threads of one core
    share the list. None when there is none or one cannot be parsed."""
    cores = set()
    for text in sibling_lists:
        siblings = parse_cpu_list(text)
        if siblings is None:
            return None
        cores.add(siblings)
    return len(cores) or None


def cpuinfo_cores(text: str) -> int | None:
    """Physical cores of a /proc/cpuinfo text: its distinct (physical id, core id) pairs; None without core ids."""
    cores, package = set(), ""
    for key, value in _cpuinfo_fields(text):
        if key == "processor":
            package = ""
        elif key == "physical id":
            package = value
        elif key == "core id":
            cores.add((package, value))
    return len(cores) or None


def _scheduler_cpu_ids() -> list[int]:
    if hasattr(os, "sched_getaffinity"):
        try:
            return sorted(os.sched_getaffinity(0))
        except OSError:
            pass
    return list(range(os.cpu_count() or 1))


def physical_cores(sys_cpu: str | Path | None = None, cpuinfo: str | Path = CPUINFO) -> int | None:
    """Physical cores among the CPUs this process may run on (its affinity), from /sys topology; where /sys has
    none, those of the whole machine in /proc/cpuinfo; None where neither says. ``sys_cpu`` None: SYS_CPU."""
    sys_cpu = Path(SYS_CPU if sys_cpu is None else sys_cpu)
    texts = [_read(sys_cpu / f"cpu{i}" / "topology" / "thread_siblings_list") for i in _scheduler_cpu_ids()]
    if texts and all(t is not None for t in texts):
        found = count_cores(t for t in texts if t is not None)
        if found is not None:
            return found
    text = _read(Path(cpuinfo))
    return None if text is None else cpuinfo_cores(text)


def cpu_vendor_family(path: str | Path = CPUINFO) -> tuple[str | None, int | None]:
    """(vendor_id, cpu family) of the first processor in a /proc/cpuinfo text ("AuthenticAMD", 25); None for what it
    does not say or cannot be read."""
    text = _read(Path(path))
    vendor, family = None, None
    for key, value in _cpuinfo_fields(text or ""):
        if not value:
            continue
        if key == "vendor_id" and vendor is None:
            vendor = value
        elif key == "cpu family" and family is None:
            family = int(value) if value.isascii() and value.isdigit() and len(value) < 6 else None
    return vendor, family
