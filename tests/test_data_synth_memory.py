"""streamdet-synth generate and memory: a resolution / --workers combination the machine cannot hold is refused before
any work, in one line naming the options; a MemoryError during the run is one line too, and leaves --out as it was.
No test allocates more than a tiny dataset: the available-memory probe is replaced."""

from __future__ import annotations

from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest
from click.testing import CliRunner

import streamdet.data.synth_memory as memory
import streamdet.data.synth_writer as writer
from streamdet.data.synth_cli import main as synth_main

GB = 10**9


def _snapshot(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def _no_simulation(monkeypatch) -> None:
    def write_scene(*args, **kwargs):
        raise AssertionError("a scene was simulated although the run should have been refused first")

    monkeypatch.setattr(writer, "_write_scene", write_scene)


def _error_line(output: str) -> str:
    assert "Traceback" not in output, output
    (line,) = [x for x in output.splitlines() if x.startswith("Error")]
    return line


def test_the_estimate_adds_up_per_process():
    per = memory.peak_bytes_per_process((1600, 900))
    assert per == memory.PEAK_BASE_BYTES + memory.PEAK_BYTES_PER_PIXEL * 1600 * 900
    assert memory.processes(4, 2) == 2 and memory.processes(1, 9) == 1 and memory.processes(3, 9) == 3
    assert memory.peak_bytes((1600, 900), 1, 5) == per
    assert memory.peak_bytes((1600, 900), 3, 5) == 3 * per + memory.PEAK_BASE_BYTES  # and the waiting parent
    assert memory.peak_bytes((1600, 900), 8, 2) == 2 * per + memory.PEAK_BASE_BYTES  # no more processes than scenes
    assert memory.peak_bytes((4096, 2304), 1, 1) > 5 * GB  # the largest accepted size: several GB per process


def test_memory_problem_names_the_options_and_what_is_available(monkeypatch):
    monkeypatch.setattr(memory, "available_memory", lambda: (4 * GB, None))
    problem = memory.memory_problem((4096, 2304), 1, 2)
    assert problem is not None and "\n" not in problem
    assert "--resolution 4096x2304 with --workers 1" in problem and "4.0 GB available" in problem
    assert "lower --resolution" in problem and "fewer --workers" not in problem  # one process: fewer is no remedy
    problem = memory.memory_problem((1600, 900), 8, 8)
    assert "--resolution 1600x900 with --workers 8 (8 scene(s) simulated at once)" in problem
    assert "fewer --workers" in problem
    assert memory.memory_problem((1600, 900), 1, 8) is None
    assert memory.memory_problem((1600, 900), 8, 1) is None  # one scene: one process, whatever --workers says

    monkeypatch.setattr(memory, "available_memory", lambda: (None, 5 * GB))  # ulimit -v 5000000, as the review ran
    problem = memory.memory_problem((4096, 2304), 1, 1)
    assert "address space per process" in problem and "ulimit -v" in problem
    assert memory.memory_problem((1600, 900), 4, 4) is None  # the limit is per process

    monkeypatch.setattr(memory, "available_memory", lambda: (None, None))  # the machine does not say: nothing refused
    assert memory.memory_problem((4096, 2304), 64, 64) is None


def test_the_probe_reads_meminfo_and_cgroups(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       32000000 kB\nMemFree:  100 kB\nMemAvailable:   22834472 kB\n")
    assert memory._meminfo_available(meminfo) == 22834472 * 1024
    meminfo.write_text("MemTotal:       32000000 kB\n")
    assert memory._meminfo_available(meminfo) is None
    assert memory._meminfo_available(tmp_path / "absent") is None

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "memory.max").write_text("max\n")
    (v2 / "memory.current").write_text("123\n")
    assert memory._cgroup_left(v2) is None
    (v2 / "memory.max").write_text(f"{8 * GB}\n")
    assert memory._cgroup_left(v2) == 8 * GB - 123
    v1 = tmp_path / "v1"
    (v1 / "memory").mkdir(parents=True)
    (v1 / "memory" / "memory.limit_in_bytes").write_text("9223372036854771712\n")  # v1's "no limit"
    (v1 / "memory" / "memory.usage_in_bytes").write_text("3973672960\n")
    assert memory._cgroup_left(v1) is None
    (v1 / "memory" / "memory.limit_in_bytes").write_text(f"{5 * GB}\n")
    assert memory._cgroup_left(v1) == 5 * GB - 3973672960
    (v1 / "memory" / "memory.limit_in_bytes").write_text(f"{3 * GB}\n")  # over the limit already: nothing left
    assert memory._cgroup_left(v1) == 0
    assert memory._cgroup_left(tmp_path / "none") is None
    # the page cache the kernel drops before it kills (inactive_file) is not counted as used: a 4 GiB container
    # with 3.5 GiB of such cache refused the default 800x450 run
    (v2 / "memory.max").write_text(f"{4 * 2**30}\n")
    (v2 / "memory.current").write_text(f"{int(3.9 * 2**30)}\n")
    (v2 / "memory.stat").write_text(f"anon 12345\ninactive_file {int(3.5 * 2**30)}\nactive_file 1\n")
    assert memory._cgroup_left(v2) == 4 * 2**30 - (int(3.9 * 2**30) - int(3.5 * 2**30))
    (v1 / "memory" / "memory.stat").write_text("cache 5\ntotal_inactive_file 1000\n")
    assert memory._cgroup_left(v1) == 0  # 3 GB limit, 3.97 GB used, 1000 B of it reclaimable
    (v1 / "memory" / "memory.limit_in_bytes").write_text(f"{5 * GB}\n")
    assert memory._cgroup_left(v1) == 5 * GB - (3973672960 - 1000)

    total, per_process = memory.available_memory()  # this machine: whatever it says, in bytes
    assert total is None or total >= 0
    assert per_process is None or per_process > 0


@pytest.mark.parametrize("args, named", [
    (["--scenes", "1", "--resolution", "4096x2304"], "--resolution 4096x2304 with --workers 1"),
    (["--scenes", "4", "--resolution", "1600x900", "--workers", "4"], "--resolution 1600x900 with --workers 4"),
])  # fmt: skip
def test_generate_refuses_before_any_work(tmp_path, monkeypatch, args, named):
    monkeypatch.setattr(memory, "available_memory", lambda: (3 * GB, None))
    _no_simulation(monkeypatch)
    out = tmp_path / "parent" / "ds"
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), "--samples-per-scene", "1", *args])
    assert result.exit_code == 1, result.output
    line = _error_line(result.output)
    assert named in line and "3.0 GB available" in line and "lower --resolution" in line
    assert not (tmp_path / "parent").exists()  # nothing made: no --out, no staging folder


@pytest.mark.parametrize("exc, said", [
    (MemoryError("Unable to allocate 44.8 MiB for an array with shape (3916301, 3) and data type float32"),
     "out of memory (Unable to allocate 44.8 MiB"),
    (BrokenProcessPool("A process in the process pool was terminated abruptly"), "a worker process ended abruptly"),
])  # fmt: skip
def test_running_out_of_memory_mid_run_is_one_line_and_leaves_out_as_it_was(tmp_path, monkeypatch, exc, said):
    original = writer._write_scene

    def write_scene(out, config, index, progress):
        if index == 1:
            raise exc
        return original(out, config, index, progress)

    monkeypatch.setattr(writer, "_write_scene", write_scene)
    out = tmp_path / "ds"
    before = _snapshot(tmp_path)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), "--scenes", "2", "--samples-per-scene", "1",
                                             "--resolution", "32x18"])  # fmt: skip
    assert result.exit_code == 1, result.output
    line = _error_line(result.output)
    assert "--resolution 32x18 with --workers 1" in line and said in line and "removed what this run had written" in line
    assert "fewer --workers" not in line  # one process: fewer is no remedy
    assert _snapshot(tmp_path) == before
