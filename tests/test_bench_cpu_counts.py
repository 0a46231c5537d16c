"""streamdet-bench's thread counts and CPU description (portability audit H1, M1, M2): on a machine with more CPUs
than one onnxruntime session takes (128 logical CPUs: 64 cores with SMT, two sockets) every count the bench picks
stays within 1..MAX_SESSION_THREADS and is checked before any timing; counts come from the CPUs this process may use;
the FMA x clock x cores figure is called an estimate, counts physical cores and does not double AVX-512 on Zen 4."""

from __future__ import annotations

import dataclasses
import os

import pytest

from streamdet.benchmarks import streaming
from streamdet.benchmarks.probe import ProbeResult, estimate_cores, machine_info, nominal_peak_gflops
from streamdet.benchmarks.report import format_header, format_rows
from streamdet.benchmarks.run import BenchConfig, BenchmarkError, resolve_stream_export
from streamdet.benchmarks.streaming import StreamingConfig
from streamdet.benchmarks.table import RowResult
from streamdet.benchmarks.thread_counts import check_session_threads, default_session_threads
from streamdet.benchmarks.timing import summarize
from streamdet.core import cpu
from streamdet.core.constants import MAX_SESSION_THREADS
from streamdet.runtime_ort.detector import DetectorConfig

BIG = 128  # logical CPUs of a 64-core part with SMT


@pytest.fixture
def cpus128(monkeypatch, tmp_path):
    """Every way of counting CPUs says 128; no cgroup quota."""
    monkeypatch.setattr(os, "cpu_count", lambda: BIG)
    monkeypatch.setattr(os, "process_cpu_count", lambda: BIG, raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(BIG)), raising=False)
    monkeypatch.setattr(cpu, "CGROUP_ROOT", tmp_path / "no_cgroup")
    assert cpu.usable_cpus() == BIG


@pytest.fixture
def helper128(monkeypatch):
    """The helper itself patched: the bench must count through it."""
    monkeypatch.setattr(os, "cpu_count", lambda: BIG)
    monkeypatch.setattr(cpu, "usable_cpus", lambda cgroup_root=None: BIG)


# ---- the counts' rule --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cpus, expected", [(1, 1), (2, 2), (63, 63), (64, 64), (65, 64), (128, 64), (1024, 64), (0, 1), (-3, 1)])
def test_default_session_threads_is_clamped(cpus, expected):
    assert default_session_threads(cpus) == expected == max(1, min(cpus, MAX_SESSION_THREADS))  # the naive rule


@pytest.mark.parametrize("value", [0, -1, MAX_SESSION_THREADS + 1, 128, True, 2.0, "2", None])
def test_check_session_threads_refuses_in_one_line(value):
    with pytest.raises(ValueError, match=rf"^X must be an int in 1\.\.{MAX_SESSION_THREADS}, got ") as e:
        check_session_threads(value, "X")
    assert "\n" not in str(e.value)


def test_check_session_threads_passes_the_range():
    assert [check_session_threads(v, "X") for v in (1, 2, MAX_SESSION_THREADS)] == [1, 2, MAX_SESSION_THREADS]


# ---- H1: 128 CPUs ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("patched", ["cpus128", "helper128"])
def test_the_benchs_thread_choices_stay_within_bounds_on_128_cpus(patched, request):
    request.getfixturevalue(patched)
    cfg = BenchConfig(preset="tiny", quick=True)
    assert cfg.row_threads() == MAX_SESSION_THREADS  # was os.cpu_count(): 128
    for stream in (cfg.streaming(), BenchConfig(preset="tiny").streaming(), StreamingConfig()):
        assert stream.wide_threads == MAX_SESSION_THREADS  # was os.cpu_count(): 128, refused by DetectorConfig
        DetectorConfig(slice_lane_threads=stream.wide_threads)  # the session the streaming section builds takes it
    assert resolve_stream_export(cfg).slices == 8  # the checks before any timing pass


def test_a_threads_count_past_the_cap_is_refused_before_any_timing(monkeypatch, cpus128):
    from streamdet.benchmarks import run

    def no_timing(*args, **kwargs):
        raise AssertionError("timing started")

    monkeypatch.setattr(run, "measure_peak", no_timing)
    monkeypatch.setattr(run, "measure_rows", no_timing)
    for threads in (BIG, 0):
        with pytest.raises(BenchmarkError, match=rf"BenchConfig.threads must be an int in 1\.\.{MAX_SESSION_THREADS}"):
            run.run_benchmark(BenchConfig(preset="tiny", quick=True, threads=threads))
    assert BenchConfig(threads=3).row_threads() == 3


@pytest.mark.parametrize("value", [0, MAX_SESSION_THREADS + 1, True, 1.5])
def test_streaming_config_refuses_a_wide_count_past_the_cap(value):
    with pytest.raises(ValueError, match="StreamingConfig.wide_slice_threads must be an int in"):
        StreamingConfig(wide_slice_threads=value)
    assert StreamingConfig(wide_slice_threads=3).wide_threads == 3


def test_the_streaming_section_runs_on_128_cpus(cpus128, monkeypatch, tiny_export_fp32):
    """The section itself on a tiny export, briefly: the slice session "with every core" asks for 64 threads (what
    DetectorConfig takes), not 128. The sessions are built with 1 thread so the test stays light."""
    asked = []
    build = streaming._detector

    def recording(export_dir, cfg, profiling=False, slice_threads=1, profile_dir=None):
        asked.append(slice_threads)
        DetectorConfig(slice_lane_threads=slice_threads)  # raises past the cap, as the real one would
        return build(export_dir, cfg, profiling, 1, profile_dir)

    monkeypatch.setattr(streaming, "_detector", recording)
    cfg = resolve_stream_export(BenchConfig(preset="tiny", export_dir=tiny_export_fp32, quick=True, repeat=2))
    result = streaming.measure_streaming(tiny_export_fp32, dataclasses.replace(cfg.streaming(), schedule_seconds=0.0))
    assert asked == [1, MAX_SESSION_THREADS] and result.all_cores == MAX_SESSION_THREADS
    assert result.idle_all_cores is not None


def test_one_usable_cpu_skips_the_wide_run(monkeypatch):
    monkeypatch.setattr(cpu, "usable_cpus", lambda cgroup_root=None: 1)
    assert BenchConfig().row_threads() == 1 and BenchConfig().streaming().wide_threads == 1


# ---- M1: what machine_info records -------------------------------------------------------------------------------
def test_machine_info_records_logical_and_usable_cpus(monkeypatch, tmp_path):
    monkeypatch.setattr(os, "cpu_count", lambda: BIG)
    monkeypatch.setattr(os, "process_cpu_count", lambda: 8, raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    root = tmp_path / "cgroup"
    root.mkdir()
    (root / "cpu.max").write_text("300000 100000\n")  # docker --cpus=3
    monkeypatch.setattr(cpu, "CGROUP_ROOT", root)
    m = machine_info(default_session_threads())
    assert m["logical_cpus"] == BIG and m["usable_cpus"] == 3 and m["threads"] == 3
    assert m["nominal_peak_gflops_per_s"] == m["peak_estimate_gflops_per_s"]  # the old key kept
    assert 1 <= m["peak_estimate_cores"] <= m["threads"]


# ---- M2: the estimate --------------------------------------------------------------------------------------------
def naive_estimate(threads, flags, mhz, cores=None, vendor=None, family=None):
    if mhz is None or "fma" not in flags:
        return None
    wide = "avx512f" in flags and not (vendor == "AuthenticAMD" and family == 25)
    used = threads if cores is None else max(1, min(threads, cores))
    return (16 if wide else 8) * 2 * 2 * (mhz / 1000.0) * used


@pytest.mark.parametrize(
    "args",
    [
        (2, ("avx2", "fma"), 2445.0),
        (2, ("avx2", "fma", "avx512f"), 2596.0, None, "GenuineIntel", 6),  # two 512-bit FMA pipes assumed
        (2, ("avx2", "fma", "avx512f"), 2596.0, None, "AuthenticAMD", 25),  # Zen 4: no doubling
        (2, ("avx2", "fma", "avx512f"), 2596.0, None, "AuthenticAMD", 26),  # not Zen 4: doubled
        (16, ("avx2", "fma"), 3000.0, 8, "GenuineIntel", 6),  # 16 SMT threads on 8 cores
        (4, ("avx2", "fma"), 3000.0, 64),  # fewer threads than cores
        (4, ("avx2",), 3000.0, 4),  # no FMA
        (4, ("avx2", "fma"), None, 4),  # no clock
        (1, (), 1000.0),
    ],
)
def test_estimate_matches_the_naive_rule(args):
    got, expected = nominal_peak_gflops(*args), naive_estimate(*args)
    assert got == pytest.approx(expected) if expected is not None else got is None


def test_estimate_on_zen4_is_half_the_old_doubled_figure():
    flags = ("avx2", "fma", "avx512f")
    assert nominal_peak_gflops(2, flags, 2596.0, 2, "AuthenticAMD", 25) == pytest.approx(nominal_peak_gflops(2, flags, 2596.0) / 2)
    assert estimate_cores(2, 1) == 1 and estimate_cores(2, None) == 2 and estimate_cores(1, 0) == 1


def _machine(**extra) -> dict:
    m = {"cpu_model": "AMD EPYC", "cpu_flags": ["avx2", "fma"], "logical_cpus": 2, "load_average_1_5_15": [0.1, 0.2, 0.3],
         "onnxruntime": "1", "torch": "2", "cpu_mhz": 2596.0}  # fmt: skip
    return {**m, **extra}


def _header(machine: dict) -> str:
    meta = {"date": "2026-12-05", "preset": "tiny", "machine": machine, "threads": 2, "repeat": 3, "warmup": 1, "budget_s": 2.0}
    return format_header(meta, ProbeResult((100.0, 120.0), 256, 2))


def test_header_calls_it_an_estimate_and_names_usable_cpus():
    header = _header(_machine(peak_estimate_gflops_per_s=83.1, nominal_peak_gflops_per_s=83.1, peak_estimate_cores=1,
                              physical_cores=1, usable_cpus=1))  # fmt: skip
    assert "estimate from FMA width x the reported 2596 MHz x 1 physical core(s) (not a bound): 83 GFLOP/s" in header
    assert "2 logical CPUs (1 usable by this process), 2 threads" in header
    assert "data-sheet" not in header and "upper bound" not in header


def test_header_of_an_older_result_still_renders():
    header = _header(_machine(nominal_peak_gflops_per_s=332.0))  # no usable_cpus, no peak_estimate_* keys
    assert "x 2 threads (not a bound): 332 GFLOP/s" in header and "2 logical CPUs, 2 threads" in header
    assert "estimate" not in _header(_machine(nominal_peak_gflops_per_s=None, cpu_mhz=None))


def test_rows_note_claims_no_bound():
    row = RowResult(module="conv", key="conv", kind="conv", gmac=1.0, graph_gmac=None, fp32=summarize([1.0, 1.0]),
                    fp16=None, torch=None)  # fmt: skip
    text = format_rows([row], ProbeResult((100.0,), 256, 2))  # the row's 2000 GFLOP/s outrun the probe
    assert "not an upper bound (nor is the estimate in the header)" in text and "data-sheet" not in text
