"""The replay player with a fake detector on a fake clock: release times, drops, supersedes and each mode's order."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.replay.clock import FakeClock, WallClock
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.schedule import release_schedule, slice_sweep
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import simultaneous_triggers
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult
from streamdet.runtime_ort.lanes import LaneConfig
from streamdet.runtime_ort.postprocess import Detections

PERIOD_S = 0.05


class FakeDetector:
    """Takes ``slice_ms`` per slice (``sweep_ms`` for a whole sweep) and ``image_ms`` per image update on a clock."""

    uses_images = True

    def __init__(self, clock, slice_ms: float, image_ms: float, sweep_ms: float | None = None) -> None:
        self.clock, self.slice_ms, self.image_ms = clock, slice_ms, image_ms
        self.sweep_ms = sweep_ms if sweep_ms is not None else 8 * slice_ms
        self.image_ts = None
        self.calls: list[tuple] = []

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        self.calls.append(("slice", timestamp, slice_index, num_slices))
        if self.clock is not None:
            self.clock.sleep((self.sweep_ms if num_slices == 1 else self.slice_ms) / 1e3)
        return SliceResult(Detections.empty(), slice_index, num_slices, timestamp, self.image_ts, len(points), 0, 0)

    def update_images(self, images, timestamp=None):
        self.calls.append(("images", timestamp))
        if self.clock is not None:
            self.clock.sleep(self.image_ms / 1e3)
        self.image_ts = timestamp
        return ImageUpdate(timestamp, tuple(images), ())


def ring_sweep(index: int, points_per_deg: int = 1, with_times: bool = True) -> LidarSweep:
    """A full ring of points every 1/points_per_deg degree, fired counter-clockwise from azimuth 0."""
    az = (np.arange(360 * points_per_deg) + 0.5) / points_per_deg  # off the sector boundaries
    pts = np.zeros((len(az), 5), np.float32)
    pts[:, 0] = 10 * np.cos(np.radians(az))
    pts[:, 1] = 10 * np.sin(np.radians(az))
    times = az / 360.0 * PERIOD_S if with_times else None
    return LidarSweep(index, (index + 1) * PERIOD_S, PERIOD_S, pts, times, np.eye(4), np.eye(4))


def make_drive(sweeps: int = 4, camera_hz: float = 12.0, with_times: bool = True) -> Drive:
    image = {"CAM_FRONT": np.zeros((4, 4, 3), np.uint8)}
    triggers = np.arange(0.0, sweeps * PERIOD_S + 1e-9, 1.0 / camera_hz)
    sets = tuple(ImageSet(i, float(t), dict(image), float(t)) for i, t in enumerate(triggers))
    return Drive("test", tuple(ring_sweep(i, with_times=with_times) for i in range(sweeps)), sets, 0)


@pytest.mark.parametrize("with_times", [True, False])
def test_slices_are_released_when_their_last_point_is_scanned(with_times):
    sweep = ring_sweep(2, points_per_deg=4, with_times=with_times)
    slices = slice_sweep(sweep, 8)
    # the last point of sector k is at azimuth 45 (k + 1) - 0.125 deg
    expected = sweep.start_s + (45.0 * (np.arange(8) + 1) - 0.125) / 360.0 * PERIOD_S
    np.testing.assert_allclose([s.scan_end_s for s in slices], expected, atol=1e-9)
    assert [len(s.points) for s in slices] == [180] * 8
    full = slice_sweep(sweep, 1)
    assert len(full) == 1 and full[0].scan_end_s == pytest.approx(sweep.end_s)


def test_empty_slice_is_released_when_the_sensor_leaves_its_sector():
    sweep = ring_sweep(0)
    keep = np.arctan2(sweep.points[:, 1], sweep.points[:, 0]) >= 0  # only the first half of the ring
    half = LidarSweep(0, PERIOD_S, PERIOD_S, sweep.points[keep], sweep.point_time_s[keep], np.eye(4), np.eye(4))
    slices = slice_sweep(half, 4)
    assert [len(s.points) for s in slices[2:]] == [0, 0]
    np.testing.assert_allclose([s.scan_end_s for s in slices[2:]], [0.75 * PERIOD_S, PERIOD_S])


def test_schedule_is_in_time_order_slices_first_at_ties():
    drive = make_drive(sweeps=2, camera_hz=20.0)
    schedule = release_schedule(drive, 1)  # a whole sweep is released exactly at the rotation's end
    times = [r.time_s for r in schedule]
    assert times == sorted(times)
    at_sweep_end = [r.kind for r in schedule if abs(r.time_s - PERIOD_S) < 1e-9]
    assert at_sweep_end == ["slice", "images"]


def test_streaming_keeps_up_when_slices_fit_their_period():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=5.0, image_ms=40.0)
    rec = play(make_drive(), det, clock, PlayerConfig("streaming", num_slices=8, lanes=LaneConfig(1, 8)))
    assert len(rec.slices) == 32 and rec.slices_dropped == 0
    lat = rec.latencies_ms()
    np.testing.assert_allclose(lat, 5.0 + 0.0, atol=0.2)  # released at its last point, done 5 ms later
    assert all(s.queue_depth == 0 for s in rec.slices)
    # 12 Hz images, 40 ms each: every update runs, none waits for another
    assert rec.images_superseded == 0 and all(i.emit_s - i.capture_s == pytest.approx(0.04) for i in rec.images)


def test_streaming_drops_the_oldest_waiting_slice_when_the_queue_is_full():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=20.0, image_ms=1.0)  # 20 ms per slice, one arrives every 6.25 ms
    rec = play(make_drive(sweeps=2), det, clock, PlayerConfig("streaming", num_slices=8, lanes=LaneConfig(1, 2)))
    dropped = [s for s in rec.slices if s.dropped]
    assert len(dropped) > 0 and rec.slices_dropped == len(dropped)
    assert all(not np.isfinite(s.emit_s) for s in dropped)
    emitted = [s for s in rec.slices if s.emitted]
    # one worker: emissions 20 ms apart, in release order
    emits = [s.emit_s for s in emitted]
    assert emits == sorted(emits)
    np.testing.assert_allclose(np.diff(emits), 0.02, atol=1e-9)
    assert max(s.queue_depth for s in rec.slices) == 2
    assert len(dropped) + len(emitted) == 16


def test_image_sets_are_superseded_when_the_image_lane_is_slow():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=1.0, image_ms=200.0)  # 5 Hz image lane, 12 Hz cameras
    rec = play(make_drive(sweeps=8), det, clock, PlayerConfig("streaming", num_slices=4))
    assert rec.images_superseded > 0
    served = [i for i in rec.images if not i.superseded]
    np.testing.assert_allclose(np.diff([i.start_s for i in served]), 0.2, atol=1e-9)  # back to back
    ages = rec.image_ages_ms()
    assert ages.size and ages.min() >= 200.0 - 1.0 - 1e-6  # a BEV exists once an update has finished (the fake reads it at its end)


def test_full_sweep_waits_for_the_whole_rotation():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=1.0, image_ms=1.0, sweep_ms=10.0)
    rec = play(make_drive(), det, clock, PlayerConfig("full-sweep", num_slices=8))
    assert len(rec.slices) == 4 and all(s.num_slices == 1 for s in rec.slices)
    np.testing.assert_allclose([s.scan_end_s for s in rec.slices], PERIOD_S * (np.arange(4) + 1), atol=1e-9)
    np.testing.assert_allclose(rec.latencies_ms(), 10.0, atol=1e-6)
    assert all(c[3] == 1 for c in det.calls if c[0] == "slice")


def test_sequential_latency_grows_without_bound_when_slices_are_slower_than_their_period():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=8.0, image_ms=1.0)  # 8 ms per slice, 6.25 ms between slices
    rec = play(make_drive(sweeps=6, camera_hz=1.0), det, clock, PlayerConfig("sequential", num_slices=8))
    assert rec.slices_dropped == 0
    lat = rec.latencies_ms()
    assert np.all(np.diff(lat[1:]) > 0)  # each slice waits for every one before it
    assert lat[-1] - lat[1] >= 1.75 * (len(lat) - 2) - 1e-6  # 8 - 6.25 ms more per slice
    # one queue: no two jobs overlap, served in release order
    jobs = sorted([(s.start_s, s.end_s) for s in rec.slices] + [(i.start_s, i.end_s) for i in rec.images if not i.superseded])
    assert all(b[0] >= a[1] - 1e-12 for a, b in zip(jobs, jobs[1:]))


def test_sequential_serves_image_sets_between_slices_in_arrival_order():
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=2.0, image_ms=30.0)
    play(make_drive(sweeps=2, camera_hz=20.0), det, clock, PlayerConfig("sequential", num_slices=4))
    order = [c[1] for c in det.calls]
    assert order == sorted(order)  # arrival (timestamp) order, whatever the kind


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_time_scale_reports_drive_time(scale):
    clock = FakeClock()
    det = FakeDetector(clock, slice_ms=4.0, image_ms=1.0)  # 4 ms of wall time
    rec = play(make_drive(sweeps=2), det, clock, PlayerConfig("streaming", num_slices=4, time_scale=scale))
    np.testing.assert_allclose(rec.latencies_ms(), 4.0 / scale, atol=1e-6)
    assert rec.wall_s == pytest.approx(rec.drive_s * scale)


def test_same_fake_replay_twice_gives_the_same_record():
    def run():
        clock = FakeClock()
        rec = play(make_drive(sweeps=3), FakeDetector(clock, 9.0, 70.0), clock, PlayerConfig("streaming", 8, lanes=LaneConfig(1, 3)))
        return [(s.release_s, s.start_s, s.emit_s, s.dropped) for s in rec.slices], [i.superseded for i in rec.images]

    assert run() == run()


def test_wall_clock_replay_with_a_noop_detector():
    rec = play(make_drive(sweeps=2), FakeDetector(None, 0.0, 0.0), WallClock(), PlayerConfig("streaming", 8, time_scale=0.5))
    assert rec.slices_dropped == 0 and len(rec.latencies_ms()) == 16
    assert np.all(rec.latencies_ms() >= 0)


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="mode"):
        PlayerConfig("fastest")
    with pytest.raises(ValueError, match="time_scale"):
        PlayerConfig(time_scale=0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: PlayerConfig(time_scale=1e300), r"PlayerConfig.time_scale must be a number in 0.01..1000"),
        (lambda: PlayerConfig(time_scale=1e-300), r"PlayerConfig.time_scale must be a number in 0.01..1000"),
        (lambda: PlayerConfig(time_scale=float("nan")), "PlayerConfig.time_scale"),
        (lambda: PlayerConfig(time_scale=True), "PlayerConfig.time_scale"),
        (lambda: PlayerConfig(camera_delivery_ms=1e300), r"camera_delivery_ms must be a number of ms in 0..10000"),
        (lambda: PlayerConfig(camera_delivery_ms=-1.0), "camera_delivery_ms"),
        (lambda: simultaneous_triggers(1.0, 1e9, ["CAM_FRONT"]), r"camera_hz must be a rate in 0.1..1000 Hz"),
        (lambda: simultaneous_triggers(1.0, 1e-300, ["CAM_FRONT"]), r"camera_hz must be a rate in 0.1..1000 Hz"),
        (lambda: simultaneous_triggers(1.0, float("inf"), ["CAM_FRONT"]), "camera_hz"),
    ],
)
def test_the_library_bounds_what_the_cli_bounds(make, match):
    """The replay's own configs refuse what streamdet-replay's options refuse (rates, scales, delays that would
    allocate gigabytes of triggers or overflow a clock), for callers of the library."""
    with pytest.raises(ValueError, match=match):
        make()
    PlayerConfig(time_scale=1000.0, camera_delivery_ms=10_000.0)  # the bounds themselves are accepted
    PlayerConfig(time_scale=0.01)


def test_a_failing_detector_fails_the_replay_with_its_error():
    class Broken(FakeDetector):
        def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
            raise ValueError("broken slice graph")

    clock = FakeClock()
    with pytest.raises(RuntimeError, match="broken slice graph"):
        play(make_drive(sweeps=1), Broken(clock, 1.0, 1.0), clock, PlayerConfig("streaming", 4))


class CoalescingDetector(FakeDetector):
    """A FakeDetector that can detect consecutive slices of a quadrant in one run of ``slice_ms``."""

    class config:  # noqa: N801 (what the runner reads of a StreamingDetector's DetectorConfig)
        start_deg = 0.0
        clockwise = False

    num_slices = 8

    def detect_slices(self, points, slice_indices, timestamps, num_slices=None):
        self.calls.append(("slices", tuple(timestamps), tuple(slice_indices), num_slices))
        self.clock.sleep(self.slice_ms / 1e3)
        run = tuple(int(k) for k in slice_indices)
        return tuple(SliceResult(Detections.empty(), k, num_slices, t, self.image_ts, len(p), 0, 0, coalesced=run)
                     for k, t, p in zip(run, timestamps, points))  # fmt: skip


def naive_coalesced_lane(releases: list[tuple[float, int]], run_s: float, most: int, n: int = 8) -> list[tuple[float, tuple]]:
    """One worker, an unbounded queue, one run of ``run_s`` per slice or group: when the worker is free it takes the
    oldest released slice and the released slices right after it of the same quadrant (up to ``most``).
    Returns (end time, slice indices) of every run."""
    runs, free_at, i = [], 0.0, 0
    while i < len(releases):
        start = max(free_at, releases[i][0])
        group = [i]
        while (len(group) < most and i + len(group) < len(releases) and releases[i + len(group)][0] <= start + 1e-12
               and releases[group[-1]][1] + 1 == releases[i + len(group)][1]
               and releases[group[-1]][1] // (n // 4) == releases[i + len(group)][1] // (n // 4)):  # fmt: skip
            group.append(i + len(group))
        free_at = start + run_s
        runs.append((free_at, tuple(releases[j][1] for j in group)))
        i += len(group)
    return runs


@pytest.mark.parametrize("slice_ms", [4.0, 9.0, 11.0])
def test_a_lane_behind_coalesces_slices_on_the_fake_clock(slice_ms):
    """Slices of 9-11 ms every 6.25 ms: one worker alone falls behind without end; coalescing pairs of a quadrant it
    keeps up, drops nothing, and the runs match a naive model of the lane (4 ms: it never needs to)."""
    clock = FakeClock()
    det = CoalescingDetector(clock, slice_ms=slice_ms, image_ms=1.0)
    lanes = LaneConfig(1, 64, coalesce_slices=2)
    rec = play(make_drive(sweeps=4), det, clock, PlayerConfig("streaming", num_slices=8, lanes=lanes))
    assert rec.slices_dropped == 0 and all(s.emitted for s in rec.slices)
    releases = [(s.release_s, s.slice_index) for s in sorted(rec.slices, key=lambda s: s.release_s)]
    # images run in their own lane (1 ms each, never in the way of the slice worker's clock)
    want = naive_coalesced_lane(releases, slice_ms / 1e3, 2)
    got = {}
    for s in rec.slices:
        got.setdefault(round(s.emit_s, 9), []).append(s.slice_index)
    assert sorted((t, tuple(sorted(ks))) for t, ks in got.items()) == [(round(t, 9), ks) for t, ks in want]
    assert all(s.coalesced == 2 for s in rec.slices if len(got[round(s.emit_s, 9)]) == 2)
    if slice_ms < 6.25:
        assert all(s.coalesced == 1 for s in rec.slices)


@pytest.mark.parametrize("value, label", [(10.0, "10"), (20.0, "20"), (50.0, "50"), (0.5, "0.5"), (3.0, ""), (40.0, ""),
                                          (0.0, ""), (-2.0, "")])  # fmt: skip
def test_the_latency_axis_labels_one_two_five_only(value, label):
    """Every minor tick of the CDF's log axis was labelled "2x10^1 3x10^1 ...", and the labels ran into each other."""
    from streamdet.replay.plot import _one_two_five

    assert _one_two_five(value) == label


def test_a_camera_out_longer_than_the_timeout_leaves_the_staleness_reference():
    """The reference of staleness added is the oldest of the newest frames of a slice's cameras; a camera silent for
    longer than the lanes' camera_timeout_s is out (the lane drops it) and leaves it, as the review found it made the
    reference seconds old and the staleness hugely negative during an outage."""
    import numpy as np

    from streamdet.replay.player import _newest_images_by_scan_start
    from streamdet.replay.record import SliceRecord
    from streamdet.replay.source import Drive, ImageSet, LidarSweep

    empty = np.zeros((0, 5), np.float32)
    sweeps = tuple(LidarSweep(i, (i + 1) * 0.05, 0.05, empty, None, np.eye(4), np.eye(4)) for i in range(60))
    img = np.zeros((2, 2, 3), np.uint8)
    sets = [ImageSet(0, 0.01, {"A": img, "B": img}, 0.01)]  # B's only frame; A goes on at 12 Hz
    sets += [ImageSet(i, 0.01 + i / 12, {"A": img}, 0.01 + i / 12) for i in range(1, 36)]
    drive = Drive("d", sweeps, tuple(sets), 0)
    records = [SliceRecord(50, 0, 1, 2.55, 0)]  # scan start 2.5 s: A's newest frame 2.51 - ..., B's 2.5 s old
    for timeout, want in ((None, 0.01), (1.0, max(s.capture_s for s in sets if s.capture_s <= 2.5))):
        _newest_images_by_scan_start(drive, records, None, 0.0, 0.0, False, timeout)
        assert records[0].newest_capture_s == pytest.approx(want)
