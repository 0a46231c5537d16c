"""This machine's attainable fp32 throughput, measured in the run: one large MatMul in onnxruntime.

A square n x n x n float32 matmul is the most efficient kernel onnxruntime (MLAS) has, so its best-of-several
GFLOP/s with the benchmark's thread count is the "peak" the rows' achieved GFLOP/s are divided by. It is an
attainable rate, not an upper bound (convolution kernels can outrun it). Beside it the report prints an estimate
from FMA width x clock x physical cores (``nominal_peak_gflops``): a rough figure, not a data-sheet one and not a
bound either, since the clock /proc/cpuinfo shows and the FMA width the flags suggest can both be off.
"""

from __future__ import annotations

import os
import platform
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper

from streamdet.core.cpu import cpu_identity, cpu_info, physical_cores
from streamdet.runtime_ort.onnx_build import make_model
from streamdet.runtime_ort.sessions import CPU_ONLY, GraphSession, SessionConfig


@dataclass(frozen=True)
class ProbeConfig:
    size: int = 2048  # n of the n x n x n matmul: 17.2 GFLOP, ~0.1 s at 200 GFLOP/s
    runs: int = 8  # timed runs; the best one counts (the probe asks what the machine can do, not what it usually does)
    warmup: int = 2

    def __post_init__(self) -> None:
        for name in ("size", "runs"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"ProbeConfig.{name} must be a positive integer, got {v!r}")
        if isinstance(self.warmup, bool) or not isinstance(self.warmup, int) or self.warmup < 0:
            raise ValueError(f"ProbeConfig.warmup must be an integer >= 0, got {self.warmup!r}")


@dataclass(frozen=True)
class ProbeResult:
    """GFLOP/s (2 n^3 / seconds / 1e9) of every timed probe run; the best one is the peak."""

    run_gflops_per_s: tuple[float, ...]
    size: int
    threads: int

    @property
    def gflops_per_s(self) -> float:
        return max(self.run_gflops_per_s)

    @property
    def median_gflops_per_s(self) -> float:
        return float(np.median(self.run_gflops_per_s))

    @property
    def runs(self) -> int:
        return len(self.run_gflops_per_s)

    def merged(self, other: "ProbeResult") -> "ProbeResult":
        """Both probes' runs: on a shared machine the probe runs at the start and the end of the benchmark."""
        if (other.size, other.threads) != (self.size, self.threads):
            raise ValueError(f"cannot merge probes of n={self.size}/{self.threads} threads and n={other.size}/{other.threads} threads")
        return ProbeResult(self.run_gflops_per_s + other.run_gflops_per_s, self.size, self.threads)

    def to_dict(self) -> dict:
        return {
            "gflops_per_s": self.gflops_per_s,
            "median_gflops_per_s": self.median_gflops_per_s,
            "run_gflops_per_s": list(self.run_gflops_per_s),
            "size": self.size,
            "runs": self.runs,
            "threads": self.threads,
            "kernel": "onnxruntime MatMul fp32, n x n x n",
        }


def row_session_config(threads: int, profile: bool = False, profile_dir: str | os.PathLike | None = None) -> SessionConfig:
    """Sessions of the per-module rows and of the probe: CPU, ORT_ENABLE_ALL (GraphSession's level), ``threads``
    intra-op threads, spinning on (onnxruntime's default; one graph runs alone, so no other lane needs the core);
    ``profile_dir``: where a profiling session writes (None: the current directory)."""
    return SessionConfig(CPU_ONLY, threads, allow_spinning=True, enable_profiling=profile,
                         profile_dir=profile_dir)  # fmt: skip


def matmul_model(n: int) -> onnx.ModelProto:
    a = helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])
    b = helper.make_tensor_value_info("b", TensorProto.FLOAT, [n, n])
    c = helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])
    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"], name="probe")], "peak_probe", [a, b], [c])
    return make_model(graph, [helper.make_opsetid("", 17)])


def measure_peak(threads: int, config: ProbeConfig = ProbeConfig()) -> ProbeResult:
    n = config.size
    with tempfile.TemporaryDirectory(prefix="streamdet_probe_") as tmp:
        path = os.path.join(tmp, "matmul.onnx")
        onnx.save_model(matmul_model(n), path)
        session = GraphSession(path, row_session_config(threads))
    rng = np.random.default_rng(0)
    feeds = {"a": rng.standard_normal((n, n), dtype=np.float32), "b": rng.standard_normal((n, n), dtype=np.float32)}
    for _ in range(config.warmup):
        session.run(feeds)
    seconds = []
    for _ in range(config.runs):
        start = time.perf_counter()
        session.run(feeds)
        seconds.append(time.perf_counter() - start)
    return ProbeResult(tuple(2.0 * n**3 / s / 1e9 for s in seconds), n, threads)


PROC_STAT = Path("/proc/stat")
_STAT_CPU = re.compile(r"cpu([0-9]*)")


def affinity_cpu_ids() -> frozenset[int] | None:
    """The CPUs this process may run on (its affinity mask); None where the OS does not say (no sched_getaffinity,
    or it fails)."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    try:
        return frozenset(os.sched_getaffinity(0)) or None
    except OSError:
        return None


def stat_busy_ticks(text: str, cpus: frozenset[int] | None) -> tuple[float, int | None] | None:
    """(busy clock ticks, the CPUs they count) of a /proc/stat text: the per-CPU ``cpuN`` lines of ``cpus`` summed;
    the host-wide ``cpu`` line where ``cpus`` is None or the text has a line for none of them (the CPUs counted: None,
    every CPU of the host). Busy: user, nice, system, irq, softirq and steal (guest time is already inside user and
    nice; idle and iowait are not busy). None where a line counted is not one of numbers, or there is none to count.
    A CPU of ``cpus`` without a line (offline) counts nothing."""
    host, per_cpu = None, {}
    for line in text.splitlines():
        parts = line.split()
        found = _STAT_CPU.fullmatch(parts[0]) if parts else None
        if found is None:
            continue
        values = parts[1:]
        if found[1]:
            per_cpu[int(found[1])] = values
        elif host is None:
            host = values
    wanted = [per_cpu[c] for c in sorted(cpus) if c in per_cpu] if cpus is not None else []
    counted: int | None = len(wanted)
    if not wanted:
        if host is None:
            return None
        wanted, counted = [host], None
    busy = 0.0
    for values in wanted:
        if not values or not all(v.isascii() and v.isdigit() for v in values):
            return None
        fields = [float(v) for v in values]
        # user nice system idle iowait irq softirq steal [guest guest_nice, already inside user and nice]
        busy += sum(fields[:3]) + sum(fields[5:8])
    return busy, counted


class OtherCpuUse:
    """CPU time other processes take on the CPUs this one may run on while it runs: the /proc/stat lines of those
    CPUs (``stat_busy_ticks``: the affinity set; host-wide where it is unknown) minus this process's own time.

    ``cores()`` is the average number of those CPUs busy with (or stolen by) anything but this process since the
    start: 0 on a quiet machine; 1 means another job took a whole core from the benchmark. None off Linux.
    ``cpus`` is how many CPUs that counts (None: the host-wide line, or no /proc/stat); load on CPUs the process may
    not use (``taskset``, a container's cpuset) is not counted. ``stat`` and ``cpus_allowed`` (None: this process's
    affinity) are for tests.
    """

    def __init__(self, stat: str | Path = PROC_STAT, cpus_allowed: frozenset[int] | None = None) -> None:
        self._stat = Path(stat)
        self._allowed = affinity_cpu_ids() if cpus_allowed is None else cpus_allowed
        self._start = self._sample()
        self.cpus: int | None = None if self._start is None else self._start[3]

    def _sample(self) -> tuple[float, float, float, int | None] | None:
        try:
            text = self._stat.read_text(errors="replace")
        except (OSError, ValueError):
            return None
        found = stat_busy_ticks(text, self._allowed)
        if found is None:
            return None
        busy, counted = found
        t = os.times()
        return busy / os.sysconf("SC_CLK_TCK"), t.user + t.system, time.monotonic(), counted

    def cores(self) -> float | None:
        end = self._sample()
        if self._start is None or end is None or end[2] <= self._start[2] or end[3] != self._start[3]:
            return None  # no figure, or a CPU went offline (its time left the sum) during the run
        others = (end[0] - self._start[0]) - (end[1] - self._start[1])
        return max(0.0, others / (end[2] - self._start[2]))


def cpu_mhz() -> float | None:
    """The clock /proc/cpuinfo reports (a VM shows the nominal one; boost clocks may be higher)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("cpu MHz"):
                    return float(line.split(":", 1)[1])
    except (OSError, ValueError):
        pass
    return None


def estimate_cores(threads: int, cores: int | None) -> int:
    """The cores ``nominal_peak_gflops`` counts: ``threads`` on at most ``cores`` physical cores (None: one per thread)."""
    return threads if cores is None else max(1, min(threads, cores))


def nominal_peak_gflops(threads: int, flags: tuple[str, ...], mhz: float | None, cores: int | None = None,
                        vendor: str | None = None, family: int | None = None) -> float | None:
    """An estimate of the fp32 rate, not a bound: FMA lanes x 2 FLOP x 2 FMA pipes x clock x cores, with cores the
    physical cores the threads can run on (``estimate_cores``).

    AVX-512: 16 lanes, AVX2 + FMA: 8 lanes; None without FMA or a clock (FMA: x86's ``fma`` flag, so an ARM part,
    whose lanes this rule does not know, and flags that could not be read give None, not a wrong number). It can be
    far off either way: ``mhz`` is the clock /proc/cpuinfo shows (boost runs above it, an idle core with cpufreq
    below), several Intel parts have one 512-bit FMA pipe, hybrid E-cores have others; there is no
    per-microarchitecture table, only the Zen 4 case below.
    """
    if mhz is None or "fma" not in flags:
        return None
    lanes = 16 if "avx512f" in flags else 8
    if vendor == "AuthenticAMD" and family == 25:  # Zen 4 runs a 512-bit FMA as two 256-bit halves: no doubling
        lanes = 8
    return lanes * 2 * 2 * mhz / 1e3 * estimate_cores(threads, cores)


def load_average() -> list[float]:
    """1, 5 and 15 minute load averages (runnable processes); NaN where the OS has none."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return [round(v, 2) for v in load]


def machine_info(threads: int) -> dict:
    import torch  # the benchmark needs torch anyway; kept local so the probe itself stays torch-free

    # the CPU as every report records it (core.cpu.cpu_info: the kernels' SIMD flags, less a CPUID mask's)
    cpu, mhz, cores, identity = cpu_info(), cpu_mhz(), physical_cores(), cpu_identity()
    estimate = nominal_peak_gflops(threads, tuple(cpu["flags"]), mhz, cores, identity["vendor_id"], identity["family"])
    return {
        "cpu_model": cpu["model"],
        # vendor_id, family, model, stepping (core.cpu.cpu_identity; None each where /proc/cpuinfo does not say): a
        # guest's model name is often generic ("AMD EPYC"), and parts of one family differ
        "cpu_identity": identity,
        "cpu_flags": cpu["flags"],
        "cpu_flags_source": cpu["flags_source"],  # core.cpu.visible_flags: "/proc/cpuinfo", "numpy", or None (unknown)
        "cpuid_mask": cpu["cpuid_mask"],
        "cpu_mhz": mhz,  # the first "cpu MHz" of /proc/cpuinfo: the nominal clock in a VM, cpu0's current one otherwise
        "peak_estimate_gflops_per_s": estimate,  # nominal_peak_gflops: an estimate, not a data-sheet figure nor a bound
        "nominal_peak_gflops_per_s": estimate,  # the same estimate under its older key (kept for readers of old JSON)
        "peak_estimate_cores": estimate_cores(threads, cores),  # the cores that estimate counts
        "physical_cores": cores,  # among the CPUs this process may run on (core.cpu.physical_cores); None: unknown
        "logical_cpus": cpu["logical_cpus"],  # the machine's, whatever this process may use
        "usable_cpus": cpu["threads"],  # what this process may use: affinity and cgroup quota (core.cpu.usable_cpus)
        "other_cpu_use_cpus": OtherCpuUse().cpus,  # the CPUs other_cpu_use counts (the affinity set); None: all, or unknown
        "threads": threads,
        "load_average_1_5_15": load_average(),
        "onnxruntime": ort.__version__,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
