"""The streaming section's image-lane schedules (benchmarks/streaming_schedules.py) on the tiny export."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.benchmarks.streaming_schedules import CAMERA_HZ, LIDAR_HZ, bundled_drive, format_schedules, measure_schedules
from streamdet.data.sample import load_bundled_sample


@pytest.mark.parametrize("trigger", ["lidar-synced", "simultaneous"])
def test_bundled_drive_repeats_the_sweep_and_triggers_every_camera(trigger):
    rig = load_bundled_sample().rig
    images = {n: np.zeros((2, 2, 3), np.uint8) for n in rig.names}
    drive = bundled_drive(1.0, images, trigger)
    assert len(drive.sweeps) == int(LIDAR_HZ) and drive.sweeps[-1].end_s == pytest.approx(1.0)
    per_camera = {n: sum(n in s.images for s in drive.image_sets) for n in rig.names}
    assert all(abs(c - CAMERA_HZ) <= 1 for c in per_camera.values())
    if trigger == "simultaneous":
        assert all(len(s.images) == len(rig.names) for s in drive.image_sets)
    else:
        assert max(len(s.images) for s in drive.image_sets) < len(rig.names)  # the cameras fire one after the other


def test_both_schedules_are_measured_and_reported(tiny_export):
    out = measure_schedules(tiny_export, "fp32", None, 0.2)
    assert set(out) == {"full", "phase-locked"}
    for r in out.values():
        assert r["slices_total"] > 0 and 0 <= r["slices_dropped"] <= r["slices_total"]
        assert r["image_lane_cpu_ms_per_rotation"] >= 0 and r["trigger"] == "lidar-synced"
    assert out["phase-locked"]["phase_lock"] is not None and out["full"]["phase_lock"] is None
    lines = format_schedules(out)
    assert len(lines) == 2 and "image lane 'phase-locked'" in lines[1]


def test_slice_workers_are_the_lanes_and_are_reported(tiny_export):
    out = measure_schedules(tiny_export, "fp32", None, 0.2, slice_workers=1)
    assert [r["slice_workers"] for r in out.values()] == [1, 1]
    assert all("1 slice worker(s)" in line for line in format_schedules(out))


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2", 1025])
def test_streaming_config_refuses_bad_slice_workers(bad):
    from streamdet.benchmarks.streaming import StreamingConfig

    with pytest.raises(ValueError, match="schedule_slice_workers must be None or an int in 1..1024"):
        StreamingConfig(schedule_slice_workers=bad)


def test_staleness_floor_is_zero_without_processing_and_a_camera_period_when_lifts_are_long():
    from streamdet.benchmarks.schedule_model import SleepingDetector, staleness_floor_ms
    from streamdet.replay.cost import synthetic_drive

    cams = SleepingDetector(1.0, 1.0, 1.0).quadrant_cameras
    for trigger in ("simultaneous", "lidar-synced"):
        drive = synthetic_drive(2.0, camera_trigger=trigger, points=720, image_size=(4, 4))
        assert np.nanmax(staleness_floor_ms(drive, cams, 0.0)) <= 0.0  # frames lifted at once are never stale
        long = staleness_floor_ms(drive, cams, 0.2)  # a lift longer than two camera periods misses the newest frames
        assert np.nanmin(long) >= 0.0 and np.nanmax(long) > 80.0


@pytest.mark.parametrize("delivery_ms", [5.0, 20.0, 45.0])
def test_staleness_floor_with_a_delivery_delay_is_still_zero_without_processing(delivery_ms):
    """Frames that arrive after their capture: the newest arrived frame is older, but a lift of 0 ms still takes it."""
    from streamdet.benchmarks.schedule_model import SleepingDetector, staleness_floor_ms
    from streamdet.replay.cost import synthetic_drive

    cams = SleepingDetector(1.0, 1.0, 1.0).quadrant_cameras
    drive = synthetic_drive(2.0, camera_trigger="lidar-synced", points=720, image_size=(4, 4))
    f = staleness_floor_ms(drive, cams, 0.0, delivery_s=delivery_ms / 1e3)
    assert np.isfinite(f).any() and np.nanmax(f) <= 0.0
    long = staleness_floor_ms(drive, cams, 0.2, delivery_s=delivery_ms / 1e3)
    assert np.nanmin(long) >= 0.0 and np.nanmax(long) > 80.0


@pytest.mark.parametrize("bad", ["x", "5,-1", "nan"])
def test_schedule_model_refuses_bad_delivery_delays(bad):
    from click.testing import CliRunner

    from streamdet.benchmarks.schedule_model import main

    result = CliRunner().invoke(main, ["--seconds", "1", "--delivery-ms", bad])
    assert result.exit_code == 2 and "--delivery-ms" in result.output
