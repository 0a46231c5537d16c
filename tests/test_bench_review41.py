"""Review 41, area bench: the rows follow the --export-dir export's preset (B1), a p95 of too few samples is neither
judged nor printed (B2), the --resolution help says which sizes each mode takes (B3)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from streamdet.benchmarks import cli as bench_cli
from streamdet.benchmarks import report, run
from streamdet.benchmarks.prepost import PrePostCase, format_prepost
from streamdet.benchmarks.run import BenchConfig, BenchmarkError, resolve_stream_export, rows_preset
from streamdet.benchmarks.streaming import LaneStats, StreamingConfig, StreamingResult
from streamdet.benchmarks.timing import MIN_P95_SAMPLES, summarize
from streamdet.core.constants import DEFAULT_PRESET

# ---- B1: the rows' preset with --export-dir -----------------------------------------------------------------


@pytest.mark.parametrize(
    "given, export_preset, expected",
    [
        (None, None, DEFAULT_PRESET),  # no export: the benchmark makes one of the rows' preset
        ("tiny", None, "tiny"),
        (None, "tiny", "tiny"),  # the rows follow the export, as the slices do
        ("tiny", "tiny", "tiny"),
        ("paper", "paper", "paper"),
        ("tiny", "renamed_preset", "tiny"),  # an export of a preset this version does not know: the given one
    ],
)
def test_rows_preset(given, export_preset, expected):
    assert rows_preset(given, export_preset) == expected


@pytest.mark.parametrize("given, export_preset", [("small_v3", "tiny"), ("tiny", "small_v3"), ("paper", "tiny")])
def test_a_preset_other_than_the_exports_is_refused_naming_both(given, export_preset):
    with pytest.raises(ValueError, match="is not the export's preset") as e:
        rows_preset(given, export_preset)
    assert repr(given) in str(e.value) and repr(export_preset) in str(e.value)


@pytest.mark.parametrize("export_preset", ["renamed_preset", "", "TINY"])
def test_an_unknown_export_preset_needs_one_given(export_preset):
    with pytest.raises(ValueError, match="is not one this version knows") as e:
        rows_preset(None, export_preset)
    assert repr(export_preset) in str(e.value)


def test_library_rows_follow_the_export(tiny_export):
    assert BenchConfig().preset is None  # the library default follows the CLI's
    cfg = resolve_stream_export(BenchConfig(export_dir=tiny_export))
    assert cfg.preset == "tiny" and cfg.given_resolution == (128, 72)
    assert resolve_stream_export(BenchConfig(preset="tiny", export_dir=tiny_export)).preset == "tiny"
    assert resolve_stream_export(BenchConfig(slices=8)).preset == DEFAULT_PRESET  # no export: the default's


def test_library_refuses_a_preset_other_than_the_exports(tiny_export):
    with pytest.raises(BenchmarkError, match="BenchConfig.preset: 'small_v3' is not the export's preset 'tiny'") as e:
        resolve_stream_export(BenchConfig(preset="small_v3", export_dir=tiny_export))
    assert str(tiny_export) in str(e.value)


@pytest.fixture
def reached(monkeypatch):
    """The BenchConfig streamdet-bench hands run_benchmark (which is stubbed: nothing is timed)."""
    seen: list[BenchConfig] = []

    def stub(cfg, progress=lambda msg: None):
        seen.append(cfg)
        raise BenchmarkError("stub: nothing timed")

    monkeypatch.setattr(run, "run_benchmark", stub)
    return seen


def test_cli_rows_follow_the_export(tiny_export, reached):
    result = CliRunner().invoke(bench_cli.main, ["--export-dir", str(tiny_export)])
    assert "stub: nothing timed" in result.output, result.output
    assert [(c.preset, c.slices) for c in reached] == [("tiny", 8)]


def test_cli_refuses_a_preset_other_than_the_exports(tiny_export, reached):
    result = CliRunner().invoke(bench_cli.main, ["--export-dir", str(tiny_export), "--preset", "small_v3"])
    assert result.exit_code == 2, result.output
    assert "--preset" in result.output and "'small_v3' is not the export's preset 'tiny'" in result.output
    assert str(tiny_export) in result.output.replace("\n", "") and "Traceback" not in result.output
    assert reached == []  # refused before any timing


@pytest.fixture
def renamed_export(tiny_export, tmp_path) -> Path:
    """The tiny export with its manifest naming a preset this version does not know."""
    out = tmp_path / "renamed"
    shutil.copytree(tiny_export, out)
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["preset_name"] = "renamed_preset"
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return out


def test_cli_export_of_an_unknown_preset_needs_preset(renamed_export, reached):
    result = CliRunner().invoke(bench_cli.main, ["--export-dir", str(renamed_export)])
    assert result.exit_code == 2 and "'renamed_preset' is not one this version knows" in result.output
    assert "--preset" in result.output and reached == []
    result = CliRunner().invoke(bench_cli.main, ["--export-dir", str(renamed_export), "--preset", "tiny"])
    assert "stub: nothing timed" in result.output, result.output
    assert [c.preset for c in reached] == ["tiny"]


# ---- B2: a p95 of fewer than MIN_P95_SAMPLES samples ---------------------------------------------------------


def _stats(n: int, slow_last: float = 1.0) -> object:
    return summarize([1.0] * (n - 1) + [slow_last])


def _lane(n: int, slow_last: float = 1.0) -> LaneStats:
    return LaneStats(_stats(n, slow_last), {})


def _streaming(busy_n: int, idle_n: int) -> StreamingResult:
    return StreamingResult(
        export_dir="x", preset="tiny", precision="fp32", num_slices=8, num_points=(100,) * 8, image_size=(128, 72),
        num_cameras=6, slice_budget_ms=12.5, idle=_lane(idle_n), idle_all_cores=None, all_cores=1,
        busy=_lane(busy_n, slow_last=20.0), image_alone=_lane(1), image_busy_updates=1, sequential_slice=_stats(8),
        sequential_wait=_stats(8, slow_last=9.0), sequential_images_served=1, sequential_images_superseded=0,
        sequential_horizon_ms=100.0, config=StreamingConfig(),
    )  # fmt: skip


def _busy_target(streaming: StreamingResult) -> report.Target:
    row = SimpleNamespace(torch_over_ort=None, key="image_128x72", module="m", kind="image", gflops_per_s=1.0, int8=None)
    targets = report.evaluate_targets([row], SimpleNamespace(gflops_per_s=10.0), streaming)
    (target,) = [t for t in targets if t.name.startswith("slice p95 with a busy image lane")]
    return target


def test_min_p95_samples_is_one_constant():
    assert report.MIN_P95_SAMPLES is MIN_P95_SAMPLES == 20


@pytest.mark.parametrize("busy_n, idle_n", [(16, 16), (19, 40), (40, 19), (1, 1), (2, 100)])
def test_busy_over_idle_target_not_judged_on_few_samples(busy_n, idle_n):
    target = _busy_target(_streaming(busy_n, idle_n))
    assert target.met is None and target.line().startswith("  [n/a   ]")
    assert f"p95 of {busy_n} busy / {idle_n} idle samples: fewer than {MIN_P95_SAMPLES}" in target.detail
    text = report.format_streaming(_streaming(busy_n, idle_n))
    assert "busy / idle slice p95: n/a (" in text


@pytest.mark.parametrize("n", [MIN_P95_SAMPLES, 40])
def test_busy_over_idle_target_judged_on_enough_samples(n):
    s = _streaming(n, n)
    target = _busy_target(s)
    assert target.met is (s.busy_over_idle_p95 <= report.BUSY_OVER_IDLE_P95_MAX)
    assert f"= {s.busy_over_idle_p95:.2f}x" in target.detail
    assert f"busy / idle slice p95: {s.busy_over_idle_p95:.2f}x" in report.format_streaming(s)


def test_queue_wait_p95_prints_n_a_on_few_samples():
    text = report.format_streaming(_streaming(16, 16))
    assert "slice wait p50 1.0 ms, p95 n/a, n=8)" in text


@pytest.mark.parametrize("n, shown", [(1, False), (10, False), (MIN_P95_SAMPLES - 1, False), (MIN_P95_SAMPLES, True), (50, True)])
def test_prepost_p95_prints_n_a_under_the_minimum(n, shown):
    stats = summarize([1.0] * (n - 1) + [7.25])
    text = format_prepost((PrePostCase("pillarize 30,000 points, real sweep", "pre", stats, 5.0, "1 pillar"),))
    line = text.splitlines()[1]
    assert (f"p95 {stats.p95_ms:6.2f} ms" in line) is shown
    assert ("p95       n/a" in line) is not shown and f"n={n}" in line


# ---- B3: which sizes each mode takes (documented; the paper's 1200x675 row is odd) -----------------------------


@pytest.fixture
def flops(monkeypatch):
    calls: list = []
    monkeypatch.setattr(bench_cli, "_flops_only", lambda *a: calls.append(a))
    return calls


@pytest.mark.parametrize("size", ["801x451", "801x450", "800x451", "17x16", "4095x4096"])
def test_odd_sides_are_refused_where_the_export_is_made_here(size, reached):
    result = CliRunner().invoke(bench_cli.main, ["--preset", "tiny", "--resolution", size])
    assert result.exit_code == 2, result.output
    assert f"{size}: the export needs even sizes" in result.output and "--resolution" in result.output
    assert reached == []


@pytest.mark.parametrize("size, expected", [("800x450", (800, 450)), ("1200x675", (1200, 675)), ("801x451", (801, 451)),
                                            ("16x16", (16, 16)), ("4095x4096", (4095, 4096))])  # fmt: skip
def test_flops_only_counts_any_size(size, expected, flops):
    result = CliRunner().invoke(bench_cli.main, ["--flops-only", "--preset", "tiny", "--resolution", size])
    assert result.exit_code == 0, result.output
    assert flops == [("tiny", expected, None)]


@pytest.mark.parametrize("size", ["4097x450", "15x16", "0x450", "801", "801x451x3"])
def test_flops_only_still_refuses_sizes_out_of_range(size, flops):
    result = CliRunner().invoke(bench_cli.main, ["--flops-only", "--resolution", size])
    assert result.exit_code == 2 and "--resolution" in result.output and flops == []


def test_rows_with_an_export_dir_take_an_odd_size(tiny_export, reached):
    result = CliRunner().invoke(bench_cli.main, ["--export-dir", str(tiny_export), "--resolution", "1200x675"])
    assert "stub: nothing timed" in result.output, result.output
    assert [c.resolution for c in reached] == [(1200, 675)]


def test_help_says_which_sizes_each_mode_takes():
    out = " ".join(CliRunner().invoke(bench_cli.main, ["--help"], terminal_width=400).output.split())
    assert "Even sides of the bundled cameras' aspect only where the export is made here" in out
    assert "--flops-only and the rows with --export-dir count any size, odd ones included" in out
    assert "the --export-dir export's preset" in out
