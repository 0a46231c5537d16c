"""Camera trigger models (simultaneous, LiDAR-synchronised) against a direct computation, the set assembler of the
full schedule, and the player's per-quadrant staleness reference, on fake clocks and fake detectors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.replay.assemble import SetAssembler
from streamdet.replay.clock import FakeClock
from streamdet.replay.cost import AXES_DEG, CAMERAS, synthetic_drive
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.source import LidarSweep
from streamdet.replay.triggers import check_trigger, crossing_phase_s, lidar_synced_triggers, simultaneous_triggers
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult
from streamdet.runtime_ort.postprocess import Detections

PERIOD_S = 0.05


def ring(index: int, clockwise: bool = False, with_times: bool = True, start_deg: float = 0.0) -> LidarSweep:
    az = (np.arange(1440) + 0.5) / 4.0  # every 0.25 deg
    pts = np.zeros((len(az), 5), np.float32)
    pts[:, 0], pts[:, 1] = 10 * np.cos(np.radians(az)), 10 * np.sin(np.radians(az))
    turned = np.mod((start_deg - az) if clockwise else (az - start_deg), 360.0)
    times = turned / 360.0 * PERIOD_S if with_times else None
    return LidarSweep(index, (index + 1) * PERIOD_S, PERIOD_S, pts, times, np.eye(4), np.eye(4))


def direct_triggers(axis_deg: float, sweeps: int, camera_hz: float, clockwise: bool = False, start_deg: float = 0.0):
    """Brute force: every crossing, then for each i the first crossing at or after i / camera_hz."""
    frac = np.mod((start_deg - axis_deg) if clockwise else (axis_deg - start_deg), 360.0) / 360.0
    crossings = [(r + frac) * PERIOD_S for r in range(sweeps)]
    out = []
    i = 0
    while i / camera_hz <= crossings[-1] + 1e-12:
        later = [c for c in crossings if c >= i / camera_hz - 1e-12]
        if later and (not out or later[0] != out[-1]):
            out.append(later[0])
        i += 1
    return np.array(out)


@pytest.mark.parametrize("camera_hz", [12.0, 20.0, 5.0])
@pytest.mark.parametrize("clockwise", [False, True])
def test_lidar_synced_triggers_match_a_direct_computation(camera_hz, clockwise):
    sweeps = [ring(i, clockwise) for i in range(24)]
    axes = {"A": 90.0, "B": 33.5, "C": 200.0, "D": 359.0}
    got = lidar_synced_triggers(sweeps, axes, camera_hz)
    for name, axis in axes.items():
        want = direct_triggers(axis, len(sweeps), camera_hz, clockwise)
        assert got[name].shape == want.shape, name
        np.testing.assert_allclose(got[name], want, atol=PERIOD_S * 1.5 / 360)  # the window's median, within 1.5 deg
        if camera_hz <= 20.0:
            assert abs(len(want) - camera_hz * len(sweeps) * PERIOD_S) <= 1  # the mean rate is camera_hz


def test_without_point_times_the_release_convention_times_the_crossing():
    sweep = ring(3, with_times=False)
    for axis, start in [(90.0, 0.0), (10.0, 270.0), (300.0, 90.0)]:
        want = sweep.start_s + np.mod(axis - start, 360.0) / 360.0 * PERIOD_S
        assert sweep.start_s + crossing_phase_s(sweep, axis, start) == pytest.approx(want)
    # the data's own direction wins where it has times: clockwise from 90 deg reaches 0 deg a quarter turn later
    assert crossing_phase_s(ring(0, clockwise=True, start_deg=90.0), 0.0) == pytest.approx(PERIOD_S / 4, abs=2e-4)


def test_a_camera_faster_than_the_lidar_fires_at_every_crossing():
    sweeps = [ring(i) for i in range(10)]
    got = lidar_synced_triggers(sweeps, {"A": 45.0}, 50.0)["A"]
    np.testing.assert_allclose(np.diff(got), PERIOD_S, atol=1e-4)
    assert len(got) == 10


def test_simultaneous_triggers_and_bad_input():
    got = simultaneous_triggers(0.25, 12.0, ("A", "B"))
    np.testing.assert_allclose(got["A"], np.arange(4) / 12.0)
    np.testing.assert_array_equal(got["A"], got["B"])
    assert lidar_synced_triggers([], {"A": 0.0}, 12.0)["A"].size == 0
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="camera_hz"):
            simultaneous_triggers(1.0, bad, ("A",))
    with pytest.raises(ValueError, match="trigger model"):
        check_trigger("staggered")


def test_synthetic_drive_lidar_synced_fires_each_camera_as_the_lidar_crosses_its_axis():
    drive = synthetic_drive(1.0, camera_trigger="lidar-synced", points=3600)
    per_camera: dict[str, list[float]] = {}
    for s in drive.image_sets:
        for name in s.images:
            per_camera.setdefault(name, []).append(s.capture_s)
    assert set(per_camera) == set(CAMERAS)
    for name, times in per_camera.items():
        phase = np.mod(np.array(times), PERIOD_S) / PERIOD_S * 360.0  # where in the rotation it fired (CCW from 0)
        np.testing.assert_allclose(np.abs(np.mod(phase - AXES_DEG[name] + 180, 360) - 180), 0.0, atol=1.0)
        assert len(times) in (12, 13)
    whole = synthetic_drive(1.0, camera_trigger="simultaneous", points=3600)
    assert all(set(s.images) == set(CAMERAS) for s in whole.image_sets) and len(whole.image_sets) == 12


def test_assembler_hands_over_a_whole_set_when_every_camera_is_fresh():
    img = {n: np.full((2, 2, 3), i, np.uint8) for i, n in enumerate("ABC")}
    asm = SetAssembler("ABC")
    assert asm.offer({"A": img["A"]}, 0.01) is None
    assert asm.offer({"B": img["B"]}, 0.02) is None
    assert asm.offer({"A": img["A"]}, 0.05) is None  # A again: still waiting for C
    whole = asm.offer({"C": img["C"]}, 0.03)
    assert whole is not None and whole.timestamp == 0.02
    assert whole.camera_timestamps == {"A": 0.05, "B": 0.02, "C": 0.03}
    assert set(whole.images) == {"A", "B", "C"}
    same = asm.offer(dict(img), 0.1)  # a simultaneous set: handed over at once, one timestamp
    assert same is not None and same.camera_timestamps is None and same.timestamp == 0.1
    with pytest.raises(ValueError, match="unknown cameras"):
        asm.offer({"Z": img["A"]}, 0.2)
    with pytest.raises(ValueError, match="at least one camera"):
        SetAssembler(())


def test_assembler_leaves_out_a_camera_silent_for_the_timeout():
    """C stops after its first frame: with a 0.2 s timeout the sets are made of A and B once C is 0.2 s silent; without
    one they wait for C forever. C's next frame makes it one of the set again."""
    img = np.zeros((2, 2, 3), np.uint8)
    for timeout in (0.2, None):
        asm = SetAssembler("ABC", timeout)
        assert asm.offer({"A": img, "B": img, "C": img}, 0.0) is not None
        offers = [(k / 10 + dt, cam) for k in range(1, 6) for dt, cam in ((0.01, "A"), (0.02, "B"))]
        got = [(t, s) for t, cam in offers if (s := asm.offer({cam: img}, t)) is not None]
        if timeout is None:
            assert got == []
            continue
        assert [t for t, _ in got] == pytest.approx([0.21, 0.31, 0.41, 0.51])  # from C's timeout on, one set per pair
        assert all(set(s.images) == {"A", "B"} for _, s in got)
        assert got[0][1].camera_timestamps == pytest.approx({"A": 0.21, "B": 0.12})
        assert asm.offer({"C": img}, 0.6) is None  # A and B are not fresh since the last set
        back = asm.offer({"A": img, "B": img}, 0.61)
        assert back is not None and set(back.images) == {"A", "B", "C"}


def test_assembler_a_camera_never_heard_from_counts_from_the_first_frame():
    img = np.zeros((2, 2, 3), np.uint8)
    asm = SetAssembler("ABC", 0.2)
    assert asm.offer({"A": img, "B": img}, 0.0) is None  # C may still come
    assert asm.offer({"A": img, "B": img}, 0.1) is None
    late = asm.offer({"A": img, "B": img}, 0.25)
    assert late is not None and set(late.images) == {"A", "B"}


class QuadrantFake:
    """A fake detector with cameras per quadrant; records update calls; takes ``image_ms`` per update."""

    uses_images = True

    def __init__(self, clock, image_ms: float = 5.0) -> None:
        self.clock, self.image_ms = clock, image_ms
        self.updates: list[tuple] = []
        self.stamps = [None] * 4

    def quadrant_cameras(self, quadrants):
        # cameras by the azimuth of their axis, +-60 deg of it seen
        out = []
        for n, axis in AXES_DEG.items():
            if any(abs(((90 * q + 45) - axis + 180) % 360 - 180) < 105 for q in quadrants):
                out.append(n)
        return tuple(out)

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        q = slice_index * 4 // (num_slices or 8)
        ts = self.stamps[q] if (num_slices or 8) >= 4 else min((s for s in self.stamps if s is not None), default=None)
        return SliceResult(Detections.empty(), slice_index, num_slices or 8, timestamp, ts, len(points), 0, 0)

    def update_images(self, images, timestamp=None, camera_timestamps=None, **options):
        self.updates.append((set(images), timestamp, camera_timestamps))
        self.clock.sleep(self.image_ms / 1e3)
        for q in range(4):
            cams = self.quadrant_cameras([q])
            stamps = [camera_timestamps.get(c, timestamp) for c in cams] if camera_timestamps else [timestamp]
            self.stamps[q] = min(stamps)
        return ImageUpdate(timestamp, tuple(images), ())


def test_full_schedule_gets_one_whole_set_per_camera_cycle_under_lidar_synced_triggers():
    clock = FakeClock()
    drive = synthetic_drive(1.0, camera_trigger="lidar-synced", points=720)
    det = QuadrantFake(clock)
    rec = play(drive, det, clock, PlayerConfig("streaming", 8))
    assert all(imgs == set(CAMERAS) for imgs, _, _ in det.updates)
    assert 11 <= len(det.updates) <= 12  # one per completed cycle of 12 Hz cameras (the last may not complete)
    assert all(cts is not None and ts == min(cts.values()) for _, ts, cts in det.updates)
    used = [i for i in rec.images if not i.superseded]
    assert len(used) == 6 * len(det.updates)  # every frame of a handed-over set is used
    assert sum(i.superseded for i in rec.images) == len(rec.images) - len(used)
    # the staleness reference: per slice, the oldest of the newest frames of its quadrant's cameras by scan start
    for s in rec.slices:
        if not math.isfinite(s.newest_capture_s):
            continue
        scan_start = s.sweep * PERIOD_S + PERIOD_S * s.slice_index / 8
        cams = det.quadrant_cameras([s.slice_index // 2])
        newest = [max(i.capture_s for i in drive.image_sets if n in i.images and i.capture_s <= scan_start)
                  for n in cams if any(n in i.images and i.capture_s <= scan_start for i in drive.image_sets)]  # fmt: skip
        assert s.newest_capture_s == pytest.approx(min(newest))
    st = rec.staleness_ms()
    assert st.size > 0 and np.all(np.isfinite(st))  # negative where frames that came during the scan made it in


@pytest.mark.parametrize("mode", ["full-sweep", "sequential"])
def test_the_other_modes_get_whole_sets_too_and_frames_left_at_the_end_count_as_superseded(mode):
    clock = FakeClock()
    drive = synthetic_drive(0.5, camera_trigger="lidar-synced", points=720)
    det = QuadrantFake(clock, image_ms=1.0)
    rec = play(drive, det, clock, PlayerConfig(mode, 8))
    assert det.updates and all(imgs == set(CAMERAS) for imgs, _, _ in det.updates)
    used = sum(not i.superseded for i in rec.images)
    assert used <= 6 * len(det.updates) and used + sum(i.superseded for i in rec.images) == len(rec.images)
    assert sum(s.emitted for s in rec.slices) == len(rec.slices)  # no slice lost to the batching


@pytest.mark.parametrize("delivery_ms", [0.0, 10.0, 37.5])
def test_camera_delivery_delay_releases_frames_late_and_moves_the_staleness_reference(delivery_ms):
    clock = FakeClock()
    drive = synthetic_drive(0.6, camera_trigger="lidar-synced", points=720)
    det = QuadrantFake(clock)
    rec = play(drive, det, clock, PlayerConfig("streaming", 8, camera_delivery_ms=delivery_ms))
    delay = delivery_ms / 1e3
    for i in rec.images:  # released (handed to the runtime) a delay after capture; stamped with the capture time
        assert i.release_s == pytest.approx(i.capture_s + delay, abs=1e-9)
    assert all(ts == min(cts.values()) for _, ts, cts in det.updates)  # the runtime still gets capture times
    for s in rec.slices:
        scan_start = s.sweep * PERIOD_S + PERIOD_S * s.slice_index / 8
        cams = det.quadrant_cameras([s.slice_index // 2])
        arrived = {n: [i.capture_s for i in drive.image_sets if n in i.images and i.capture_s + delay <= scan_start + 1e-12]
                   for n in cams}  # fmt: skip
        newest = [max(t) for t in arrived.values() if t]
        if newest:
            assert s.newest_capture_s == pytest.approx(min(newest))
        else:
            assert not math.isfinite(s.newest_capture_s)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_camera_delivery_delay_refuses_negative_and_non_finite(bad):
    from streamdet.replay.schedule import release_schedule

    with pytest.raises(ValueError, match="camera_delivery_ms"):
        PlayerConfig("streaming", 8, camera_delivery_ms=bad)
    with pytest.raises(ValueError, match="delivery delay"):
        release_schedule(synthetic_drive(0.1, points=90), 8, camera_delivery_s=bad)
