"""Hostile numeric options of the click CLIs (fuzz report 2, finding 10): every number has an upper bound that ends
in one click error line (exit 2, no traceback) before any work, and the defaults and documented values still parse.

Each refused command is built so that, were its bound missing, it would stop on a cheap later check (a missing
manifest, a missing --json folder, --calibration-data without --int8, an existing dataset) rather than allocate.
"""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from streamdet.benchmarks.cli import main as bench_main
from streamdet.cli_utils import (
    MAX_RESOLUTION_PX, MIN_RESOLUTION_PX, RESOLUTION_RANGE_HELP, parse_resolution, resolution_callback, run_edge,
    write_json_output,
)
from streamdet.data.synth_cli import generate as synth_generate
from streamdet.data.synth_cli import main as synth_main
from streamdet.export.cli import main as export_main
from streamdet.replay.cli import main as replay_main

HUGE_INT = "1000000000000"  # 10**12
HUGE_FLOAT = "1e300"


def _assert_range_error(result, option: str, *needles: str) -> None:
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    assert option in errors[0], errors[0]
    for needle in needles:
        assert needle in errors[0], errors[0]


# ---- the shared WxH parser -----------------------------------------------------------------------------------


def test_resolution_bounds_are_the_documented_ones():
    assert (MIN_RESOLUTION_PX, MAX_RESOLUTION_PX) == (16, 4096)
    assert RESOLUTION_RANGE_HELP == "each side 16..4096 px"
    for text in ("16x16", "4096x4096", "800x450", "1600x900", "480x270", "160x90", "130x74", " 800x450", "８００x４５０"):
        w, h = parse_resolution(text)
        assert MIN_RESOLUTION_PX <= min(w, h) and max(w, h) <= MAX_RESOLUTION_PX
    assert parse_resolution("0000000800x0450") == (800, 450)  # leading zeros are no digits of the size


@pytest.mark.parametrize(
    "text, message",
    [
        ("30000x30000", "16..4096"),
        ("4097x450", "16..4096"),
        ("800x4098", "16..4096"),
        ("15x450", "16..4096"),
        ("99999999999999999999999x2", "16..4096"),
        ("9" * 5000 + "x2", "16..4096"),  # past int()'s digit limit: still the range error, not a ValueError
        ("²x450", "expected WIDTHxHEIGHT"),  # isdigit() but not a number int() reads
        ("0x450", "must be positive"),
    ],
)
def test_resolution_refuses_out_of_range_sizes(text, message):
    with pytest.raises(click.BadParameter, match=message) as info:
        parse_resolution(text)
    assert len(str(info.value)) < 200  # the bad value is quoted, shortened


def test_resolution_unbounded_on_request():
    assert parse_resolution("30000x30000", max_px=None) == (30000, 30000)
    with pytest.raises(click.BadParameter, match="at least 16"):
        parse_resolution("8x8", max_px=None)
    assert resolution_callback()(None, None, ("800x450", "4096x2304")) == ((800, 450), (4096, 2304))


# ---- streamdet-replay ------------------------------------------------------------------------------------------


def _replay_args(tmp_path) -> list[str]:
    # no manifest.json in --export-dir: a value past parsing ends in that one-line error, never in a replay
    return ["--data", str(tmp_path), "--export-dir", str(tmp_path)]


@pytest.mark.parametrize(
    "option, value, bound",
    [
        ("--camera-hz", "1e9", "0.1<=x<=1000"),
        ("--lidar-hz", "1e9", "0.1<=x<=1000"),
        ("--lidar-hz", "1e-300", "0.1<=x<=1000"),  # asked numpy for 1e300 trigger times
        ("--time-scale", HUGE_FLOAT, "0.01<=x<=1000"),
        ("--time-scale", "1e6", "0.01<=x<=1000"),
        ("--time-scale", "1e-300", "0.01<=x<=1000"),  # reported latencies of 1e296 ms
        ("--camera-delivery-ms", HUGE_FLOAT, "0<=x<=10000"),
        ("--max-seconds", HUGE_FLOAT, "0<x<=86400"),
        ("--scenes", HUGE_INT, "1<=x<=10000"),
        ("--slices", "8192", "1<=x<=4096"),
        ("--threads", HUGE_INT, "1<=x<=64"),
        ("--image-lane-threads", HUGE_INT, "1<=x<=64"),
        ("--slice-workers", HUGE_INT, "1<=x<=1024"),
        ("--queue-size", HUGE_INT, "1<=x<=1024"),
        ("--image-lane-yield", "1025", "0<=x<=1024"),
        ("--coalesce-slices", "65", "1<=x<=64"),
        ("--pair-hold-load", "17", "0<=x<=16"),
        ("--fallback-after-ms", HUGE_FLOAT, "0<=x<=60000"),
    ],
)
def test_replay_refuses_huge_numbers(tmp_path, option, value, bound):
    result = CliRunner().invoke(replay_main, [*_replay_args(tmp_path), option, value])
    _assert_range_error(result, option, bound)


def test_replay_defaults_and_documented_values_parse(tmp_path):
    ctx = replay_main.make_context("streamdet-replay", _replay_args(tmp_path))
    p = ctx.params
    assert (p["lidar_hz"], p["camera_hz"], p["time_scale"], p["camera_delivery_ms"], p["threads"]) == (20.0, 12.0, 1.0, 0.0, 1)
    documented = [
        "--scenes", "60", "--lidar-hz", "20", "--camera-hz", "12", "--slices", "32", "--time-scale", "0.02",
        "--camera-delivery-ms", "20", "--max-seconds", "0.3", "--threads", "2", "--image-lane-threads", "2",
        "--slice-workers", "1", "--queue-size", "64", "--fallback-after-ms", "500",
    ]  # fmt: skip
    p = replay_main.make_context("streamdet-replay", [*_replay_args(tmp_path), *documented]).params
    assert (p["scenes"], p["num_slices"], p["time_scale"], p["queue_size"], p["fallback_after_ms"]) == (60, 32, 0.02, 64, 500.0)
    edges = ["--camera-hz", "1000", "--time-scale", "1000", "--camera-delivery-ms", "10000", "--slices", "4096"]
    p = replay_main.make_context("streamdet-replay", [*_replay_args(tmp_path), *edges]).params
    assert (p["camera_hz"], p["time_scale"], p["camera_delivery_ms"], p["num_slices"]) == (1000.0, 1000.0, 10000.0, 4096)


# ---- streamdet-bench -------------------------------------------------------------------------------------------


def _bench_args(tmp_path) -> list[str]:
    # a --json folder that does not exist: a value past parsing ends in that error before any export or timing
    return ["--json", str(tmp_path / "missing" / "b.json")]


@pytest.mark.parametrize(
    "args, option, bound",
    [
        (["--resolution", "30000x30000"], "--resolution", "16..4096"),
        (["--resolution", "99999999999999999999999x2"], "--resolution", "16..4096"),
        (["--slices", HUGE_INT], "--slices", "1<=x<=4096"),
        (["--repeat", HUGE_INT], "--repeat", "1<=x<=10000"),
        (["--threads", HUGE_INT], "--threads", "1<=x<=64"),
        (["--stream-slice-workers", "1025"], "--stream-slice-workers", "1<=x<=1024"),
    ],
)
def test_bench_refuses_huge_numbers(tmp_path, args, option, bound):
    result = CliRunner().invoke(bench_main, [*_bench_args(tmp_path), *args])
    _assert_range_error(result, option, bound)


def test_bench_flops_only_refuses_a_huge_resolution():
    # the report's TypeError: refused while parsing, before torch is imported or a tensor is made
    result = CliRunner().invoke(bench_main, ["--flops-only", "--resolution", "99999999999999999999999x2"])
    _assert_range_error(result, "--resolution", "16..4096")


def test_bench_defaults_and_documented_values_parse(tmp_path):
    p = bench_main.make_context("streamdet-bench", []).params
    # --slices None: the --export-dir export's count, 8 for the export the bench makes (benchmarks/cli.py)
    assert (p["resolution"], p["slices"], p["repeat"], p["threads"]) == (None, None, None, None)
    args = ["--resolution", "1600x900", "--slices", "32", "--repeat", "2", "--threads", "2", "--stream-slice-workers", "1"]
    p = bench_main.make_context("streamdet-bench", args).params
    assert (p["resolution"], p["slices"], p["repeat"]) == ((1600, 900), 32, 2)
    for text, size in (("1200x675", (1200, 675)), ("4096x2304", (4096, 2304))):
        assert bench_main.make_context("streamdet-bench", ["--resolution", text]).params["resolution"] == size


# ---- streamdet-export ------------------------------------------------------------------------------------------


def _export_args(tmp_path) -> list[str]:
    # --calibration-data without --int8: a value past parsing ends in that ExportError before any graph is built
    return ["--preset", "tiny", "--out", str(tmp_path / "exp"), "--calibration-data", str(tmp_path)]


@pytest.mark.parametrize(
    "args, option, bound",
    [
        (["--resolution", "30000x30000"], "--resolution", "16..4096"),
        (["--resolution", "4098x450"], "--resolution", "16..4096"),
        (["--slices", HUGE_INT], "--slices", "1<=x<=4096"),
        (["--calibration-samples", HUGE_INT], "--calibration-samples", "1<=x<=10000"),
        (["--top-k", HUGE_INT], "--top-k", "1<=x<=100000"),
        (["--seed", str(10**23)], "--seed", "0<=x<=9223372036854775807"),
        (["--seed", "-1"], "--seed", "0<=x<=9223372036854775807"),
    ],
)
def test_export_refuses_huge_numbers(tmp_path, args, option, bound):
    result = CliRunner().invoke(export_main, [*_export_args(tmp_path), *args])
    _assert_range_error(result, option, bound)
    assert not (tmp_path / "exp").exists()


def test_export_defaults_and_documented_values_parse(tmp_path):
    p = export_main.make_context("streamdet-export", []).params
    assert (p["resolution"], p["num_slices"], p["calibration_samples"], p["seed"], p["top_k"]) == (None, 8, 8, 0, None)
    args = ["--resolution", "130x74", "--slices", "4", "--top-k", "100", "--seed", "3", "--calibration-samples", "2"]
    p = export_main.make_context("streamdet-export", args).params
    assert (p["resolution"], p["num_slices"], p["top_k"], p["seed"], p["calibration_samples"]) == ((130, 74), 4, 100, 3, 2)
    assert export_main.make_context("streamdet-export", ["--resolution", "4096x2304"]).params["resolution"] == (4096, 2304)


# ---- streamdet-synth -------------------------------------------------------------------------------------------


def _synth_args(tmp_path) -> list[str]:
    (tmp_path / "v1.0-synth").mkdir(exist_ok=True)  # an existing dataset: past parsing, refused without --overwrite
    return ["--out", str(tmp_path)]


@pytest.mark.parametrize(
    "option, value, bound",
    [
        ("--samples-per-scene", HUGE_INT, "1<=x<=1000"),
        ("--samples-per-scene", str(3 * 10**7), "1<=x<=1000"),
        ("--scenes", HUGE_INT, "1<=x<=10000"),
        ("--workers", HUGE_INT, "1<=x<=1024"),
        ("--sweeps-per-sample", "11", "1<=x<=10"),
        ("--resolution", "30000x30000", "16..4096"),
    ],
)
def test_synth_refuses_huge_numbers(tmp_path, option, value, bound):
    # through the group, as `streamdet-synth --out DIR ...` is typed (the default generate command)
    result = CliRunner().invoke(synth_main, [*_synth_args(tmp_path), option, value])
    _assert_range_error(result, option, bound)


def test_synth_stats_refuses_a_huge_max_samples(tmp_path):
    result = CliRunner().invoke(synth_main, ["stats", str(tmp_path), "--max-samples", HUGE_INT])
    _assert_range_error(result, "--max-samples", "1<=x<=1000000")


def test_synth_defaults_and_documented_values_parse(tmp_path):
    p = synth_generate.make_context("generate", ["--out", str(tmp_path)]).params
    assert (p["scenes"], p["resolution"], p["samples_per_scene"], p["sweeps_per_sample"], p["workers"]) == (2, (800, 450), 10, 1, 1)
    args = ["--out", str(tmp_path), "--scenes", "60", "--resolution", "32x18", "--samples-per-scene", "1",
            "--sweeps-per-sample", "10", "--workers", "2", "--seed", str(10**23)]  # fmt: skip
    p = synth_generate.make_context("generate", args).params
    assert (p["scenes"], p["resolution"], p["sweeps_per_sample"], p["seed"]) == (60, (32, 18), 10, 10**23)


# ---- the console-script edge: the report's repros end in one line and exit 2 ------------------------------------


@pytest.mark.parametrize(
    "module, prog, args, option",
    [
        ("streamdet.replay.cli", "streamdet-replay", ["--camera-hz", "1e9"], "--camera-hz"),
        ("streamdet.replay.cli", "streamdet-replay", ["--time-scale", HUGE_FLOAT], "--time-scale"),
        ("streamdet.replay.cli", "streamdet-replay", ["--camera-delivery-ms", HUGE_FLOAT], "--camera-delivery-ms"),
        ("streamdet.benchmarks.cli", "streamdet-bench", ["--resolution", "30000x30000"], "--resolution"),
        ("streamdet.benchmarks.cli", "streamdet-bench", ["--flops-only", "--resolution", "9" * 23 + "x2"], "--resolution"),
        ("streamdet.export.cli", "streamdet-export", ["--resolution", "30000x30000"], "--resolution"),
        ("streamdet.data.synth_cli", "streamdet-synth", ["--samples-per-scene", HUGE_INT], "--samples-per-scene"),
    ],
)
def test_report_repros_end_in_one_line(tmp_path, capsys, module, prog, args, option):
    base = {
        "streamdet-replay": _replay_args(tmp_path),
        "streamdet-bench": _bench_args(tmp_path),
        "streamdet-export": _export_args(tmp_path),
        "streamdet-synth": _synth_args(tmp_path),
    }[prog]
    assert run_edge(module, prog, args=[*base, *args]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("Error")]
    assert len(errors) == 1 and option in errors[0], err


@pytest.mark.parametrize("width, height", [(30000, 30000), (4098, 450), (14, 450), (801, 450), (0, 450), (True, 450)])
def test_the_exporters_own_resolution_check_has_the_tools_bounds(width, height):
    """An API caller of the exporter gets the CLI's bounds (core/constants.py), not a 2.7 GB image tensor."""
    from streamdet.export.options import ExportError, check_resolution

    with pytest.raises(ExportError, match=r"must be an even number of pixels in 16..4096"):
        check_resolution(width, height)
    check_resolution(4096, 16)


def test_json_outputs_are_written_atomically(tmp_path):
    """Every tool's --json goes through write_json_output: a symlink at the path is replaced rather than written
    through, a non-finite figure is a one-line error that leaves no file, and the document ends in a newline."""
    victim = tmp_path / "victim.json"
    victim.write_text("keep")
    link = tmp_path / "out.json"
    link.symlink_to(victim)
    write_json_output(link, {"mAP": 0.5})
    assert victim.read_text() == "keep" and not link.is_symlink()
    assert link.read_text() == '{\n "mAP": 0.5\n}\n'
    with pytest.raises(click.ClickException, match=r"cannot write --json .*nan.json: Out of range float"):
        write_json_output(tmp_path / "nan.json", {"mAP": float("nan")})
    with pytest.raises(click.ClickException, match="cannot write --out .*: No such file or directory"):
        write_json_output(tmp_path / "missing" / "x.json", {}, "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json", "victim.json"]
