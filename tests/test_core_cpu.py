"""streamdet.core.cpu (the flags the kernels see) and the AVX2-only CPUID mask of benchmarks/avx2_only.sh."""

from __future__ import annotations

import json
import os
import platform
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from streamdet.core import cpu
from streamdet.replay.report import cpu_info, cpu_line

REPO = Path(__file__).resolve().parents[1]
WRAPPER = REPO / "benchmarks" / "avx2_only.sh"

ZEN4_FLAGS = "fpu sse2 avx avx2 fma f16c avx512f avx512dq avx512ifma avx512cd avx512bw avx512vl avx512_bf16 avx512vbmi avx512_vbmi2 avx512_vnni avx512_bitalg avx512_vpopcntdq cpuid_fault"
SPR_EXTRA = "amx_bf16 amx_tile amx_int8 avx_vnni avx512_fp16 avx_ifma avx_vnni_int8 avx10"


# numpy CPU feature tables (numpy's __cpu_features__) injected so the tests do not depend on this host's CPUID:
# a Zen 4 as it is, the same under the AVX2 mask, and none at all (the mask's variable is then trusted)
ZEN4_FEATURES = {"AVX": True, "AVX2": True, "FMA3": True, "F16C": True, "AVX512F": True, "AVX512BW": True, "AVX512VNNI": True,
                 "AVX512BF16": True, "AVX512FP16": False, "ASIMD": False}  # fmt: skip
MASKED_FEATURES = {k: v and not k.startswith("AVX512") for k, v in ZEN4_FEATURES.items()}
NO_TABLE: dict[str, bool] = {}


def cpuinfo_text(model: str, flags: str, processors: int = 2) -> str:
    block = f"processor\t: {{i}}\nvendor_id\t: AuthenticAMD\nmodel name\t: {model}\nflags\t\t: {flags}\n\n"
    return "".join(block.format(i=i) for i in range(processors))


@pytest.fixture
def zen4(tmp_path: Path) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(cpuinfo_text("AMD EPYC 9B14", ZEN4_FLAGS + " " + SPR_EXTRA))
    return path


def test_flags_unmasked_are_the_silicon(zen4: Path) -> None:
    flags = cpu.cpu_flags(zen4, environ={})
    assert {"avx2", "avx512f", "avx512_vnni", "amx_tile", "avx_vnni"} <= flags
    assert cpu.cpu_model(zen4) == "AMD EPYC 9B14"


def test_avx2_mask_hides_everything_above_avx2(zen4: Path) -> None:
    flags = cpu.cpu_flags(zen4, environ={cpu.CPUID_MASK_ENV: "avx2"}, features=MASKED_FEATURES)
    assert {"avx", "avx2", "fma", "f16c", "sse2", "cpuid_fault"} <= flags
    hidden = set(cpu.read_cpuinfo(zen4)[1]) - flags
    assert hidden == set((ZEN4_FLAGS + " " + SPR_EXTRA).split()) - flags
    assert not any(f.startswith(("avx512", "amx", "avx10")) for f in flags)
    assert not {"avx_vnni", "avx_ifma", "avx_vnni_int8"} & flags


def test_kernel_flags_are_the_visible_ones_in_the_reports_order(zen4: Path, tmp_path: Path) -> None:
    unmasked = cpu.kernel_flags(zen4, environ={})
    assert unmasked == cpu.X86_KERNEL_FLAGS  # this fake part has every x86 one of them
    assert cpu.KERNEL_FLAGS[: len(cpu.X86_KERNEL_FLAGS)] == cpu.X86_KERNEL_FLAGS  # x86's order kept, ARM's after it
    masked = cpu.kernel_flags(zen4, environ={cpu.CPUID_MASK_ENV: "avx2"}, features=MASKED_FEATURES)
    assert masked == ("avx", "avx2", "fma", "f16c")
    bare = tmp_path / "bare"
    bare.write_text(cpuinfo_text("Old", "fpu sse2 avx512_unknown"))
    assert cpu.kernel_flags(bare, environ={}) == ()
    assert cpu.kernel_flags(tmp_path / "missing", environ={}, features=NO_TABLE) == ()


@pytest.mark.parametrize("value", ["avx512", "AVX2", "sse", " avx2"])
def test_unknown_mask_names_the_value(value: str) -> None:
    with pytest.raises(ValueError, match=repr(value).replace("[", r"\[")):
        cpu.cpuid_mask({cpu.CPUID_MASK_ENV: value})


def test_empty_mask_is_none() -> None:
    assert cpu.cpuid_mask({cpu.CPUID_MASK_ENV: ""}) is None
    assert cpu.cpuid_mask({}) is None


@pytest.mark.parametrize(
    "text",
    ["", "garbage without colons\n\x00\xff", "flags\t:\nmodel name\t:   \n", "model name : X\nflags : a b\n" * 3],
)
def test_malformed_or_empty_cpuinfo(tmp_path: Path, text: str) -> None:
    path = tmp_path / "cpuinfo"
    path.write_bytes(text.encode("latin-1"))  # a NUL and a byte that is not UTF-8 among them
    model, flags = cpu.read_cpuinfo(path)
    assert model in (None, "X") and isinstance(flags, frozenset)
    assert cpu.cpu_model(path)  # falls back to the platform's name
    masked = cpu.cpu_flags(path, environ={cpu.CPUID_MASK_ENV: "avx2"}, features=MASKED_FEATURES)
    assert masked <= flags | cpu.numpy_flags(MASKED_FEATURES)  # numpy's where the text has no flags line


def test_missing_cpuinfo(tmp_path: Path) -> None:
    assert cpu.read_cpuinfo(tmp_path / "absent") == (None, frozenset())
    assert cpu.cpu_flags(tmp_path / "absent", environ={}, features=NO_TABLE) == frozenset()


def test_first_processor_decides(tmp_path: Path) -> None:
    path = tmp_path / "cpuinfo"
    path.write_text(cpuinfo_text("First", "avx2") + cpuinfo_text("Second", "avx2 avx512f", processors=1))
    assert cpu.read_cpuinfo(path) == ("First", frozenset({"avx2"}))


def test_replay_cpu_line_names_the_mask(zen4: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The variable of this process's environment, with the CPUID it claims (features without AVX-512) injected."""
    monkeypatch.setenv(cpu.CPUID_MASK_ENV, "avx2")
    info = cpu_info(zen4, features=MASKED_FEATURES)
    assert info["cpuid_mask"] == "avx2" and "avx512f" not in info["flags"] and "avx2" in info["flags"]
    assert "masked to avx2" in cpu_line(info)
    monkeypatch.delenv(cpu.CPUID_MASK_ENV)
    info = cpu_info(zen4, features=ZEN4_FEATURES)
    assert info["cpuid_mask"] is None and "avx512f" in info["flags"] and "masked" not in cpu_line(info)
    assert "masked" not in cpu_line({k: v for k, v in info.items() if k != "cpuid_mask"})  # replays recorded before


def test_mask_claimed_and_confirmed(zen4: Path) -> None:
    env = {cpu.CPUID_MASK_ENV: "avx2"}
    assert cpu.cpuid_mask(env, features=MASKED_FEATURES) == "avx2"
    info = cpu_info(zen4, environ=env, features=MASKED_FEATURES)
    assert info["cpuid_mask"] == "avx2" and "masked to avx2" in cpu_line(info)


@pytest.mark.parametrize(
    "features, says",
    [
        (ZEN4_FEATURES, "still reports AVX512F, AVX512BF16, AVX512BW and 1 more"),  # set by hand on an AVX-512 part
        ({**MASKED_FEATURES, "AVX512_SKX": True}, "still reports AVX512_SKX"),  # any AVX-512 feature, not only AVX512F
        ({"AVX2": False, "AVX512F": False, "ASIMD": True}, "reports no AVX2"),  # an ARM part: nothing to mask to AVX2
    ],
)
def test_mask_claimed_but_not_in_effect_is_refused(zen4: Path, features: dict, says: str) -> None:
    env = {cpu.CPUID_MASK_ENV: "avx2"}
    for call in (lambda: cpu.cpuid_mask(env, features=features), lambda: cpu_info(zen4, environ=env, features=features),
                 lambda: cpu.kernel_flags(zen4, environ=env, features=features)):  # fmt: skip
        with pytest.raises(ValueError, match="STREAMDET_CPUID_MASK='avx2', but the mask is not in effect") as raised:
            call()
        assert says in str(raised.value) and "LD_PRELOAD of benchmarks/avx2_only.sh" in str(raised.value)


def test_mask_without_a_numpy_table_is_trusted(zen4: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env = {cpu.CPUID_MASK_ENV: "avx2"}
    assert cpu.cpuid_mask(env, features=NO_TABLE) == "avx2"
    assert cpu.cpuid_mask(env, features={"SSE2": True}) == "avx2"  # a table that does not say
    monkeypatch.setattr(cpu, "numpy_cpu_features", lambda: None)  # numpy's table cannot be imported
    assert cpu.cpuid_mask(env) == "avx2" and cpu.kernel_flags(zen4, environ=env) == ("avx", "avx2", "fma", "f16c")


def test_mask_is_checked_against_this_process_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """No features given: this process's numpy table decides (the case of the audit: the variable set by hand)."""
    monkeypatch.setattr(cpu, "numpy_cpu_features", lambda: dict(ZEN4_FEATURES))
    with pytest.raises(ValueError, match="not in effect"):
        cpu.cpuid_mask({cpu.CPUID_MASK_ENV: "avx2"})
    monkeypatch.setattr(cpu, "numpy_cpu_features", lambda: dict(MASKED_FEATURES))
    assert cpu.cpuid_mask({cpu.CPUID_MASK_ENV: "avx2"}) == "avx2"


def _can_mask() -> str | None:
    if platform.system() != "Linux" or platform.machine() != "x86_64":
        return "CPUID masks need Linux on x86-64"
    if "cpuid_fault" not in cpu.read_cpuinfo()[1]:
        return "no CPUID faulting on this CPU or hypervisor"
    if shutil.which(os.environ.get("CC", "cc")) is None:
        return "no C compiler to build the mask"
    return None


needs_mask = pytest.mark.skipif(_can_mask() is not None, reason=str(_can_mask()))

PROBE = """
import json, os
import numpy as np
import onnxruntime
from streamdet.core.cpu import cpu_flags
features = np._core._multiarray_umath.__cpu_features__
print(json.dumps({"numpy_avx512f": features["AVX512F"], "numpy_avx2": features["AVX2"],
                  "mask": os.environ.get("STREAMDET_CPUID_MASK"), "flags": sorted(cpu_flags())}))
"""


def _masked(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "STREAMDET_CACHE": str(tmp_path / "cache")}
    env.pop(cpu.CPUID_MASK_ENV, None)
    return subprocess.run([str(WRAPPER), *args], capture_output=True, text=True, env=env, timeout=300, check=False)


@needs_mask
def test_mask_makes_numpy_and_the_report_see_avx2_only(tmp_path: Path) -> None:
    done = _masked([sys.executable, "-c", PROBE], tmp_path)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["mask"] == "avx2" and seen["numpy_avx2"] is True
    assert seen["numpy_avx512f"] is False
    assert "avx2" in seen["flags"] and not any(f.startswith("avx512") for f in seen["flags"])
    assert len(list((tmp_path / "cache").glob("cpuid_mask_avx2_*.so"))) == 1  # built once, named by its source
    again = _masked([sys.executable, "-c", PROBE], tmp_path)
    assert again.returncode == 0 and json.loads(again.stdout.strip().splitlines()[-1]) == seen


@needs_mask
def test_mask_is_inherited_by_child_processes(tmp_path: Path) -> None:
    child = f"import subprocess, sys; sys.exit(subprocess.run([sys.executable, '-c', {PROBE!r}]).returncode)"
    done = _masked([sys.executable, "-c", child], tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["numpy_avx512f"] is False


@needs_mask
def test_other_segfaults_still_crash(tmp_path: Path) -> None:
    done = _masked([sys.executable, "-c", "import ctypes; ctypes.string_at(0)"], tmp_path)
    assert done.returncode == -signal.SIGSEGV


@needs_mask
def test_mask_clears_pythonfaulthandler_and_refuses_x_faulthandler(tmp_path: Path) -> None:
    """Python's faulthandler takes the CPUID faults the mask answers (exit 139 under PYTHONFAULTHANDLER=1, as CI
    systems set it): the wrapper clears the variable, and refuses ``-X faulthandler`` / ``-X dev``."""
    env = {**os.environ, "STREAMDET_CACHE": str(tmp_path / "cache"), "PYTHONFAULTHANDLER": "1"}
    env.pop(cpu.CPUID_MASK_ENV, None)
    done = subprocess.run([str(WRAPPER), sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300,
                          check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["numpy_avx512f"] is False and "PYTHONFAULTHANDLER" in done.stderr
    for flag in (["-X", "faulthandler"], ["-X", "dev"], ["-Xdev"]):
        refused = _masked([sys.executable, *flag, "-c", "print(1)"], tmp_path)
        assert refused.returncode == 2 and "faulthandler" in refused.stderr, flag


def test_wrapper_without_command_says_how(tmp_path: Path) -> None:
    done = subprocess.run([str(WRAPPER)], capture_output=True, text=True, check=False)
    assert done.returncode == 2 and "usage" in done.stderr


@pytest.mark.parametrize("mask", [None, "avx2"])
def test_bench_header_names_the_mask(mask):
    from streamdet.benchmarks.probe import ProbeResult
    from streamdet.benchmarks.report import format_header

    machine = {"cpu_model": "AMD EPYC", "cpu_flags": ["avx2", "fma"], "logical_cpus": 2, "load_average_1_5_15": [0.1, 0.2, 0.3],
               "onnxruntime": "1", "torch": "2", "cpu_mhz": None, "nominal_peak_gflops_per_s": None}  # fmt: skip
    if mask is not None:
        machine["cpuid_mask"] = mask
    meta = {"date": "2026-12-05", "preset": "tiny", "machine": machine, "threads": 2, "repeat": 3, "warmup": 1, "budget_s": 2.0}
    header = format_header(meta, ProbeResult((100.0, 120.0), 256, 2))
    assert ("CPUID masked to avx2" in header) == (mask is not None)
    assert "AMD EPYC (avx2, fma" in header
