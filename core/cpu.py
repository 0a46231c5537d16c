"""The CPU as this process's kernels see it: its model and SIMD flags, less what a CPUID mask hides.

onnxruntime, numpy and OpenCV pick their kernels from the CPUID instruction, not from /proc/cpuinfo (which always
shows the silicon). ``benchmarks/avx2_only.sh`` runs a command with a CPUID mask (``benchmarks/cpuid_mask/``,
LD_PRELOAD): the instruction reports an AVX2-only CPU (no AVX-512, AVX-VNNI or AMX), so every library takes its AVX2
code path, and the mask writes its name into ``STREAMDET_CPUID_MASK``. Reports read the flags here, so a run under
the mask names the instruction set its kernels used; a variable that names a mask the process's CPUID contradicts
(set by hand, or inherited without the LD_PRELOAD) is refused rather than reported (``cpuid_mask``).

The model and flags come from /proc/cpuinfo on Linux: x86's ``model name`` and ``flags``, aarch64's ``CPU
implementer`` / ``CPU part`` and ``Features``, POWER's ``cpu``. Where it has no flags (no /proc: macOS, Windows;
POWER), numpy's CPU feature table stands in (``numpy_cpu_features``: what numpy's own dispatch read from CPUID);
where neither can be read the flags are unknown, and reports say so rather than "none of" them (``cpu_line``).

Also how many CPUs this process may use (``usable_cpus``: affinity and cgroup quota, the one count every default
thread count and every report's "usable" figure comes from) and the physical cores among them (``physical_cores``).
Standard library only at import time: every package imports core (numpy, a base dependency, is imported inside the
functions that read its table).
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

CPUID_MASK_ENV = "STREAMDET_CPUID_MASK"  # set by the mask itself (its constructor), inherited by child processes
CPUINFO = Path("/proc/cpuinfo")
# /proc/cpuinfo flags above x86-64-v3 (AVX2, FMA) that the "avx2" mask hides: the CPUID bits benchmarks/cpuid_mask
# clears, by the names Linux gives them
_ABOVE_AVX2 = ("avx_vnni", "avx_ifma", "avx_vnni_int8", "avx_ne_convert", "avx_vnni_int16")


def _hidden_by_avx2(flag: str) -> bool:
    return flag.startswith(("avx512", "amx", "avx10")) or flag in _ABOVE_AVX2


MASKS = {"avx2": _hidden_by_avx2}  # mask name -> which /proc/cpuinfo flags it hides


def _avx2_mask_contradicted(features: Mapping[str, bool]) -> str | None:
    """What in numpy's CPU feature table shows the "avx2" mask is not in effect (AVX-512 still reported, or no AVX2
    at all: not an x86 CPU the mask could make AVX2-only); None where it agrees or the table does not say."""
    if "AVX2" not in features:
        return None
    above = sorted((k for k, v in features.items() if k.startswith("AVX512") and v is True), key=lambda k: (k != "AVX512F", k))
    if above:
        more = f" and {len(above) - 3} more" if len(above) > 3 else ""
        return f"still reports {', '.join(above[:3])}{more}"
    if features["AVX2"] is not True:
        return "reports no AVX2"
    return None


# mask name -> what in numpy's CPU feature table contradicts it (None: nothing does)
MASK_CONTRADICTIONS = {"avx2": _avx2_mask_contradicted}


def numpy_cpu_features() -> dict[str, bool] | None:
    """numpy's CPU feature table (``__cpu_features__``: "AVX2" -> True, ...), the features numpy's dispatch found with
    CPUID in this process (so a CPUID mask shows in it); None where numpy or its table cannot be imported. numpy is
    imported here, not at module level: core stays importable without it."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__  # numpy >= 2
    except ImportError:
        try:
            from numpy.core._multiarray_umath import __cpu_features__  # numpy 1.x
        except ImportError:
            return None
    return dict(__cpu_features__)


def _features(features: Mapping[str, bool] | None) -> Mapping[str, bool]:
    """``features`` as given, or this process's numpy table where None (empty where numpy has none)."""
    if features is not None:
        return features
    return numpy_cpu_features() or {}


def cpuid_mask(environ: Mapping[str, str] | None = None, features: Mapping[str, bool] | None = None) -> str | None:
    """The CPUID mask this process runs under (``"avx2"``), None without one.

    The name comes from ``STREAMDET_CPUID_MASK`` (``environ``; None: os.environ), and is checked against the CPUID the
    process sees, numpy's CPU feature table (``features``; None: this process's ``numpy_cpu_features``, {}: no
    table): a variable set by hand, or inherited by a process that did not inherit the mask's LD_PRELOAD, would make
    every report name an instruction set its kernels did not use. Raises ValueError for an unknown name and for a
    mask the table contradicts; where there is no table, the variable is trusted."""
    name = (os.environ if environ is None else environ).get(CPUID_MASK_ENV, "")
    if not name:
        return None
    if name not in MASKS:
        raise ValueError(f"{CPUID_MASK_ENV}={name!r} names no known CPUID mask (known: {', '.join(sorted(MASKS))})")
    contradiction = MASK_CONTRADICTIONS[name](_features(features))
    if contradiction is not None:
        raise ValueError(
            f"{CPUID_MASK_ENV}={name!r}, but the mask is not in effect: this process's CPUID {contradiction} (numpy's "
            "CPU feature table). The variable was set by hand, or inherited without the LD_PRELOAD of "
            "benchmarks/avx2_only.sh: unset it, or run the command under benchmarks/avx2_only.sh"
        )
    return name


def _cpuinfo_fields(text: str):
    """(key, value) of each "key : value" line of a /proc/cpuinfo text, both stripped, in order."""
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            yield key.strip(), value.strip()


# aarch64's "CPU implementer" / "CPU part" (the MIDR register's fields, as Linux's arch/arm64 cputype.h names them):
# a few common ones by name; any other is printed by its numbers
ARM_IMPLEMENTERS = {0x41: "ARM", 0x4E: "NVIDIA", 0x51: "Qualcomm", 0x61: "Apple", 0xC0: "Ampere"}
ARM_PARTS = {
    (0x41, 0xD03): "Cortex-A53",
    (0x41, 0xD05): "Cortex-A55",
    (0x41, 0xD08): "Cortex-A72",
    (0x41, 0xD0B): "Cortex-A76",
    (0x41, 0xD0C): "Neoverse N1",
    (0x41, 0xD40): "Neoverse V1",
    (0x41, 0xD49): "Neoverse N2",
    (0x41, 0xD4F): "Neoverse V2",
}
_HEX = re.compile(r"0[xX][0-9a-fA-F]{1,8}")
_GENERIC_ARM = re.compile(r"ARMv[0-9]")  # the "model name" some kernels give any ARM core


def arm_core_name(implementer: str, part: str) -> str | None:
    """The core that aarch64's ``CPU implementer`` and ``CPU part`` texts name ("0x41", "0xd0c" -> "ARM Neoverse
    N1"); an unknown part of a known implementer by its number ("Apple part 0x23"), an unknown implementer by both
    ("ARM implementer 0x42 part 0x516"); None for text that is not a hexadecimal number."""
    if _HEX.fullmatch(implementer) is None or _HEX.fullmatch(part) is None:
        return None
    imp, prt = int(implementer, 16), int(part, 16)
    vendor = ARM_IMPLEMENTERS.get(imp)
    if vendor is None:
        return f"ARM implementer {imp:#x} part {prt:#x}"
    name = ARM_PARTS.get((imp, prt))
    return f"{vendor} {name}" if name else f"{vendor} part {prt:#x}"


@dataclass(frozen=True)
class ProcCpuinfo:
    """What a /proc/cpuinfo text says of the CPU.

    ``model``: x86's ``model name`` (the first processor's); else the aarch64 cores by ``CPU implementer`` / ``CPU
    part`` (each kind once, in order: "ARM Cortex-A76 + ARM Cortex-A55" on a big.LITTLE part); else POWER's ``cpu``;
    with the board's ``Model`` or ``Hardware`` line (Raspberry Pi and other boards) beside it, or alone. None where
    the text names none. ``flags``: x86's ``flags`` or aarch64's ``Features`` line of the first processor; None
    where the text has neither (unknown: not the same as an empty line)."""

    model: str | None
    flags: frozenset[str] | None


def parse_cpuinfo(text: str) -> ProcCpuinfo:
    """``ProcCpuinfo`` of a /proc/cpuinfo text (any text: lines without "key : value" are skipped)."""
    first: dict[str, str] = {}  # the first non-empty value of each key
    cores: list[str] = []  # aarch64: each processor's core, once each
    implementer = part = None
    flags = None

    def end_processor() -> None:
        if implementer is not None and part is not None:
            name = arm_core_name(implementer, part)
            if name is not None and name not in cores:
                cores.append(name)

    for key, value in _cpuinfo_fields(text):
        if key == "processor":
            end_processor()
            implementer = part = None
        elif key == "CPU implementer":
            implementer = value
        elif key == "CPU part":
            part = value
        elif key in ("flags", "Features") and flags is None:
            flags = frozenset(value.split())
        if value and key not in first:
            first[key] = value
    end_processor()
    model_name = first.get("model name")
    if model_name and cores and _GENERIC_ARM.match(model_name):  # "ARMv8 Processor rev 1 (v8l)": the cores say more
        model_name = None
    core = model_name or " + ".join(cores) or first.get("cpu")
    board = first.get("Model") or first.get("Hardware")
    if core and board:
        return ProcCpuinfo(f"{core} ({board})", flags)
    return ProcCpuinfo(core or board, flags)


def read_cpuinfo(path: str | Path = CPUINFO) -> tuple[str | None, frozenset[str]]:
    """(model, flags) of a /proc/cpuinfo file (``parse_cpuinfo``); (None, empty) where it cannot be read, empty flags
    where it has no flags line."""
    info = parse_cpuinfo(_read(Path(path)) or "")
    return info.model, info.flags or frozenset()


def _macos_brand() -> str | None:
    """macOS's name of the CPU ("Apple M2", "Intel(R) Core(TM) i7-9750H ..."): sysctl machdep.cpu.brand_string;
    None where it cannot be run."""
    try:
        args = ["sysctl", "-n", "machdep.cpu.brand_string"]
        done = subprocess.run(args, capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return (done.stdout.strip() or None) if done.returncode == 0 else None


def cpu_model(path: str | Path = CPUINFO) -> str:
    """The CPU's model (``parse_cpuinfo``); where /proc/cpuinfo names none, macOS's brand string, else
    platform.processor() (on Linux often empty, on macOS only "arm" or "i386"), else the machine's architecture."""
    model, _ = read_cpuinfo(path)
    if model:
        return model
    brand = _macos_brand() if sys.platform == "darwin" else None
    return brand or platform.processor() or platform.machine() or "unknown CPU"


# The SIMD flags that decide which kernels numpy, OpenCV, onnxruntime and PyTorch pick, by Linux's names, in the order
# reports list them: x86's, then aarch64's (NEON, its dot product, SVE / SVE2, the int8 and bf16 matrix instructions).
X86_KERNEL_FLAGS = ("avx", "avx2", "fma", "f16c", "avx512f", "avx512_bf16", "avx512_fp16", "avx512_vnni", "avx_vnni", "amx_tile")
ARM_KERNEL_FLAGS = ("asimd", "asimddp", "sve", "sve2", "i8mm", "bf16")
KERNEL_FLAGS = X86_KERNEL_FLAGS + ARM_KERNEL_FLAGS
# numpy's names of those it has in its CPU feature table (it has none for avx_vnni, amx_tile, sve2, i8mm, bf16)
NUMPY_FLAG_NAMES = {"AVX": "avx", "AVX2": "avx2", "FMA3": "fma", "F16C": "f16c", "AVX512F": "avx512f",
                    "AVX512BF16": "avx512_bf16", "AVX512FP16": "avx512_fp16", "AVX512VNNI": "avx512_vnni",
                    "ASIMD": "asimd", "ASIMDDP": "asimddp", "SVE": "sve"}  # fmt: skip
FLAGS_FROM_CPUINFO = "/proc/cpuinfo"
FLAGS_FROM_NUMPY = "numpy"


def numpy_flags(features: Mapping[str, bool]) -> frozenset[str]:
    """The flags (Linux's names, ``NUMPY_FLAG_NAMES``) a numpy CPU feature table reports present."""
    return frozenset(flag for name, flag in NUMPY_FLAG_NAMES.items() if features.get(name) is True)


def visible_flags(
    path: str | Path = CPUINFO, environ: Mapping[str, str] | None = None, features: Mapping[str, bool] | None = None
) -> tuple[frozenset[str], str | None]:
    """(flags, where they came from) as the kernels of this process see them: /proc/cpuinfo's flags less the CPUID
    mask's (``FLAGS_FROM_CPUINFO``); where the file has no flags line, numpy's table (``features``, as for
    ``cpuid_mask``: ``FLAGS_FROM_NUMPY``, by Linux's names and only those in ``NUMPY_FLAG_NAMES``); (empty, None)
    where neither says: unknown. Raises ValueError as ``cpuid_mask`` does."""
    mask = cpuid_mask(environ, features)
    flags = parse_cpuinfo(_read(Path(path)) or "").flags
    source: str | None = FLAGS_FROM_CPUINFO
    if flags is None:
        table = _features(features)
        flags, source = numpy_flags(table), FLAGS_FROM_NUMPY if table else None
    if mask is not None:
        hidden = MASKS[mask]
        flags = frozenset(f for f in flags if not hidden(f))
    return flags, source


def cpu_flags(
    path: str | Path = CPUINFO, environ: Mapping[str, str] | None = None, features: Mapping[str, bool] | None = None
) -> frozenset[str]:
    """The flags the kernels of this process can see: those of the silicon less the CPUID mask's (``visible_flags``;
    empty where unknown)."""
    return visible_flags(path, environ, features)[0]


def kernel_flags(
    path: str | Path = CPUINFO, environ: Mapping[str, str] | None = None, features: Mapping[str, bool] | None = None
) -> tuple[str, ...]:
    """Those of ``KERNEL_FLAGS`` the kernels of this process can see (``cpu_flags``), in that order."""
    visible = cpu_flags(path, environ, features)
    return tuple(f for f in KERNEL_FLAGS if f in visible)


def cpu_info(
    cpuinfo: str | Path = CPUINFO, environ: Mapping[str, str] | None = None, features: Mapping[str, bool] | None = None
) -> dict:
    """What reports record of the CPU (the replay's ``config.cpu``): {model (``cpu_model``), flags (those of
    KERNEL_FLAGS the kernels can see, in that order), flags_source (``visible_flags``: "/proc/cpuinfo", "numpy", or
    None: unknown), cpuid_mask (None, or the mask hiding the rest), threads (usable by this process:
    ``usable_cpus``, which also counts a cgroup CPU quota), logical_cpus}. Raises ValueError as ``cpuid_mask``
    does: call it before the work it describes, not after."""
    visible, source = visible_flags(cpuinfo, environ, features)
    return {
        "model": cpu_model(cpuinfo),
        "flags": [f for f in KERNEL_FLAGS if f in visible],
        "flags_source": source,
        "cpuid_mask": cpuid_mask(environ, features),
        "threads": usable_cpus(),
        "logical_cpus": os.cpu_count(),
    }


def cpu_line(info: dict) -> str:
    """One line of a ``cpu_info`` record: "model, N threads usable (flags; the mask)". Flags that could not be read
    say "SIMD flags unknown", not "none of" them: so do records written before ``flags_source`` that hold none."""
    flags = list(info.get("flags") or ())
    source = info.get("flags_source", FLAGS_FROM_CPUINFO if flags else None)  # absent in records written before it
    if source == FLAGS_FROM_NUMPY:
        known = [f for f in KERNEL_FLAGS if f in NUMPY_FLAG_NAMES.values()]
        text = (", ".join(flags) or "none of " + "/".join(known)) + ": numpy's CPU features"
    elif source is not None:
        text = ", ".join(flags) or "none of " + "/".join(KERNEL_FLAGS)
    else:
        text = "SIMD flags unknown"
    mask = info.get("cpuid_mask")  # absent in replays recorded before the mask existed
    masked = f"; CPUID masked to {mask}: the kernels' instruction set, not the silicon's" if mask else ""
    return f"{info['model']}, {info['threads']} threads usable ({text}{masked})"


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


def _small_int(value: str) -> int | None:
    """A /proc/cpuinfo number ("25"); None for anything else ("unknown", which some VMs give as the stepping, or
    another script's digits, which int() would take)."""
    return int(value) if value.isascii() and value.isdigit() and len(value) < 6 else None


def cpu_identity(path: str | Path = CPUINFO) -> dict[str, str | int | None]:
    """{vendor_id, family, model, stepping} of the first processor in a /proc/cpuinfo file (x86's ``vendor_id``,
    ``cpu family``, ``model`` and ``stepping``: "AuthenticAMD", 25, 17, 1); None for each one it does not say (an
    ARM or POWER CPU, a VM that hides it) or that cannot be read. The model name alone does not tell parts apart:
    a guest often shows a generic one ("AMD EPYC"), and Zen 3 and Zen 4 are both family 25."""
    out: dict[str, str | int | None] = {"vendor_id": None, "family": None, "model": None, "stepping": None}
    keys = {"vendor_id": "vendor_id", "cpu family": "family", "model": "model", "stepping": "stepping"}
    seen = set()
    for key, value in _cpuinfo_fields(_read(Path(path)) or ""):
        if key == "processor" and seen:
            break  # the first processor's lines only
        name = keys.get(key)
        if name is None or not value or name in seen:
            continue
        seen.add(name)
        out[name] = value if name == "vendor_id" else _small_int(value)
    return out


def cpu_vendor_family(path: str | Path = CPUINFO) -> tuple[str | None, int | None]:
    """(vendor_id, cpu family) of the first processor in a /proc/cpuinfo text ("AuthenticAMD", 25); None for what it
    does not say or cannot be read (``cpu_identity``)."""
    found = cpu_identity(path)
    vendor, family = found["vendor_id"], found["family"]
    return (vendor if isinstance(vendor, str) else None), (family if isinstance(family, int) else None)
