"""streamdet-bench end to end on the tiny preset (no assertions on speed), and its one-line errors."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

import streamdet
from streamdet.benchmarks.cli import main
from streamdet.benchmarks.provenance import SCHEMA_VERSION
from streamdet.benchmarks.run import image_resolutions
from streamdet.models.lifter_fold import folded_mac_ratio
from streamdet.models.presets import get_preset

TINY_LIFTER, TINY_NZ = get_preset("tiny").lifter, get_preset("tiny").grid.nz
ROW_KEYS = {"module", "gmac", "ms_fp32", "ms_fp16", "ms_torch", "gflops_per_s", "peak_fraction"}


# The run's other image rows are the paper's resolutions (test_image_resolutions); here one small stand-in, so that
# the end-to-end run checks the rows' plumbing without timing the tiny encoder at 1600x900 (most of its cost).
OTHER_RESOLUTIONS = ((192, 108),)
NUM_ROWS = 5 + 1 + len(OTHER_RESOLUTIONS)  # slice and 3D-conv rows, tiny's own 128x72 image row, the others'


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    args = ["--quick", "--preset", "tiny", "--repeat", "2", "--json", str(d / "b.json"), "--plot", str(d / "b.png")]
    args += ["--profile", str(d / "prof")]
    args += ["--stream-image-precision", "int8"]  # the streaming section: int8 image lane, fp32 slices
    args += ["--no-fp16"]  # the rows' fp16 column is measure_rows' (tests/test_benchmarks_table.py); int8 is timed here
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("streamdet.benchmarks.run.PAPER_RESOLUTIONS", OTHER_RESOLUTIONS)
        result = CliRunner().invoke(main, args)
    return result, d


def test_quick_tiny_run_writes_documented_json(quick_run):
    result, d = quick_run
    assert result.exit_code == 0, result.output
    doc = json.loads((d / "b.json").read_text())
    assert {"rows", "streaming", "meta", "peak", "targets", "units"} <= set(doc)
    modules = [r["module"] for r in doc["rows"]]
    assert len(modules) == NUM_ROWS  # tiny's own 128x72 plus the others (the paper's three in a real run)
    assert modules[5:] == ["image encoding 128x72"] + [f"image encoding {w}x{h}" for w, h in OTHER_RESOLUTIONS]
    assert [tuple(r) for r in doc["meta"]["resolutions"]] == [(128, 72), *OTHER_RESOLUTIONS]
    for r in doc["rows"]:
        assert ROW_KEYS <= set(r)
        assert r["ms_fp32"] > 0 and r["gflops_per_s"] > 0 and 0 < r["peak_fraction"]
        assert r["ms_fp16"] is None and r["ms_int8"] > 0  # --no-fp16; int8 by default
        # the 3D convolutions are exported over folded z (models/lifter_fold.py): the graph multiplies banded zeros
        folded = folded_mac_ratio(TINY_LIFTER, TINY_NZ) if r["key"].startswith("conv3d") else 1.0
        # the multi-head's branches are exported grouped across tasks (models/slice_split.py): zero blocks too
        grouped = r["key"] == "slice_multi_head"
        # the single head's regression is computed at the peaks only (models/peak_head.py): fewer MACs
        at_peaks = r["key"].startswith("slice_single_head")
        if grouped:
            assert r["graph_gmac_ratio"] > 1.0
        elif at_peaks:
            assert 0.5 < r["graph_gmac_ratio"] < 1.0
        else:
            assert r["graph_gmac_ratio"] == pytest.approx(folded)
        assert any("folded" in n for n in r["notes"]) == (folded != 1.0)
        assert any("grouped across the 6 tasks" in n for n in r["notes"]) == grouped
        assert any("at the decode's" in n for n in r["notes"]) == at_peaks
        # slice and 3D-conv graphs come from export-time rewrites: PyTorch is timed on the trained module and on those
        rewritten = not r["key"].startswith("image")
        assert (r["ms_torch_export_form"] is not None and r["ms_torch_export_form"] > 0) == rewritten
        assert any("export's rewrite" in n for n in r["notes"]) == rewritten
        assert r["fp32"]["count"] >= 2  # quick: --repeat 2, and never fewer than the minimum of 3 under a budget
        assert r["profile"]["fp32"]["ops"]
    assert len(doc["streaming"]["prepost"]) == 6 and "pillarize 30,000 points" in result.output
    assert any(t["name"].startswith("post-process 500 candidates") for t in doc["targets"])
    meta = doc["meta"]
    assert meta["preset"] == "tiny" and meta["threads"] >= 1 and meta["repeat"] == 2 and meta["machine"]["cpu_model"]
    # provenance (docs/cli.md, "streamdet-bench"): the schema, the code, the export timed, the CPU's identity
    assert meta["schema_version"] == SCHEMA_VERSION and meta["mode"] == "timing"
    assert meta["streamdet_version"] == streamdet.__version__ and "git_commit" in meta and "git_dirty" in meta
    assert meta["command"].startswith("streamdet-bench ") and meta["date"]
    assert len(meta["export_manifest_sha256"]) == 64 and meta["export_dir"] == "(temporary export)"
    assert set(meta["machine"]["cpu_identity"]) == {"vendor_id", "family", "model", "stepping"}
    # the peak probe at the start and at the end, apart (the merged keys stay)
    peak = doc["peak"]
    assert peak["runs"] == peak["start"]["runs"] + peak["end"]["runs"]
    assert peak["gflops_per_s"] == max(peak["start"]["gflops_per_s"], peak["end"]["gflops_per_s"])
    assert peak["end_over_start"] == pytest.approx(peak["end"]["gflops_per_s"] / peak["start"]["gflops_per_s"])
    assert isinstance(peak["drift_warning"], bool)
    s = doc["streaming"]
    for key in ("slice_idle", "slice_busy", "sequential", "image_lane_alone", "busy_over_idle_p95", "real_time_factor_idle",
                "real_time_factor_busy", "pre_post_share_idle", "keeps_up_busy", "slice_budget_ms"):
        assert key in s
    assert s["num_slices"] == 8 and s["slice_budget_ms"] == pytest.approx(12.5)
    assert (s["precision"], s["image_precision"]) == ("fp32", "int8") and meta["stream_image_precision"] == "int8"
    assert "int8 image lane + fp32 slices" in result.output
    assert s["slice_idle"]["latency"]["count"] == 2 * 8
    if s["all_cores"] > 1:
        assert s["slice_idle_all_cores"]["latency"]["count"] == 2 * 8
    assert {"pre", "slice_head", "post", "slice_total"} <= set(s["slice_idle"]["stages"])
    assert s["sequential"]["slice_latency"]["count"] == 8
    # --quick: 2 sweeps, taken in turns (idle, all cores, busy) in 2 rounds; the schedules in 2 rounds too
    assert s["phase_rounds"] == 2 and s["phase_sweeps_per_round"] == [1, 1]
    assert [r["rounds"] for r in s["image_lane_schedules"].values()] == [2, 2]
    assert all(t["met"] in (True, False, None) for t in doc["targets"])
    assert (d / "b.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list((d / "prof").glob("*.fp32.json"))) == NUM_ROWS
    assert {"idle/slice_head", "busy/slice_head", "busy/image_encoder.int8"} <= set(s["profiles"])  # named by graph file
    assert (d / "prof" / "streaming_busy.slice_head.json").is_file()


def test_quick_tiny_run_prints_the_table(quick_run):
    result, _ = quick_run
    out = result.output
    for text in ("ms fp32 (p95)", "torch/ort", "% peak", "peak probe", "slice lane, image lane busy", "one sequential queue",
                 "real-time", "targets:", "machine:", "at the start best", "at the end best", "taken in turns: 2 rounds",
                 "in turns with the other schedule: 2 rounds"):
        assert text in out
    # --repeat 2 and the image lane alone timed once: too few runs for a p95
    assert "p95 n/a" in out and "(n/a)" in out
    assert f"[row 1/{NUM_ROWS}]" in out  # progress lines (stderr, mixed into the runner's output)


def test_image_resolutions():
    assert image_resolutions((800, 450)) == [(800, 450), (1600, 900), (1200, 675)]
    assert image_resolutions((640, 360)) == [(640, 360), (1600, 900), (1200, 675), (800, 450)]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--slices", "3"], "multiple of 4"),
        (["--resolution", "800by450"], "expected WIDTHxHEIGHT"),
        (["--repeat", "0"], "0 is not in the range"),
        (["--json", "/nonexistent-dir/x.json"], "does not exist"),
        (["--plot", "/nonexistent-dir/x.png"], "does not exist"),
        (["--export-dir", "/nonexistent-dir"], "does not exist"),
        (["--preset", "huge"], "'huge' is not one of"),
        (["--resolution", "801x450"], "needs even sizes"),
    ],
)
def test_bad_input_is_one_line_error(args, message):
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0
    assert message in result.output
    assert "Traceback" not in result.output


def test_export_dir_without_manifest(tmp_path):
    result = CliRunner().invoke(main, ["--preset", "tiny", "--export-dir", str(tmp_path)])
    assert result.exit_code != 0 and "is not a usable export" in result.output and "Traceback" not in result.output
