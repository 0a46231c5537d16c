"""streamdet-replay with a LiDAR-only export (audit F7): the options of the image lane and of the cameras are refused,
named, before any work, when given on the command line; their defaults, and the slice lane's options, still work."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from streamdet.replay import cli as replay_cli

# every image-lane option with a value it accepts (at its default where one exists: given is given)
IMAGE_LANE_ARGS = [
    (["--image-precision", "int8"], "--image-precision"),
    (["--image-precision", "fp32"], "--image-precision"),
    (["--camera-hz", "10"], "--camera-hz"),
    (["--camera-hz", "12"], "--camera-hz"),
    (["--camera-trigger", "simultaneous"], "--camera-trigger"),
    (["--camera-delivery-ms", "50"], "--camera-delivery-ms"),
    (["--camera-delivery-ms", "0"], "--camera-delivery-ms"),
    (["--image-lane-threads", "2"], "--image-lane-threads"),
    (["--schedule", "phase-locked"], "--schedule"),
    (["--schedule", "full"], "--schedule"),
    (["--image-lane-nice", "5"], "--image-lane-nice"),
    (["--image-lane-yield", "2"], "--image-lane-yield"),
    (["--camera-terms", "on"], "--camera-terms"),
    (["--camera-terms", "auto"], "--camera-terms"),
    (["--fallback-export", "{lidar}"], "--fallback-export"),
    (["--fallback-after-ms", "5"], "--fallback-after-ms"),
    (["--camera-outage", "CAM_FRONT@0-1"], "--camera-outage"),
    (["--camera-timeout-ms", "500"], "--camera-timeout-ms"),
]
# slice-lane and run options: they apply to a LiDAR-only export too
SLICE_LANE_ARGS = [["--slice-workers", "1"], ["--queue-size", "4"], ["--coalesce-slices", "2"], ["--threads", "1"],
                   ["--pair-hold-load", "1.5", "--coalesce-slices", "2"], ["--precision", "fp32"], ["--slices", "4"],
                   ["--lidar-hz", "10"], ["--time-scale", "2"], ["--mode", "sequential"], ["--no-freeze-heap"]]  # fmt: skip


@pytest.fixture
def replay(tiny_drive_data, monkeypatch):
    """``replay(export, *extra)`` runs the CLI with the real run_replay replaced by a stub that records the config
    and stops (exit 1): "refused before the work" is exit 2 and no call."""
    calls: list = []

    def stub(config, progress=None):
        calls.append(config)
        raise ValueError("stub: the replay was reached")

    monkeypatch.setattr("streamdet.replay.run.run_replay", stub)

    def run(export, *extra: str):
        args = ["--data", str(tiny_drive_data), "--split", "all", "--export-dir", str(export), "--max-seconds", "0.1", *extra]
        return CliRunner().invoke(replay_cli.main, args)

    run.calls = calls
    return run


def _error_line(result) -> str:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    return errors[0]


@pytest.mark.parametrize("args, option", IMAGE_LANE_ARGS)
def test_each_image_lane_option_is_refused_with_a_lidar_only_export(replay, tiny_lidar_export, args, option):
    args = [a.format(lidar=tiny_lidar_export) for a in args]
    error = _error_line(replay(tiny_lidar_export, *args))
    assert f"{tiny_lidar_export} is a LiDAR-only export" in error and f"{option} only applies" in error
    assert error.endswith("drop it") and replay.calls == []


def test_the_audits_command_names_every_option_at_once(replay, tiny_lidar_export):
    error = _error_line(replay(tiny_lidar_export, "--mode", "streaming", "--schedule", "phase-locked",
                               "--image-lane-yield", "2", "--camera-delivery-ms", "50", "--image-lane-nice", "3"))  # fmt: skip
    for option in ("--schedule", "--image-lane-yield", "--camera-delivery-ms", "--image-lane-nice"):
        assert option in error
    assert "--mode" not in error and "only apply" in error and error.endswith("drop them") and replay.calls == []


def test_defaults_reach_the_replay_with_a_lidar_only_export(replay, tiny_lidar_export):
    result = replay(tiny_lidar_export)
    assert result.exit_code == 1 and "stub: the replay was reached" in result.output, result.output
    (config,) = replay.calls
    assert config.image_precision is None and config.lanes.schedule == "full" and config.camera_delivery_ms == 0.0


@pytest.mark.parametrize("args", SLICE_LANE_ARGS)
def test_slice_lane_options_reach_the_replay_with_a_lidar_only_export(replay, tiny_lidar_export, args):
    result = replay(tiny_lidar_export, *args)
    assert result.exit_code == 1 and "stub: the replay was reached" in result.output, result.output


@pytest.mark.parametrize("args, option", [a for a in IMAGE_LANE_ARGS if a[1] not in ("--fallback-export", "--fallback-after-ms")])
def test_image_lane_options_reach_the_replay_with_cameras(replay, tiny_export, args, option):
    if option == "--image-lane-yield":
        args = [*args, "--schedule", "phase-locked"]  # LaneConfig: the yield is the phase-locked schedule's
    result = replay(tiny_export, *args)
    assert result.exit_code == 1 and "stub: the replay was reached" in result.output, (option, result.output)


def test_every_listed_option_is_an_option_of_the_command():
    names = {p.name for p in replay_cli.main.params}
    assert set(replay_cli.IMAGE_LANE_OPTIONS) <= names  # a renamed option must not drop out of the refusal silently


def test_a_broken_manifest_is_left_to_the_replay_to_report(replay, tmp_path):
    """The option check reads only the modality; an export that is none fails as it did without the options."""
    (tmp_path / "manifest.json").write_text("{not json")
    result = replay(tmp_path, "--schedule", "phase-locked")
    assert result.exit_code == 1 and "stub: the replay was reached" in result.output, result.output


def test_help_says_the_image_lane_options_need_cameras():
    text = " ".join(CliRunner().invoke(replay_cli.main, ["--help"]).output.split())
    assert "A LiDAR-only export has no image lane and no cameras" in text


def test_a_real_replay_of_a_lidar_only_export_with_defaults(tiny_drive_data, tiny_lidar_export):
    args = ["--data", str(tiny_drive_data), "--split", "all", "--export-dir", str(tiny_lidar_export),
            "--max-seconds", "0.1", "--mode", "sequential", "--time-scale", "2"]  # fmt: skip
    result = CliRunner().invoke(replay_cli.main, args)
    assert result.exit_code == 0, result.output
    assert "| sequential |" in result.output
    # its report says there are no cameras and shows no image-lane table (they were defaults, not in effect)
    assert "no cameras (a LiDAR-only export)" in result.output and "cameras 12 Hz" not in result.output
    assert "image lane, schedule" not in result.output
