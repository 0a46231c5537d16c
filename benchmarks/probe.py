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
import tempfile
import time
from dataclasses import dataclass

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper

from streamdet.core.cpu import cpu_model, cpu_vendor_family, cpuid_mask, kernel_flags, physical_cores, usable_cpus
from streamdet.runtime_ort.onnx_build import make_model
from streamdet.runtime_ort.sessions import GraphSession, SessionConfig


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
    return SessionConfig(("CPUExecutionProvider",), threads, allow_spinning=True, enable_profiling=profile,
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


def cpu_flags() -> tuple[str, ...]:
    """The SIMD flags that decide the kernels onnxruntime and PyTorch pick (avx2, fma, avx512f, ...), as the kernels
    see them (a CPUID mask hides some): `streamdet.core.cpu.kernel_flags`."""
    return kernel_flags()


class OtherCpuUse:
    """CPU time other processes take while this one runs, from /proc/stat minus this process's own time.

    ``cores()`` is the average number of CPUs busy with (or stolen by) anything but this process since the start:
    0 on a quiet machine; 1 means another job took a whole core from the benchmark. None off Linux.
    """

    def __init__(self) -> None:
        self._start = self._sample()

    @staticmethod
    def _sample() -> tuple[float, float, float] | None:
        try:
            with open("/proc/stat") as f:
                fields = [float(v) for v in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        # user nice system idle iowait irq softirq steal [guest guest_nice, already inside user and nice]
        busy = sum(fields[:3]) + sum(fields[5:8])
        t = os.times()
        return busy / os.sysconf("SC_CLK_TCK"), t.user + t.system, time.monotonic()

    def cores(self) -> float | None:
        end = self._sample()
        if self._start is None or end is None or end[2] <= self._start[2]:
            return None
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

    AVX-512: 16 lanes, AVX2 + FMA: 8 lanes; None without FMA or a clock. It can be far off either way: ``mhz`` is
    the clock /proc/cpuinfo shows (boost runs above it, an idle core with cpufreq below), several Intel parts have one
    512-bit FMA pipe, hybrid E-cores have others; there is no per-microarchitecture table, only the Zen 4 case below.
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

    flags, mhz, cores = cpu_flags(), cpu_mhz(), physical_cores()
    estimate = nominal_peak_gflops(threads, flags, mhz, cores, *cpu_vendor_family())
    return {
        "cpu_model": cpu_model(),
        "cpu_flags": list(flags),
        "cpuid_mask": cpuid_mask(),
        "cpu_mhz": mhz,  # the first "cpu MHz" of /proc/cpuinfo: the nominal clock in a VM, cpu0's current one otherwise
        "peak_estimate_gflops_per_s": estimate,  # nominal_peak_gflops: an estimate, not a data-sheet figure nor a bound
        "nominal_peak_gflops_per_s": estimate,  # the same estimate under its older key (kept for readers of old JSON)
        "peak_estimate_cores": estimate_cores(threads, cores),  # the cores that estimate counts
        "physical_cores": cores,  # among the CPUs this process may run on (core.cpu.physical_cores); None: unknown
        "logical_cpus": os.cpu_count(),  # the machine's, whatever this process may use
        "usable_cpus": usable_cpus(),  # what this process may use: affinity and cgroup quota (core.cpu.usable_cpus)
        "threads": threads,
        "load_average_1_5_15": load_average(),
        "onnxruntime": ort.__version__,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
