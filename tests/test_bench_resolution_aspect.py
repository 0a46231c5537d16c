"""streamdet-bench refuses a --resolution the streaming section's export would refuse (the cameras' aspect) before any
timing: the export runs after the rows, minutes later, and the whole run was lost (bench review M1)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from streamdet.benchmarks import run
from streamdet.benchmarks.cli import main
from streamdet.benchmarks.run import BenchConfig, BenchmarkError, export_resolution_problem, resolve_stream_export
from streamdet.calibration.camera import CalibrationError
from streamdet.calibration.lut import check_rig_fits
from streamdet.export.graph_steps import load_rig


@pytest.fixture
def no_timing(monkeypatch):
    """Every timing step of run_benchmark fails the test if it is reached."""
    calls = []

    def forbidden(name):
        def fail(*args, **kwargs):
            calls.append(name)
            raise AssertionError(f"{name} ran: the refusal came after timing started")

        return fail

    for name in ("measure_peak", "measure_rows", "measure_streaming", "build_rows"):
        monkeypatch.setattr(run, name, forbidden(name))
    return calls


@pytest.mark.parametrize("size, nearest", [("64x64", "64x36 or 114x64"), ("320x240", "320x180 or 426x240")])
def test_an_off_aspect_resolution_is_refused_before_any_timing(no_timing, size, nearest):
    result = CliRunner().invoke(main, ["--preset", "tiny", "--quick", "--no-fp16", "--no-int8", "--resolution", size])
    assert result.exit_code == 2, result.output
    assert no_timing == []
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    line = errors[0]
    assert "--resolution" in line and f"{size} does not fit the calibration" in line and "aspect" in line
    assert "bundled:nuscenes_sample/calibration.json" in line and nearest in line
    assert "peak probe" not in result.output  # no progress line: nothing started


def test_the_api_refuses_it_too_before_any_timing(no_timing):
    with pytest.raises(BenchmarkError, match=r"BenchConfig.resolution: 64x64 does not fit the calibration"):
        run.run_benchmark(BenchConfig(preset="tiny", resolution=(64, 64), quick=True))
    assert no_timing == []


@pytest.mark.parametrize("size", [(64, 36), (128, 72), (800, 450), (1600, 900), (64, 64), (320, 240), (800, 452), (16, 16)])
def test_the_verdict_is_the_exports_own_rule(size):
    """Not a second copy of the rule: the verdict is check_rig_fits's on the rig the export loads."""
    rig, _ = load_rig(None)
    try:
        check_rig_fits(rig, rig.names, *size)
        fits = True
    except CalibrationError:
        fits = False
    assert (export_resolution_problem(size) is None) == fits


def test_odd_sizes_get_the_exports_even_rule():
    assert "even number of pixels" in export_resolution_problem((801, 451))


def test_a_fitting_resolution_passes_and_an_export_dir_keeps_its_own_size(tiny_export):
    assert resolve_stream_export(BenchConfig(preset="tiny", resolution=(128, 72))).slices == run.DEFAULT_SLICES
    # with --export-dir the streaming section runs at the export's size: --resolution sets the rows only
    cfg = resolve_stream_export(BenchConfig(preset="tiny", resolution=(64, 64), export_dir=tiny_export))
    assert cfg.slices == 8
