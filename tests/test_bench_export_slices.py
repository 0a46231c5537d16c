"""streamdet-bench --export-dir (audit F6): the streaming section's slice count defaults to the export's, as in the
other tools, and an export the section cannot time (LiDAR-only, other cameras) is refused before any timing."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from streamdet.benchmarks.cli import main
from streamdet.benchmarks.streaming import check_streaming_export, export_unfit
from streamdet.runtime_ort.manifest import read_manifest

EXPORT_SLICES = 4  # not the temporary export's 8: a default that ignored the export would show


@pytest.fixture(scope="module")
def export4(tmp_path_factory):
    """A tiny camera + LiDAR export (fp32) made for 4 slices."""
    from streamdet.export.cli import main as export_main

    out = tmp_path_factory.mktemp("bench_export4") / "tiny4"
    result = CliRunner().invoke(export_main, ["--preset", "tiny", "--slices", str(EXPORT_SLICES), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture
def reached(monkeypatch):
    """The BenchConfig of every benchmark the CLI started; the stub stops it there (exit 1, one line)."""
    from streamdet.benchmarks.run import BenchmarkError

    configs = []

    def stub(cfg, progress=None):
        configs.append(cfg)
        raise BenchmarkError("stub: the benchmark was reached")

    monkeypatch.setattr("streamdet.benchmarks.run.run_benchmark", stub)
    return configs


def _bench(*args: str):
    return CliRunner().invoke(main, ["--preset", "tiny", *args])


def _reached_with(result, configs):
    assert result.exit_code == 1 and "stub: the benchmark was reached" in result.output, result.output
    assert len(configs) == 1
    return configs[0]


# ---- the slice count ---------------------------------------------------------------------------------------------


def test_slices_default_to_the_exports(export4, reached):
    cfg = _reached_with(_bench("--export-dir", str(export4)), reached)
    assert cfg.slices == EXPORT_SLICES


@pytest.mark.parametrize("slices", ["8", "16"])
def test_explicit_slices_still_win(export4, reached, slices):
    cfg = _reached_with(_bench("--export-dir", str(export4), "--slices", slices), reached)
    assert cfg.slices == int(slices)


def test_without_export_dir_the_library_picks_its_own_export_count(reached):
    from streamdet.benchmarks.run import DEFAULT_SLICES, BenchConfig, resolve_stream_export

    cfg = _reached_with(_bench(), reached)
    assert cfg.slices is None and cfg.export_dir is None
    assert resolve_stream_export(cfg).slices == DEFAULT_SLICES == 8
    assert resolve_stream_export(BenchConfig(slices=16)).slices == 16


def test_resolve_reads_the_exports_count_and_keeps_a_given_one(export4):
    from streamdet.benchmarks.run import BenchConfig, resolve_stream_export

    assert resolve_stream_export(BenchConfig(preset="tiny", export_dir=export4)).slices == EXPORT_SLICES
    assert resolve_stream_export(BenchConfig(preset="tiny", export_dir=export4, slices=12)).slices == 12
    assert BenchConfig().slices is None  # the library default follows the CLI's


def test_a_bad_slice_count_is_still_refused_with_an_export(export4, reached):
    result = _bench("--export-dir", str(export4), "--slices", "6")
    assert result.exit_code == 2 and "multiple of 4" in result.output and "Traceback" not in result.output
    assert reached == []


def test_help_documents_the_default():
    from streamdet.benchmarks.run import DEFAULT_SLICES

    text = " ".join(CliRunner().invoke(main, ["--help"]).output.split())
    assert "the --export-dir export's slice count" in text and f"{DEFAULT_SLICES} for the export made here" in text


# ---- exports the section cannot time: refused before any timing ------------------------------------------------


def test_lidar_only_export_is_refused_before_the_benchmark(tiny_lidar_export, reached):
    result = _bench("--export-dir", str(tiny_lidar_export), "--quick", "--no-int8", "--no-fp16")
    assert result.exit_code == 2 and "Traceback" not in result.output and reached == []
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1 and "--export-dir" in errors[0] and f"{tiny_lidar_export} is a LiDAR-only export" in errors[0]


def test_run_benchmark_refuses_a_lidar_only_export_before_the_probe(tiny_lidar_export, monkeypatch):
    """The library too: a caller of run_benchmark gets the error before the peak probe and the row timings."""
    from streamdet.benchmarks import run

    def no_timing(*args, **kwargs):
        raise AssertionError("timing started")

    monkeypatch.setattr(run, "measure_peak", no_timing)
    monkeypatch.setattr(run, "measure_rows", no_timing)
    with pytest.raises(run.BenchmarkError, match="LiDAR-only export"):
        run.run_benchmark(run.BenchConfig(preset="tiny", export_dir=tiny_lidar_export, quick=True))


def test_run_benchmark_refuses_missing_stream_graphs_before_the_probe(export4, monkeypatch):
    from streamdet.benchmarks import run

    monkeypatch.setattr(run, "measure_peak", lambda *a, **k: pytest.fail("timing started"))
    with pytest.raises(run.BenchmarkError, match="has no int8 graphs .* re-export with --int8"):
        run.run_benchmark(run.BenchConfig(preset="tiny", export_dir=export4, stream_image_precision="int8"))


def test_export_unfit_names_what_the_section_cannot_time(export4, tiny_lidar_export, monkeypatch):
    from streamdet.benchmarks.streaming import StreamingConfig

    fused, lidar = read_manifest(export4), read_manifest(tiny_lidar_export)
    assert export_unfit(fused) is None and export_unfit(fused, StreamingConfig()) is None
    assert export_unfit(lidar).startswith("is a LiDAR-only export")
    assert "has no fp16 graphs" in export_unfit(fused, StreamingConfig(precision="fp16"))
    assert "has no int8 graphs" in export_unfit(fused, StreamingConfig(image_precision="int8"))
    other = SimpleNamespace(rig=SimpleNamespace(names=("CAM_A", "CAM_B")))
    monkeypatch.setattr("streamdet.benchmarks.streaming.load_bundled_sample", lambda: other)
    assert "but the streaming section feeds the bundled sample's ['CAM_A', 'CAM_B']" in export_unfit(fused)


def test_other_cameras_are_refused_by_the_cli_before_the_benchmark(export4, reached, monkeypatch):
    other = SimpleNamespace(rig=SimpleNamespace(names=("CAM_A",)))
    monkeypatch.setattr("streamdet.benchmarks.streaming.load_bundled_sample", lambda: other)
    result = _bench("--export-dir", str(export4))
    assert result.exit_code == 2 and "bundled sample's ['CAM_A']" in result.output and reached == []


def test_check_streaming_export_is_one_line_for_a_broken_export(tmp_path, export4):
    with pytest.raises(ValueError, match="is not a usable export"):
        check_streaming_export(tmp_path)  # no manifest.json
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match="is not a usable export") as e:
        check_streaming_export(tmp_path)
    assert "\n" not in str(e.value)
    assert check_streaming_export(export4).num_slices == EXPORT_SLICES


def test_measure_streaming_uses_the_exports_count(export4):
    """The section itself, timed briefly on the 4-slice export with no --slices: 4 slices, a 25 ms budget."""
    from streamdet.benchmarks.run import BenchConfig, resolve_stream_export
    from streamdet.benchmarks.streaming import measure_streaming

    cfg = resolve_stream_export(BenchConfig(preset="tiny", export_dir=export4, quick=True, repeat=2))
    stream = dataclasses.replace(cfg.streaming(), schedule_seconds=0.0)
    result = measure_streaming(export4, stream)
    assert result.num_slices == EXPORT_SLICES and result.slice_budget_ms == pytest.approx(100.0 / EXPORT_SLICES)
