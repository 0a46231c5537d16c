"""CPU identification beyond x86 Linux (portability audit L1, L5, L8): /proc/cpuinfo of aarch64, an Intel hybrid part
and POWER, no /proc at all (macOS, Windows: numpy's CPU feature table, else "SIMD flags unknown"), the issue 22
target of a CPU that is neither AVX-512 nor AVX2, the peak estimate on such a CPU, the other processes' CPU use
summed over the CPUs this process may run on, and the shell helpers off Linux. Every text is a literal here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

from streamdet.benchmarks import probe
from streamdet.benchmarks.probe import OtherCpuUse, nominal_peak_gflops, stat_busy_ticks
from streamdet.core import cpu

REPO = Path(__file__).resolve().parents[1]

# ---- /proc/cpuinfo texts (those of the audit, and a few more) -----------------------------------------------------
_NEOVERSE_N1 = """processor\t: {n}
BogoMIPS\t: 50.00
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm lrcpc dcpop asimddp ssbs
CPU implementer\t: 0x41
CPU architecture: 8
CPU variant\t: 0x3
CPU part\t: 0xd0c
CPU revision\t: 1
"""
AARCH64 = "\n".join(_NEOVERSE_N1.format(n=n) for n in range(2))  # two processors, as the file lists every one
INTEL_HYBRID = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 183
model name\t: 13th Gen Intel(R) Core(TM) i9-13900K
stepping\t: 1
cpu MHz\t\t: 800.000
flags\t\t: fpu vme de pse tsc msr pae avx f16c fma avx2 avx_vnni
"""
POWER9 = """processor\t: 0
cpu\t\t: POWER9 (architected), altivec supported
clock\t\t: 2200.000000MHz
revision\t: 2.2 (pvr 004e 1202)
"""
NEOVERSE_V2_SVE = """processor\t: 0
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm jscvt fcma lrcpc dcpop sha3 sm3 sm4 asimddp sha512 sve asimdfhm dit uscat ilrcpc flagm ssbs sb paca pacg dcpodp sve2 sveaes svepmull svebitperm svesha3 svesm4 flagm2 frint svei8mm svebf16 i8mm bf16 dgh bti
CPU implementer\t: 0x41
CPU architecture: 8
CPU variant\t: 0x0
CPU part\t: 0xd4f
CPU revision\t: 1
"""


def big_little(*parts: str, board: str = "") -> str:
    block = "processor\t: {i}\nFeatures\t: fp asimd\nCPU implementer\t: 0x41\nCPU part\t: {p}\n\n"
    blocks = [block.format(i=i, p=p) for i, p in enumerate(parts)]
    return "".join(blocks) + board


@pytest.mark.parametrize(
    "text, model, flags",
    [
        (AARCH64, "ARM Neoverse N1", {"asimd", "asimddp", "fphp", "ssbs"}),
        (NEOVERSE_V2_SVE, "ARM Neoverse V2", {"sve", "sve2", "i8mm", "bf16"}),
        (INTEL_HYBRID, "13th Gen Intel(R) Core(TM) i9-13900K", {"avx", "avx2", "fma", "f16c", "avx_vnni"}),
        (POWER9, "POWER9 (architected), altivec supported", None),  # POWER lists no flags: unknown, not none
        (big_little("0xd0b", "0xd0b", "0xd05", "0xd05"), "ARM Cortex-A76 + ARM Cortex-A55", {"fp", "asimd"}),
        (big_little("0xd08", board="Hardware\t: BCM2835\nModel\t\t: Raspberry Pi 4 Model B Rev 1.4\n"),
         "ARM Cortex-A72 (Raspberry Pi 4 Model B Rev 1.4)", {"fp", "asimd"}),
        (big_little("0xd08", board="Hardware\t: BCM2835\n"), "ARM Cortex-A72 (BCM2835)", {"fp", "asimd"}),
        (big_little("0xd99"), "ARM part 0xd99", {"fp", "asimd"}),  # a part this table does not name
        (big_little("0xd0c").replace("0x41", "0x61"), "Apple part 0xd0c", {"fp", "asimd"}),
        (big_little("0x516").replace("0x41", "0x42"), "ARM implementer 0x42 part 0x516", {"fp", "asimd"}),
        ("model name\t: ARMv8 Processor rev 1 (v8l)\n" + big_little("0xd03"), "ARM Cortex-A53", {"fp", "asimd"}),
        ("model name\t: ARMv7 Processor rev 4 (v7l)\nFeatures\t: half thumb neon\n", "ARMv7 Processor rev 4 (v7l)",
         {"half", "thumb", "neon"}),  # no implementer lines: the kernel's model name stands
    ],
)
def test_parse_cpuinfo(text: str, model: str, flags: set[str] | None) -> None:
    info = cpu.parse_cpuinfo(text)
    assert info.model == model
    if flags is None:
        assert info.flags is None
    else:
        assert info.flags is not None and flags <= info.flags


@pytest.mark.parametrize(
    "text",
    [
        "",
        "\n\n",
        "garbage without colons\n\x00\xff",
        "CPU implementer\t: banana\nCPU part\t: 0xd0c\n",  # not a number: no core named from it
        "CPU implementer\t: 0x41\n",  # a part missing
        "CPU part\t: 0xd0c\nprocessor : 1\nCPU implementer : 0x41\n",  # split over two processors
        "Features\t:\ncpu\t:\nModel\t:   \n",
    ],
)
def test_parse_cpuinfo_of_empty_or_malformed_text_names_nothing_it_does_not_say(text: str) -> None:
    info = cpu.parse_cpuinfo(text)
    assert info.model is None
    assert info.flags in (None, frozenset())


def test_arm_core_name() -> None:
    assert cpu.arm_core_name("0x41", "0xd0c") == "ARM Neoverse N1"
    assert cpu.arm_core_name("0X41", "0XD4F") == "ARM Neoverse V2"
    assert cpu.arm_core_name("0x61", "0x023") == "Apple part 0x23"
    assert cpu.arm_core_name("0x99", "0x1") == "ARM implementer 0x99 part 0x1"
    for bad in (("", "0xd0c"), ("0x41", ""), ("65", "0xd0c"), ("0x41", "0xd0c0c0c0c"), ("0x41", "d0c")):
        assert cpu.arm_core_name(*bad) is None


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(text)
    return path


# numpy CPU feature tables (numpy's __cpu_features__), as numpy builds them on each machine
APPLE_M1_FEATURES = {"NEON": True, "ASIMD": True, "ASIMDHP": True, "ASIMDDP": True, "ASIMDFHM": True, "SVE": False,
                     "AVX": False, "AVX2": False, "AVX512F": False, "FMA3": False}  # fmt: skip
INTEL_MAC_FEATURES = {"SSE2": True, "AVX": True, "AVX2": True, "FMA3": True, "F16C": True, "AVX512F": False, "ASIMD": False}
POWER9_FEATURES = {"VSX": True, "VSX2": True, "VSX3": True, "AVX": False, "AVX2": False, "ASIMD": False}


@pytest.mark.parametrize(
    "text, features, flags, source, line",
    [
        (AARCH64, {}, ["asimd", "asimddp"], "/proc/cpuinfo", "ARM Neoverse N1, 2 threads usable (asimd, asimddp)"),
        (NEOVERSE_V2_SVE, {}, ["asimd", "asimddp", "sve", "sve2", "i8mm", "bf16"], "/proc/cpuinfo",
         "ARM Neoverse V2, 2 threads usable (asimd, asimddp, sve, sve2, i8mm, bf16)"),
        (INTEL_HYBRID, {}, ["avx", "avx2", "fma", "f16c", "avx_vnni"], "/proc/cpuinfo",
         "13th Gen Intel(R) Core(TM) i9-13900K, 2 threads usable (avx, avx2, fma, f16c, avx_vnni)"),
        (POWER9, {}, [], None, "POWER9 (architected), altivec supported, 2 threads usable (SIMD flags unknown)"),
        (POWER9, POWER9_FEATURES, [], "numpy", "POWER9 (architected), altivec supported, 2 threads usable (none of "
         "avx/avx2/fma/f16c/avx512f/avx512_bf16/avx512_fp16/avx512_vnni/asimd/asimddp/sve: numpy's CPU features)"),
        ("model name\t: Old x86\nflags\t: fpu sse2\n", {}, [], "/proc/cpuinfo",
         "Old x86, 2 threads usable (none of " + "/".join(cpu.KERNEL_FLAGS) + ")"),  # read, and none of them: said so
    ],
)
def test_cpu_info_and_line(tmp_path, monkeypatch, text, features, flags, source, line) -> None:
    monkeypatch.setattr(cpu, "usable_cpus", lambda cgroup_root=None: 2)
    info = cpu.cpu_info(_write(tmp_path, text), environ={}, features=features)
    assert info["flags"] == flags and info["flags_source"] == source and info["cpuid_mask"] is None
    assert cpu.cpu_line(info) == line
    json.dumps(info)  # the replay writes it into its JSON


@pytest.mark.parametrize(
    "platform_name, brand, features, line",
    [
        ("darwin", "Apple M1", APPLE_M1_FEATURES, "Apple M1, 2 threads usable (asimd, asimddp: numpy's CPU features)"),
        ("darwin", "Intel(R) Core(TM) i7-9750H CPU @ 2.60GHz", INTEL_MAC_FEATURES,
         "Intel(R) Core(TM) i7-9750H CPU @ 2.60GHz, 2 threads usable (avx, avx2, fma, f16c: numpy's CPU features)"),
        ("darwin", None, {}, "i386, 2 threads usable (SIMD flags unknown)"),  # no sysctl, no numpy
        ("win32", None, INTEL_MAC_FEATURES, "i386, 2 threads usable (avx, avx2, fma, f16c: numpy's CPU features)"),
    ],
)
def test_no_proc_cpuinfo(tmp_path, monkeypatch, platform_name, brand, features, line) -> None:
    """macOS and Windows: no /proc. The Intel Mac with AVX2 was reported as "none of avx/avx2/..." before."""
    monkeypatch.setattr(cpu, "usable_cpus", lambda cgroup_root=None: 2)
    monkeypatch.setattr(cpu.sys, "platform", platform_name)
    monkeypatch.setattr(cpu, "_macos_brand", lambda: brand)
    monkeypatch.setattr(cpu.platform, "processor", lambda: "i386")
    info = cpu.cpu_info(tmp_path / "absent", environ={}, features=features)
    assert cpu.cpu_line(info) == line
    assert "none of" not in cpu.cpu_line(info)


def test_macos_brand_from_sysctl(monkeypatch) -> None:
    def run(args, **kwargs):
        assert args == ["sysctl", "-n", "machdep.cpu.brand_string"]
        return types.SimpleNamespace(returncode=0, stdout="Apple M2 Pro\n")

    monkeypatch.setattr(cpu.subprocess, "run", run)
    assert cpu._macos_brand() == "Apple M2 Pro"
    monkeypatch.setattr(cpu.subprocess, "run", lambda args, **kw: types.SimpleNamespace(returncode=1, stdout=""))
    assert cpu._macos_brand() is None

    def missing(args, **kwargs):
        raise FileNotFoundError("sysctl")

    monkeypatch.setattr(cpu.subprocess, "run", missing)
    assert cpu._macos_brand() is None


def test_numpy_flags_by_linux_names() -> None:
    assert cpu.numpy_flags(INTEL_MAC_FEATURES) == {"avx", "avx2", "fma", "f16c"}
    assert cpu.numpy_flags(APPLE_M1_FEATURES) == {"asimd", "asimddp"}
    assert cpu.numpy_flags({}) == frozenset()
    assert set(cpu.NUMPY_FLAG_NAMES.values()) <= set(cpu.KERNEL_FLAGS)


def test_this_numpy_has_a_table_in_the_names_mapped() -> None:
    table = cpu.numpy_cpu_features()
    assert table and all(isinstance(v, bool) for v in table.values())
    assert set(cpu.NUMPY_FLAG_NAMES) <= set(table)  # numpy still spells them so


def test_records_written_before_flags_source() -> None:
    old = {"model": "AMD EPYC 7B13", "flags": ["avx2", "fma"], "threads": 2, "logical_cpus": 2}
    assert cpu.cpu_line(old) == "AMD EPYC 7B13, 2 threads usable (avx2, fma)"
    assert cpu.cpu_line({**old, "flags": []}) == "AMD EPYC 7B13, 2 threads usable (SIMD flags unknown)"  # could not tell


def test_the_replay_report_re_exports_them() -> None:
    from streamdet.replay import report

    assert report.cpu_info is cpu.cpu_info and report.cpu_line is cpu.cpu_line


def test_core_cpu_imports_and_reports_without_numpy(tmp_path) -> None:
    """core is imported by every package: core/cpu.py must load, and say "unknown", where numpy cannot be imported."""
    script = f"""
import importlib.util, sys
sys.modules["numpy"] = None  # any import of numpy now fails
spec = importlib.util.spec_from_file_location("cpu_alone", {str(REPO / "core" / "cpu.py")!r})
mod = sys.modules["cpu_alone"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
assert mod.numpy_cpu_features() is None
print(mod.cpu_line(mod.cpu_info({str(tmp_path / "absent")!r}, environ={{}})))
print(mod.cpuid_mask({{mod.CPUID_MASK_ENV: "avx2"}}))  # no table: the variable is trusted
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    first, second = done.stdout.splitlines()
    assert first.endswith("threads usable (SIMD flags unknown)") and second == "avx2"


# ---- issue 22's target by CPU (benchmarks/replay_table.py) ---------------------------------------------------------
ARM_CPU = {"model": "ARM Neoverse N1", "flags": ["asimd", "asimddp"], "flags_source": "/proc/cpuinfo", "threads": 2,
           "logical_cpus": 2}  # fmt: skip
UNKNOWN_CPU = {"model": "arm", "flags": [], "flags_source": None, "threads": 8, "logical_cpus": 8}
AVX2_CPU = {"model": "AMD EPYC 7B13", "flags": ["avx2", "fma"], "threads": 2, "logical_cpus": 2}
AVX512_CPU = {"model": "AMD EPYC 9B14", "flags": ["avx2", "fma", "avx512f"], "threads": 2, "logical_cpus": 2}


def test_staleness_target_by_what_was_found() -> None:
    from streamdet.benchmarks.replay_table import no_target_label, staleness_target

    assert staleness_target(AVX512_CPU) == 25.0 and staleness_target(AVX2_CPU) == 100.0
    assert staleness_target(ARM_CPU) is None and staleness_target(UNKNOWN_CPU) is None
    assert staleness_target({"model": "x"}) is None
    assert no_target_label(ARM_CPU) == "no issue 22 target for ARM Neoverse N1: asimd/asimddp (no AVX2)"
    assert no_target_label(UNKNOWN_CPU) == "no issue 22 target for arm: unknown SIMD flags"


def _replay(out: Path, name: str, cpu_info: dict, p95: float = 20.0) -> None:
    summary = {"staleness_ms": {"p50": p95 / 2, "p95": p95}, "image_age_ms": {"p95": p95 + 80}, "latency_ms": {"p99": 10.0},
               "slices_dropped": 0, "image_lane_cpu_ms_per_rotation": 30.0, "map_streaming": 0.4,
               "recordings": [{"slices": [{"emit_s": 1.0, "newest_capture_s": 0.05, "image_capture_s": 0.0}]}]}  # fmt: skip
    (out / name).mkdir(parents=True)
    (out / name / "replay.json").write_text(json.dumps({"modes": {"streaming": summary}, "config": {"cpu": cpu_info}}))


@pytest.mark.parametrize("machine", [ARM_CPU, UNKNOWN_CPU])
def test_the_line_claims_no_target_for_a_cpu_without_one(tmp_path, machine) -> None:
    from streamdet.benchmarks.replay_table import line_against, main, table

    _replay(tmp_path, "r1_scale1_full", machine)
    _replay(tmp_path, "r1_scale1_pl", machine)
    with pytest.raises(ValueError, match="no issue 22 target for .*: give --target-ms"):
        line_against(tmp_path, "full")
    assert main([str(tmp_path), "--baseline", "full"]) == 1
    assert "<= 100 ms" in line_against(tmp_path, "full", target_ms=100.0)  # given by hand: counted against it
    first = table(tmp_path).splitlines()[0]
    assert "AVX" not in first and "none of" not in first


def _plotted(tmp_path: Path, monkeypatch) -> tuple[list[float], list[str]]:
    """The target lines and legend labels of replay_table.plot's figure."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from streamdet.benchmarks import replay_table

    lines: list[float] = []
    labels: list[str] = []
    axvline = Axes.axvline

    def record_axvline(self, x=0, *args, **kwargs):
        lines.append(x)
        return axvline(self, x, *args, **kwargs)

    def record_save(self, *args, **kwargs):
        for ax in self.axes:
            labels.extend(ax.get_legend_handles_labels()[1])

    monkeypatch.setattr(Axes, "axvline", record_axvline)
    monkeypatch.setattr(Figure, "savefig", record_save)
    replay_table.plot(tmp_path, tmp_path / "cdf.png")
    return lines, labels


@pytest.mark.parametrize(
    "machine, targets, label",
    [
        (AVX512_CPU, [25.0], "issue 22 target, AVX-512: p95 <= 25 ms"),
        (AVX2_CPU, [100.0], "issue 22 target, AVX2-only: p95 <= 100 ms"),
        (ARM_CPU, [], "no issue 22 target for ARM Neoverse N1: asimd/asimddp (no AVX2)"),
        (UNKNOWN_CPU, [], "no issue 22 target for arm: unknown SIMD flags"),
    ],
)
def test_the_plot_draws_a_target_only_for_an_avx2_or_avx512_cpu(tmp_path, monkeypatch, machine, targets, label) -> None:
    _replay(tmp_path, "r1_scale1_full", machine)
    lines, labels = _plotted(tmp_path, monkeypatch)
    assert lines == targets and label in labels
    if not targets:
        assert not any("AVX2-only" in x or "AVX-512" in x for x in labels)


# ---- the peak estimate (benchmarks/probe.py) ----------------------------------------------------------------------
@pytest.mark.parametrize("flags", [("asimd", "asimddp", "sve"), (), ("avx", "avx2")])
def test_no_peak_estimate_without_x86_fma(flags) -> None:
    """An ARM part, unknown flags, or no FMA: no estimate rather than a wrong number (lanes 16/8 are x86's)."""
    assert nominal_peak_gflops(4, flags, 3000.0, 4) is None
    assert nominal_peak_gflops(4, flags, None, 4) is None


def test_no_peak_estimate_on_the_audits_cpuinfo_texts(tmp_path, monkeypatch) -> None:
    """The clock an estimate needs: /proc/cpuinfo's "cpu MHz", which aarch64 and POWER do not print."""
    for text in (AARCH64, POWER9):
        flags = cpu.kernel_flags(_write(tmp_path, text), environ={}, features={})
        assert nominal_peak_gflops(2, flags, None) is None and "fma" not in flags


# ---- other processes' CPU use over the CPUs this process may use (benchmarks/probe.py, report.py) -----------------
STAT = """cpu  1000 10 500 90000 40 0 20 30 0 0
cpu0 100 0 50 45000 20 0 10 0 0 0
cpu1 900 10 450 45000 20 0 10 30 0 0
intr 12345 0 0
ctxt 999
btime 1700000000
processes 100
"""


def test_stat_busy_ticks_sums_the_allowed_cpus() -> None:
    busy = lambda user, nice, system, irq, softirq, steal: float(user + nice + system + irq + softirq + steal)  # noqa: E731
    assert stat_busy_ticks(STAT, frozenset({0})) == (busy(100, 0, 50, 0, 10, 0), 1)  # taskset -c 0: cpu1 left out
    assert stat_busy_ticks(STAT, frozenset({1})) == (busy(900, 10, 450, 0, 10, 30), 1)
    assert stat_busy_ticks(STAT, frozenset({0, 1})) == (busy(1000, 10, 500, 0, 20, 30), 2)
    assert stat_busy_ticks(STAT, frozenset({0, 7})) == (busy(100, 0, 50, 0, 10, 0), 1)  # cpu7 offline: no line
    assert stat_busy_ticks(STAT, None) == (busy(1000, 10, 500, 0, 20, 30), None)  # affinity unknown: host-wide
    assert stat_busy_ticks(STAT, frozenset({5})) == (busy(1000, 10, 500, 0, 20, 30), None)  # none of its lines


@pytest.mark.parametrize(
    "text",
    ["", "\n", "intr 1 2\n", "cpu0 1 2 x 4\n", "cpu  1 2 3 -4\n", "cpu0\n", "cpux 1 2 3\n", "cpu 1 2 3 \u0664\n"],
)
def test_stat_busy_ticks_of_empty_or_malformed_text(text) -> None:
    for cpus in (None, frozenset({0})):
        assert stat_busy_ticks(text, cpus) is None


def test_stat_busy_ticks_of_an_old_kernel_line() -> None:
    assert stat_busy_ticks("cpu 10 20 30 40\n", None) == (60.0, None)  # before iowait, irq, softirq and steal existed


def test_other_cpu_use_counts_only_the_allowed_cpus(tmp_path, monkeypatch) -> None:
    stat = tmp_path / "stat"
    stat.write_text(STAT)
    clock = iter([10.0, 20.0])
    own = iter([types.SimpleNamespace(user=1.0, system=0.0), types.SimpleNamespace(user=3.0, system=1.0)])
    monkeypatch.setattr(probe.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(probe.os, "times", lambda: next(own))
    monkeypatch.setattr(probe.os, "sysconf", lambda name: 100)
    use = OtherCpuUse(stat, cpus_allowed=frozenset({0}))
    assert use.cpus == 1
    # 10 s later: cpu0 busy 1000 ticks more (10 s of CPU), this process 3 s of it; cpu1's 5000 ticks are not counted
    stat.write_text(STAT.replace("cpu0 100 0 50", "cpu0 1100 0 50").replace("cpu1 900", "cpu1 5900"))
    assert use.cores() == pytest.approx((10.0 - 3.0) / 10.0)


def test_other_cpu_use_without_proc_stat(tmp_path) -> None:
    use = OtherCpuUse(tmp_path / "absent", cpus_allowed=frozenset({0}))
    assert use.cpus is None and use.cores() is None
    garbage = tmp_path / "garbage"
    garbage.write_text("cpu0 a b c\n")
    assert OtherCpuUse(garbage).cores() is None


@pytest.mark.skipif(not Path("/proc/stat").exists() or not hasattr(os, "sched_getaffinity"), reason="Linux /proc/stat")
def test_other_cpu_use_on_this_machine() -> None:
    use = OtherCpuUse()
    assert use.cpus == len(os.sched_getaffinity(0))
    assert use.cores() is None or use.cores() >= 0.0


def _header(others: float, **machine) -> str:
    from streamdet.benchmarks.probe import ProbeResult
    from streamdet.benchmarks.report import format_header

    m = {"cpu_model": "AMD EPYC", "cpu_flags": ["avx2", "fma"], "logical_cpus": 2, "load_average_1_5_15": [0.1, 0.2, 0.3],
         "onnxruntime": "1", "torch": "2", "cpu_mhz": None, **machine}  # fmt: skip
    meta = {"date": "2026-12-05", "preset": "tiny", "machine": m, "threads": 2, "repeat": 3, "warmup": 1, "budget_s": 2.0,
            "other_cpu_use": others}  # fmt: skip
    return format_header(meta, ProbeResult((100.0, 120.0), 256, 2))


@pytest.mark.parametrize(
    "others, machine, busy",
    [
        (0.3, dict(logical_cpus=64, other_cpu_use_cpus=64), False),  # daemons on a 64-core box: 0.5 %
        (7.0, dict(logical_cpus=64, other_cpu_use_cpus=64), True),  # over 10 % of them
        (0.3, dict(logical_cpus=2, other_cpu_use_cpus=2), True),  # a 2-CPU machine as before: over 0.2
        (0.15, dict(logical_cpus=2, other_cpu_use_cpus=2), False),
        (0.25, dict(logical_cpus=2, other_cpu_use_cpus=1), True),  # taskset -c 0: the floor, 0.2
        (0.15, dict(logical_cpus=2, other_cpu_use_cpus=1), False),
        (0.3, dict(logical_cpus=2), True),  # a result before the key: the whole machine's CPUs, as before
        (0.3, dict(logical_cpus=64), False),
        (0.3, dict(logical_cpus=64, other_cpu_use_cpus=None), False),  # host-wide figure: the machine's CPUs
    ],
)
def test_busy_warning_is_relative_to_the_cpus_counted(others, machine, busy) -> None:
    header = _header(others, **machine)
    assert ("WARNING: the machine was busy" in header) == busy
    if busy and machine.get("other_cpu_use_cpus"):
        assert f"{others:.2f} of the {machine['other_cpu_use_cpus']} CPUs this process may run on" in header


def test_busy_threshold() -> None:
    from streamdet.benchmarks.report import BUSY_OTHER_CPUS, busy_threshold

    assert busy_threshold(None) == busy_threshold(1) == busy_threshold(2) == BUSY_OTHER_CPUS == 0.2
    assert busy_threshold(64) == pytest.approx(6.4)


# ---- the shell helpers off Linux ------------------------------------------------------------------------------------
def test_avx2_mask_off_linux_says_it_needs_linux(tmp_path) -> None:
    """An Intel Mac (x86_64, no /proc/cpuinfo) was told its CPU offers no CPUID faulting."""
    shim = tmp_path / "bin"
    shim.mkdir()
    uname = shim / "uname"
    uname.write_text('#!/bin/sh\ncase "$1" in -s) echo Darwin ;; -m) echo x86_64 ;; *) echo Darwin ;; esac\n')
    uname.chmod(0o755)
    env = {**os.environ, "PATH": f"{shim}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run([str(REPO / "benchmarks" / "avx2_only.sh"), "true"], capture_output=True, text=True, env=env,
                          timeout=60, check=False)  # fmt: skip
    assert done.returncode == 2 and "need Linux" in done.stderr and "Darwin" in done.stderr
    assert "cpuid_fault" not in done.stderr


def test_replay_readme_counts_cpus_without_nproc() -> None:
    script = (REPO / "benchmarks" / "replay_readme.sh").read_text()
    commands = [line for line in script.splitlines() if not line.lstrip().startswith("#")]
    assert not any("nproc " in line.split(">")[0] or line.strip().startswith("nproc") for line in commands)
    (count,) = [line for line in commands if "usable_cpus" in line]
    command = count.split(">")[0].replace('"$BIN/python"', sys.executable)
    done = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=60, check=False, cwd=REPO)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) == cpu.usable_cpus()
