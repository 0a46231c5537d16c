"""streamdet.core.cpu's CPU counts (portability audit M1, M2): the CPUs this process may use (affinity, cgroup quota),
the cgroup quota parsed from its files' texts, physical cores from /sys topology or /proc/cpuinfo, and the CPU's
vendor and family. Each parser against a naive reference, and on malformed and missing input."""

from __future__ import annotations

import math
import os
from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from streamdet.core import cpu


# ---- naive references --------------------------------------------------------------------------------------------
def naive_quota(quota: int, period: int) -> int | None:
    return None if quota <= 0 or period <= 0 else max(1, math.ceil(Fraction(quota, period)))


def naive_cpu_list(cpus: set[int]) -> str:
    """A Linux cpu list of ``cpus``, runs of consecutive numbers as ranges."""
    parts, ordered = [], sorted(cpus)
    start = prev = ordered[0]
    for c in ordered[1:] + [None]:
        if c is not None and c == prev + 1:
            prev = c
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if c is not None:
            start = prev = c
    return ",".join(parts)


# ---- the cgroup quota --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, expected",
    [
        ("max 100000\n", None),  # v2 without a quota
        ("max", None),
        ("200000 100000\n", 2),  # docker --cpus=2
        ("150000 100000", 2),  # 1.5 CPUs: ceil
        ("50000 100000", 1),
        ("1 100000", 1),  # at least 1
        ("6400000 100000", 64),
        ("200000 50000", 4),
    ],
)
def test_cgroup_v2_cpu_max(text, expected):
    assert cpu.cgroup_cpu_limit(text) == expected


@pytest.mark.parametrize(
    "text",
    ["", "\n", "200000", "200000 100000 5", "abc 100000", "200000 abc", "1e5 100000", "1_000 100000", "0 100000",
     "-1 100000", "200000 0", "200000 -100000", "2.5 1", "\x00\xff", "\u0663 1", "9" * 5000 + " 1"],
)  # fmt: skip
def test_malformed_cpu_max_is_ignored(text):
    assert cpu.cgroup_cpu_limit(text) is None


@pytest.mark.parametrize(
    "quota, period, expected",
    [("-1\n", "100000\n", None), ("400000\n", "100000\n", 4), ("250000", "100000", 3), ("x", "100000", None),
     ("100000", "", None), (None, "100000", None), ("100000", None, None), (None, None, None)],
)  # fmt: skip
def test_cgroup_v1_quota_and_period(quota, period, expected):
    assert cpu.cgroup_cpu_limit(None, quota, period) == expected


@given(st.integers(-(10**12), 10**12), st.integers(-(10**7), 10**7))
def test_quota_matches_the_naive_reference(quota, period):
    assert cpu.cgroup_cpu_limit(f"{quota} {period}\n") == naive_quota(quota, period)
    assert cpu.cgroup_cpu_limit(None, f"{quota}\n", f"{period}\n") == naive_quota(quota, period)


@given(st.text(max_size=40), st.text(max_size=20), st.text(max_size=20))
def test_any_text_gives_none_or_a_positive_count(v2, quota, period):
    for limit in (cpu.cgroup_cpu_limit(v2), cpu.cgroup_cpu_limit(None, quota, period)):
        assert limit is None or (isinstance(limit, int) and limit >= 1)


def _cgroup(root: Path, v2: str | None = None, v1: tuple[str, str] | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    if v2 is not None:
        (root / "cpu.max").write_text(v2)
    if v1 is not None:
        (root / "cpu").mkdir()
        (root / "cpu" / "cpu.cfs_quota_us").write_text(v1[0])
        (root / "cpu" / "cpu.cfs_period_us").write_text(v1[1])
    return root


def test_read_cgroup_files(tmp_path):
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "v2", v2="300000 100000\n")) == 3
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "v2max", v2="max 100000\n")) is None
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "v1", v1=("200000\n", "100000\n"))) == 2
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "v1none", v1=("-1\n", "100000\n"))) is None
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "empty")) is None
    assert cpu.read_cgroup_cpu_limit(tmp_path / "absent") is None
    assert cpu.read_cgroup_cpu_limit(_cgroup(tmp_path / "both", v2="100000 100000", v1=("800000", "100000"))) == 1
    bad = _cgroup(tmp_path / "dir")
    (bad / "cpu.max").mkdir()  # unreadable: a directory
    assert cpu.read_cgroup_cpu_limit(bad) is None


# ---- usable_cpus -------------------------------------------------------------------------------------------------
@pytest.fixture
def machine(monkeypatch, tmp_path):
    """Set the scheduler's view (os.process_cpu_count, sched_getaffinity, cpu_count) and the cgroup root."""

    def set_up(*, process=None, affinity=None, logical=None, cgroup=None):
        if process is None:
            monkeypatch.delattr(os, "process_cpu_count", raising=False)
        else:
            monkeypatch.setattr(os, "process_cpu_count", lambda: process, raising=False)
        if affinity is None:
            monkeypatch.delattr(os, "sched_getaffinity", raising=False)
        elif isinstance(affinity, Exception):
            def refuse(pid):
                raise affinity

            monkeypatch.setattr(os, "sched_getaffinity", refuse, raising=False)
        else:
            monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(affinity)), raising=False)
        monkeypatch.setattr(os, "cpu_count", lambda: logical)
        root = tmp_path / f"cgroup{len(list(tmp_path.iterdir()))}"
        _cgroup(root, v2=cgroup)
        monkeypatch.setattr(cpu, "CGROUP_ROOT", root)

    return set_up


@pytest.mark.parametrize(
    "setup, expected",
    [
        (dict(process=6, affinity=8, logical=16), 6),  # Python 3.13+: os.process_cpu_count() decides
        (dict(affinity=8, logical=128), 8),  # taskset: the affinity mask, not the machine
        (dict(affinity=OSError("no"), logical=12), 12),  # the mask cannot be read: os.cpu_count()
        (dict(logical=12), 12),  # no sched_getaffinity (macOS, Windows)
        (dict(logical=None), 1),  # nothing known
        (dict(affinity=64, logical=64, cgroup="400000 100000\n"), 4),  # docker --cpus=4 on a 64-CPU host
        (dict(affinity=2, logical=64, cgroup="800000 100000\n"), 2),  # a quota above the mask
        (dict(affinity=8, logical=8, cgroup="max 100000\n"), 8),
        (dict(affinity=8, logical=8, cgroup="garbage"), 8),  # a quota that cannot be parsed is ignored
        (dict(process=0, affinity=3, logical=8), 3),  # a falsy count falls through
    ],
)
def test_usable_cpus(machine, setup, expected):
    machine(**setup)
    assert cpu.usable_cpus() == expected


def test_usable_cpus_on_this_machine():
    n = cpu.usable_cpus()
    assert isinstance(n, int) and 1 <= n <= (os.cpu_count() or 1)


def test_replay_cpu_info_counts_with_usable_cpus(machine):
    """One definition: the replay's "threads usable" is usable_cpus, quota included; logical_cpus the machine's."""
    from streamdet.replay.report import cpu_info, cpu_line

    machine(affinity=32, logical=128, cgroup="300000 100000\n")
    info = cpu_info()
    assert info["threads"] == cpu.usable_cpus() == 3 and info["logical_cpus"] == 128
    assert ", 3 threads usable (" in cpu_line(info)


# ---- cpu lists and physical cores --------------------------------------------------------------------------------
@given(st.sets(st.integers(0, 300), min_size=1, max_size=40))
def test_cpu_list_matches_the_naive_reference(cpus):
    text = naive_cpu_list(cpus)
    assert cpu.parse_cpu_list(text) == frozenset(cpus)
    assert cpu.parse_cpu_list(text + "\n") == frozenset(cpus)  # as read from /sys


@pytest.mark.parametrize("text", ["", "\n", ",", "1,", "a", "3-1", "-1", "1--2", "0-", "1.5", "0-70000", "\u0663", "1 2"])
def test_malformed_cpu_list(text):
    assert cpu.parse_cpu_list(text) is None


@given(st.text(max_size=30))
def test_any_cpu_list_text_parses_or_is_none(text):
    found = cpu.parse_cpu_list(text)
    assert found is None or (found and all(0 <= c < cpu.MAX_CPU_ID for c in found))


def test_count_cores():
    assert cpu.count_cores(["0,64\n", "1,65\n", "0,64\n", "1,65\n"]) == 2  # SMT pairs
    assert cpu.count_cores(["0-1", "0-1", "2-3", "2-3"]) == 2
    assert cpu.count_cores(["0", "1", "2"]) == 3  # no SMT
    assert cpu.count_cores([]) is None
    assert cpu.count_cores(["0,64", "garbage"]) is None


def _cpuinfo_block(i: int, package: int | None, core: int | None) -> str:
    lines = [f"processor\t: {i}", "vendor_id\t: GenuineIntel"]
    if package is not None:
        lines.append(f"physical id\t: {package}")
    if core is not None:
        lines.append(f"core id\t\t: {core}")
    return "\n".join(lines) + "\n\n"


def test_cpuinfo_cores():
    # 2 packages x 2 cores x 2 SMT threads: the core ids repeat across packages
    text = "".join(_cpuinfo_block(i, i // 4, (i // 2) % 2) for i in range(8))
    assert cpu.cpuinfo_cores(text) == 4
    assert cpu.cpuinfo_cores("".join(_cpuinfo_block(i, None, None) for i in range(4))) is None  # aarch64, s390
    assert cpu.cpuinfo_cores("") is None
    assert cpu.cpuinfo_cores("core id : 0\ncore id : 0\n\x00\xff") == 1


def _sys_tree(root: Path, siblings: dict[int, str]) -> Path:
    for i, text in siblings.items():
        topo = root / f"cpu{i}" / "topology"
        topo.mkdir(parents=True)
        (topo / "thread_siblings_list").write_text(text)
    return root


def test_physical_cores_among_the_affinity(monkeypatch, tmp_path):
    sys_cpu = _sys_tree(tmp_path / "sys", {0: "0,2\n", 1: "1,3\n", 2: "0,2\n", 3: "1,3\n"})
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2}, raising=False)  # two SMT siblings of one core
    assert cpu.physical_cores(sys_cpu, tmp_path / "absent") == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert cpu.physical_cores(sys_cpu, tmp_path / "absent") == 2


def test_physical_cores_falls_back_to_cpuinfo(monkeypatch, tmp_path):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    info = tmp_path / "cpuinfo"
    info.write_text("".join(_cpuinfo_block(i, 0, i // 2) for i in range(4)))
    assert cpu.physical_cores(tmp_path / "no_sys", info) == 2
    partial = _sys_tree(tmp_path / "partial", {0: "0-1", 1: "0-1"})  # cpu2, cpu3 missing: /proc/cpuinfo decides
    assert cpu.physical_cores(partial, info) == 2
    assert cpu.physical_cores(tmp_path / "no_sys", tmp_path / "absent") is None


def test_physical_cores_on_this_machine():
    n = cpu.physical_cores()
    assert n is None or 1 <= n <= (os.cpu_count() or 1)


# ---- vendor and family -------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, expected",
    [
        ("processor : 0\nvendor_id : AuthenticAMD\ncpu family : 25\nmodel : 17\n", ("AuthenticAMD", 25)),
        ("vendor_id\t: GenuineIntel\ncpu family\t: 6\n\nvendor_id\t: Other\ncpu family\t: 7\n", ("GenuineIntel", 6)),
        ("processor : 0\nCPU implementer : 0x41\nCPU architecture: 8\n", (None, None)),  # aarch64
        ("vendor_id : AuthenticAMD\ncpu family : twenty-five\n", ("AuthenticAMD", None)),
        ("vendor_id : AuthenticAMD\ncpu family : \u0662\u0665\n", ("AuthenticAMD", None)),
        ("vendor_id :\ncpu family : 99999999\n", (None, None)),
        ("", (None, None)),
        ("\x00\xff no colons", (None, None)),
    ],
)
def test_cpu_vendor_family(tmp_path, text, expected):
    path = tmp_path / "cpuinfo"
    path.write_bytes(text.encode("latin-1", errors="ignore") if "\xff" in text else text.encode("utf-8"))  # a byte not UTF-8
    assert cpu.cpu_vendor_family(path) == expected


def test_cpu_vendor_family_without_a_file(tmp_path):
    assert cpu.cpu_vendor_family(tmp_path / "absent") == (None, None)
