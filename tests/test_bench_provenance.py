"""What a streamdet-bench result records of where it came from (bench review M4), the peak probe at the start and the
end apart (L2), percentiles of few samples (L6), the --quick skip's wording (L1) and ASCII-only sizes (L8)."""

from __future__ import annotations

import hashlib
import json
import subprocess

import pytest
from click.testing import CliRunner

import streamdet
from streamdet.benchmarks import provenance, report
from streamdet.benchmarks.cli import main
from streamdet.benchmarks.probe import ProbeResult
from streamdet.benchmarks.run import BenchConfig
from streamdet.benchmarks.timing import summarize
from streamdet.core import cpu

# ---- the CPU's identity ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, expected",
    [
        ("processor : 0\nvendor_id : AuthenticAMD\ncpu family : 25\nmodel : 17\nmodel name : AMD EPYC\nstepping : 1\n"
         "processor : 1\nvendor_id : Other\ncpu family : 7\nmodel : 9\nstepping : 2\n",
         {"vendor_id": "AuthenticAMD", "family": 25, "model": 17, "stepping": 1}),
        ("processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\nmodel\t\t: 167\nstepping\t: unknown\n",
         {"vendor_id": "GenuineIntel", "family": 6, "model": 167, "stepping": None}),  # a VM hides the stepping
        ("processor : 0\nvendor_id : GenuineIntel\ncpu family : 6\n", {"vendor_id": "GenuineIntel", "family": 6, "model": None,
                                                                       "stepping": None}),  # fields missing
        ("processor : 0\nCPU implementer : 0x41\nCPU part : 0xd0c\n", dict.fromkeys(("vendor_id", "family", "model", "stepping"))),
        ("vendor_id : X\ncpu family : \u0662\u0665\nmodel : 99999999\n", {"vendor_id": "X", "family": None, "model": None,
                                                                          "stepping": None}),  # fmt: skip
        ("", dict.fromkeys(("vendor_id", "family", "model", "stepping"))),
    ],
)
def test_cpu_identity(tmp_path, text, expected):
    path = tmp_path / "cpuinfo"
    path.write_text(text)
    assert cpu.cpu_identity(path) == expected
    assert cpu.cpu_vendor_family(path) == (expected["vendor_id"], expected["family"])


def test_cpu_identity_without_a_file(tmp_path):
    assert cpu.cpu_identity(tmp_path / "absent") == dict.fromkeys(("vendor_id", "family", "model", "stepping"))


def test_header_names_the_identity_and_older_results_still_render():
    machine = {"cpu_model": "AMD EPYC", "cpu_flags": ["avx2"], "logical_cpus": 2, "load_average_1_5_15": [0, 0, 0],
               "onnxruntime": "1", "torch": "2", "cpu_mhz": None}  # fmt: skip
    meta = {"date": "d", "preset": "p", "machine": machine, "threads": 2, "repeat": 1, "warmup": 1, "budget_s": 1.0}
    assert "AMD EPYC (avx2), 2 logical CPUs" in report.format_header(meta, ProbeResult((1.0,), 8, 2))
    machine["cpu_identity"] = {"vendor_id": "AuthenticAMD", "family": 25, "model": 17, "stepping": None}
    assert "AMD EPYC (avx2), AuthenticAMD family 25 model 17, 2 logical CPUs" in report.format_header(meta, ProbeResult((1.0,), 8, 2))


# ---- provenance --------------------------------------------------------------------------------------------------


def test_provenance_keys():
    meta = provenance.provenance("streamdet-bench --quick", "timing")
    assert list(meta)[:3] == ["schema_version", "mode", "streamdet_version"]
    assert meta["schema_version"] == provenance.SCHEMA_VERSION == 2 and meta["streamdet_version"] == streamdet.__version__
    assert meta["command"] == "streamdet-bench --quick" and meta["mode"] == "timing" and "T" in meta["date"]


def test_git_commit_of_this_checkout():
    found = provenance.git_commit()
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=provenance.HERE, capture_output=True, text=True, check=False)
    except OSError:
        pytest.skip("no git here")
    if head.returncode != 0:
        assert found == {"commit": None, "dirty": None}
    else:
        assert len(found["commit"]) == 40 and isinstance(found["dirty"], bool)


def test_git_commit_never_fails(tmp_path, monkeypatch):
    assert provenance.git_commit(tmp_path) == {"commit": None, "dirty": None}  # not a checkout
    assert provenance.git_commit(tmp_path / "absent") == {"commit": None, "dirty": None}

    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")

    monkeypatch.setattr(provenance.subprocess, "run", no_git)
    assert provenance.git_commit() == {"commit": None, "dirty": None}

    def hangs(*args, **kwargs):
        raise subprocess.TimeoutExpired("git", provenance.GIT_TIMEOUT_S)

    monkeypatch.setattr(provenance.subprocess, "run", hangs)
    assert provenance.provenance("c", "timing")["git_commit"] is None


def test_git_commit_of_an_untracked_copy_is_unknown(tmp_path):
    """A copy of the package inside another checkout (an installed one in a virtual environment) is not that
    checkout's code."""
    try:
        done = subprocess.run(["git", "init", "-q", str(tmp_path)], capture_output=True, check=False)
    except OSError:
        pytest.skip("no git here")
    if done.returncode != 0:
        pytest.skip("git init failed")
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    assert provenance.git_commit(tmp_path / "pkg") == {"commit": None, "dirty": None}


def test_manifest_sha256(tiny_export, tmp_path):
    want = hashlib.sha256((tiny_export / "manifest.json").read_bytes()).hexdigest()
    assert provenance.manifest_sha256(tiny_export) == want
    assert provenance.manifest_sha256(tmp_path) is None


def test_flops_only_json_has_the_same_meta_and_units(tmp_path):
    out = tmp_path / "f.json"
    result = CliRunner().invoke(main, ["--flops-only", "--preset", "tiny", "--resolution", "128x72", "--json", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    meta = doc["meta"]
    assert meta["schema_version"] == provenance.SCHEMA_VERSION and meta["mode"] == "flops-only"
    assert meta["streamdet_version"] == streamdet.__version__ and {"git_commit", "git_dirty", "date", "command"} <= set(meta)
    assert meta["preset"] == "tiny" and meta["resolutions"] == [[128, 72]] and meta["command"].startswith("streamdet-bench ")
    assert doc["units"].startswith("GMAC") and doc["unit"] == doc["units"]  # the older key kept for older readers
    assert doc["rows"] and {"module", "gmac", "paper_gmac"} <= set(doc["rows"][0])


# ---- the peak probe at the start and the end ------------------------------------------------------------------


def _header(probes):
    machine = {"cpu_model": "x", "cpu_flags": ["avx2"], "logical_cpus": 2, "load_average_1_5_15": [0, 0, 0], "onnxruntime": "1",
               "torch": "2", "cpu_mhz": None}  # fmt: skip
    meta = {"date": "d", "preset": "p", "machine": machine, "threads": 2, "repeat": 1, "warmup": 1, "budget_s": 1.0}
    return report.format_header(meta, probes[0].merged(probes[1]), probes)


@pytest.mark.parametrize("end_best, warned", [(135.0, False), (120.0, False), (114.0, True), (102.0, True), (160.0, True)])
def test_a_drift_of_the_probe_is_printed_and_warned(end_best, warned):
    start, end = ProbeResult((92.0, 134.0, 135.0, 134.0), 256, 2), ProbeResult((83.0, end_best, 67.0), 256, 2)
    header = _header((start, end))
    assert f"at the start best 135.0 (median 134.0), at the end best {end_best:.1f}" in header
    assert ("WARNING: the peak probe's best run changed by" in header) == warned
    doc = report.peak_to_dict(start.merged(end), (start, end))
    assert doc["gflops_per_s"] == max(135.0, end_best) and doc["runs"] == 7  # the merged keys as before
    assert doc["start"]["runs"] == 4 and doc["end"]["gflops_per_s"] == end_best
    assert doc["end_over_start"] == pytest.approx(end_best / 135.0) and doc["drift_warning"] == warned


def test_a_drift_warning_quotes_both_probes():
    header = _header((ProbeResult((135.1,), 256, 2), ProbeResult((102.0,), 256, 2)))
    assert "changed by -25% between the start (135.1 GFLOP/s) and the end (102.0)" in header


# ---- few samples, the --quick skip, --repeat, sizes --------------------------------------------------------------


def test_p95_of_fewer_than_20_samples_is_not_printed():
    few, many = summarize([84.0, 84.0, 185.0]), summarize([1.0] * 19 + [3.0])
    assert "p95         n/a" in report._lane_line("image lane alone", few) and "185" in report._lane_line("x", few)  # min-max
    assert "p95     1.10 ms" in report._lane_line("x", many)
    assert report._ms(few) == "84.0 (n/a)" and report._ms(many) == "1.00 (1.10)"


def test_help_says_first_cold_run_and_what_repeat_governs():
    result = CliRunner().invoke(main, ["--help"], terminal_width=400)
    text = " ".join(result.output.split())
    assert "first, cold fp32 run (not the median)" in text
    assert "Timed runs per measurement of the Table 3 rows" in text and "The streaming section has its own counts" in text


@pytest.mark.parametrize("repeat, quick, floor", [(1, True, 1), (1, False, 1), (2, False, 2), (None, True, 2), (None, False, 3)])
def test_a_small_repeat_is_not_refused_by_the_timing_floor(repeat, quick, floor):
    timing = BenchConfig(repeat=repeat, quick=quick).timing()
    assert timing.min_repeat == floor <= timing.repeat
