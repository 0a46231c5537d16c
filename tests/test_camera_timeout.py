"""A camera that stops sending under the phase-locked schedule (``LaneConfig.camera_timeout_s``): its last frame is
dropped once it is older than the timeout, the quadrants lifted with it are lifted again without it, a quadrant left
with none of its cameras drops its image BEV (``forget_images(quadrants=...)``), and its next frame brings it back.
On a fake clock with a fake detector (the lane's logic), then on the tiny export (the detector's per-quadrant drop)."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.benchmarks.lane_sim import ManualClock, play_events
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorClosed, ImageUpdate, StreamingDetector
from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, StreamingRunner
from streamdet.core.camera_timeout import MAX_TIMEOUTS, TIMEOUT_INTERVALS, TIMEOUT_PERIODS, CameraTimeout, check_camera_timeout
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
SEES = {0: {"CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"}, 1: {"CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK_LEFT"},
        2: {"CAM_BACK", "CAM_BACK_LEFT"}, 3: {"CAM_BACK", "CAM_BACK_RIGHT"}}  # fmt: skip
LIDAR_HZ, CAMERA_HZ, N = 20.0, 12.0, 8
WAIT_S = 30.0


class RecordingDetector:
    """Encodes and lifts in 1 ms each on the fake clock; keeps, per quadrant, the cameras of its image BEV now
    (None: no image BEV), as a StreamingDetector's cache would."""

    uses_images = True
    camera_names = CAMERAS
    num_slices = N
    config = SimpleNamespace(start_deg=0.0, clockwise=False)

    def __init__(self, clock: ManualClock) -> None:
        self.clock = clock
        self.held: list[frozenset[str] | None] = [None] * 4
        self.lifts: list[tuple[tuple[int, ...], frozenset[str], float]] = []  # (quadrants, cameras given, end)
        self.forgets: list[tuple[tuple[int, ...], float]] = []
        self.forgot_cameras_out: list[bool] = []  # forget_images' cameras_out, per call
        self.stamps: list[dict[str, float]] = []  # per lift: each camera's frame time

    def quadrant_cameras(self, quadrants):
        return tuple(n for n in CAMERAS if any(n in SEES[q] for q in quadrants))

    def check_images(self, images) -> None:
        pass

    def encode_images(self, images):
        self.clock.t += 0.001 * len(images)
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        qs = tuple(quadrants) if quadrants else (0, 1, 2, 3)
        self.clock.t += 0.001 * len(qs)
        for q in qs:
            self.held[q] = frozenset(n for n in images if n in SEES[q])
        self.lifts.append((qs, frozenset(images), self.clock.t))
        self.stamps.append(dict(camera_timestamps) if camera_timestamps else {n: timestamp for n in images})
        return ImageUpdate(timestamp, tuple(images), (), quadrants=qs)

    def forget_images(self, through=None, quadrants=None, cameras_out=False):
        qs = tuple(quadrants) if quadrants else (0, 1, 2, 3)
        for q in qs:
            self.held[q] = None
        self.forgets.append((qs, self.clock.t))
        self.forgot_cameras_out.append(cameras_out)


def drive(timeout_s: float | None, senders, seconds: float = 3.0, slices: bool = True):
    """Slices at 20 Hz x 8 (unless ``slices`` is False: the lane never locks) and, every 1/12 s, a set of the
    cameras ``senders(t)`` names (none: no set) into a lane with ``camera_timeout_s=timeout_s`` on a fake clock.
    Returns the lane, the detector and the image sets' futures."""
    clock = ManualClock()
    det = RecordingDetector(clock)
    lane = PhaseLockedImageLane(det, N, 0.0, LIDAR_HZ, 0.002, clock=clock, thread=False, camera_timeout_s=timeout_s,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    futures = []
    events = []
    if slices:
        events += [((i + 1) / (N * LIDAR_HZ), lambda i=i: lane.observe_slice(i % N, (i + 1) / (N * LIDAR_HZ)))
                   for i in range(int(seconds * LIDAR_HZ * N))]  # fmt: skip
    for i in range(int(seconds * CAMERA_HZ)):
        t = i / CAMERA_HZ + 0.003
        cams = senders(t)
        if cams:
            frame = np.zeros((2, 2, 3), np.uint8)
            events.append((t, lambda t=t, cams=cams: futures.append(lane.submit_images({c: frame for c in cams}, t))))
    events.append((seconds, lambda: None))  # the lane's own wake-ups run until then, whatever arrives
    play_events(lane, clock, sorted(events, key=lambda e: e[0]))
    return lane, det, futures


def _lifts_with(det: RecordingDetector, camera: str, after_s: float) -> list:
    return [lift for lift in det.lifts if lift[2] > after_s and camera in lift[1]]


# ---- the lane, on a fake clock ------------------------------------------------------------------------------------
@pytest.mark.parametrize("timeout_s", [0.2, 0.5])
def test_a_camera_that_stops_is_dropped_and_its_quadrants_relifted_without_it(timeout_s):
    stop_s = 1.0
    lane, det, _ = drive(timeout_s, lambda t: CAMERAS if t < stop_s else tuple(c for c in CAMERAS if c != "CAM_BACK"))
    assert lane.stats.cameras_timed_out == 1 and lane.stats.quadrants_cleared == 0
    # no lift that ended after the timeout (plus a rotation to reach each quadrant) reads CAM_BACK's old frame
    assert _lifts_with(det, "CAM_BACK", stop_s + timeout_s + 2 / LIDAR_HZ) == []
    assert det.held[2] == {"CAM_BACK_LEFT"} and det.held[3] == {"CAM_BACK_RIGHT"}  # lifted again, without it
    assert det.held[0] == SEES[0] and det.held[1] == SEES[1]


@pytest.mark.parametrize("lift_ms", [1, 4])
def test_a_camera_back_from_an_outage_is_never_lifted_from_a_frame_before_it(lift_ms, monkeypatch):
    """Whatever the lifts cost: a pass its newest frames cannot make may be lifted from the frames ready (a camera's
    previous frame while its newest is still to encode), and a camera that timed out must leave none of those, nor
    any other frame from before its outage."""
    monkeypatch.setattr(RecordingDetector, "update_images", _slow(RecordingDetector.update_images, lift_ms * 1e-3))
    back_s = 2.0
    lane, det, _ = drive(0.2, lambda t: CAMERAS if t < 1.0 or t > back_s else tuple(c for c in CAMERAS if c != "CAM_BACK"))
    assert lane.stats.cameras_timed_out == 1
    after = [st["CAM_BACK"] for (qs, cams, end), st in zip(det.lifts, det.stamps) if end > back_s and "CAM_BACK" in st]
    assert after and min(after) > back_s  # every lift since reads its new frames only


def _slow(update, extra_s: float):
    def slower(self, *args, **kwargs):
        self.clock.t += extra_s
        return update(self, *args, **kwargs)

    return slower


def test_without_a_timeout_the_last_frame_of_a_stopped_camera_stays():
    lane, det, _ = drive(None, lambda t: CAMERAS if t < 1.0 else tuple(c for c in CAMERAS if c != "CAM_BACK"))
    assert lane.stats.cameras_timed_out == 0
    assert det.held[2] == SEES[2] and det.held[3] == SEES[3]  # still fused, however old


def test_a_quadrant_whose_cameras_all_stop_drops_its_image_bev_and_a_frame_brings_it_back():
    out = {"CAM_BACK", "CAM_BACK_LEFT"}  # every camera of quadrant 2
    lane, det, _ = drive(0.3, lambda t: CAMERAS if not 1.0 <= t < 2.0 else tuple(c for c in CAMERAS if c not in out))
    assert lane.stats.cameras_timed_out == 2 and lane.stats.quadrants_cleared >= 1
    cleared = [t for qs, t in det.forgets if qs == (2,)]
    last_frame = 11 / CAMERA_HZ + 0.003  # their last frame before 1 s
    assert cleared and last_frame + 0.3 <= cleared[0] < last_frame + 0.3 + 0.01  # at once: no pass to wait for
    assert det.held[2] == SEES[2]  # the cameras came back at 2 s: lifted again from their new frames


def test_every_camera_stopping_clears_every_quadrant_and_the_lane_then_idles():
    lane, det, _ = drive(0.25, lambda t: CAMERAS if t < 1.0 else ())
    assert lane.stats.cameras_timed_out == len(CAMERAS) and det.held == [None] * 4
    assert det.forgot_cameras_out and all(det.forgot_cameras_out)  # their slices name the cameras (cameras_missing)
    steps = det.lifts[:], det.forgets[:]
    assert lane.step(10.0) is None and (det.lifts, det.forgets) == steps  # nothing left to do or to time out


def test_before_the_lane_locks_a_timed_out_camera_leaves_the_full_update():
    lane, det, _ = drive(0.25, lambda t: CAMERAS if t < 1.0 else CAMERAS[:2], slices=False)
    assert lane.stats.quadrant_lifts == 0 and lane.stats.full_updates >= 1 and lane.stats.cameras_timed_out == 4
    last = det.lifts[-1]
    assert last[0] == (0, 1, 2, 3) and last[1] == set(CAMERAS[:2])
    lane2, det2, _ = drive(0.25, lambda t: CAMERAS if t < 1.0 else (), slices=False)
    assert det2.forgets and det2.forgets[-1][0] == (0, 1, 2, 3) and det2.held == [None] * 4


def test_a_set_dropped_unused_by_the_timeout_fails_as_superseded():
    clock = ManualClock()
    det = RecordingDetector(clock)
    lane = PhaseLockedImageLane(det, N, 0.0, LIDAR_HZ, 0.002, clock=clock, thread=False, camera_timeout_s=0.1,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    lane.observe_slice(7, 0.0)  # locked (the rate is given): the lifts wait for their passes
    lane._durations[2].extend([0.5, 0.5])  # quadrant 2's lifts take longer than the timeout: never lifted in time
    fut = lane.submit_images({"CAM_BACK": np.zeros((2, 2, 3), np.uint8)}, 0.0)
    clock.t = 0.2
    lane.step(clock.t)
    error = fut.exception(timeout=0)
    assert isinstance(error, ImagesSuperseded) and "timed out (camera_timeout_s)" in str(error)
    assert lane.stats.cameras_timed_out == 1


def test_the_lane_asks_to_be_woken_when_the_oldest_frame_times_out():
    clock = ManualClock()
    lane = PhaseLockedImageLane(RecordingDetector(clock), N, 0.0, LIDAR_HZ, 0.002, clock=clock, thread=False,
                                camera_timeout_s=0.5)  # fmt: skip
    lane.submit_images({"CAM_FRONT": np.zeros((2, 2, 3), np.uint8)}, 0.0)
    wake = lane.step(0.0)  # not locked: a full update now
    assert wake is not None and wake <= 0.5 + 1e-9
    assert lane.step(0.4) == pytest.approx(0.5)  # done: only the timeout is left to wait for


@pytest.mark.parametrize("bad", [0, -1.0, math.nan, math.inf, "1", True])
def test_a_bad_timeout_is_refused(bad):
    with pytest.raises(ValueError, match="camera_timeout_s must be None or a finite number of seconds > 0"):
        LaneConfig(schedule="phase-locked", camera_timeout_s=bad)
    with pytest.raises(ValueError, match="camera_timeout_s"):
        check_camera_timeout(bad, "camera_timeout_s")


@pytest.mark.parametrize("good", [None, 0.05, 1, np.float32(2.5)])
def test_a_good_timeout_is_taken(good):
    assert LaneConfig(schedule="phase-locked", camera_timeout_s=good).camera_timeout_s == good


def test_a_runner_on_the_real_clock_drops_a_stopped_camera():
    """The worker thread wakes for a timeout with no event to wake it (the fake detector is instant)."""
    det = RecordingDetector(time.monotonic)
    det.clock = SimpleNamespace(t=0.0)  # its costs go nowhere: the runner's clock is the real one
    runner = StreamingRunner(det, LaneConfig(schedule="phase-locked", camera_timeout_s=0.05))
    try:
        frame = np.zeros((2, 2, 3), np.uint8)
        runner.submit_images({c: frame for c in CAMERAS}, 0.0).result(timeout=WAIT_S)
        deadline = time.monotonic() + WAIT_S
        while det.held != [None] * 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert det.held == [None] * 4 and runner.phase_lock.cameras_timed_out == len(CAMERAS)
    finally:
        runner.close()


# ---- the detector's per-quadrant drop, on the tiny export ----------------------------------------------------------
def _images(det: StreamingDetector, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}


def test_forget_some_quadrants_keeps_the_others(tiny_export):
    det = StreamingDetector(tiny_export)
    first = det.update_images(_images(det, 0), 1.0)
    det.forget_images(quadrants=[1, 3])
    held = det.image_state.quadrants
    assert held[1] is None and held[3] is None and held[0].seq == held[2].seq == first.seq
    # a slice of quadrant 1 now reads no image; one of quadrant 0 still does
    sweep = load_bundled_sample().points
    parts = split_sweep(sweep, det.num_slices, det.config.start_deg)
    by_quadrant = {}
    for k, pts in enumerate(parts):
        by_quadrant.setdefault(k * 4 // det.num_slices, (k, pts))
    k1, p1 = by_quadrant[1]
    k0, p0 = by_quadrant[0]
    assert det.detect_slice(p1, k1, 1.05).image_age_s is None
    assert det.detect_slice(p0, k0, 1.05).image_age_s == pytest.approx(0.05)
    later = det.update_images(_images(det, 1), 2.0, quadrants=[1])  # the next update installs there as ever
    assert not later.superseded and det.image_state.quadrants[1].seq == later.seq
    det.forget_images(quadrants=[0, 1, 2, 3])
    assert det.image_state is None


def test_forget_some_quadrants_during_an_update_keeps_its_other_quadrants(tiny_export):
    det = StreamingDetector(tiny_export)
    install = det._install

    def hooked(*args, **kwargs):
        det._install = install
        det.forget_images(quadrants=[2])
        return install(*args, **kwargs)

    det._install = hooked
    update = det.update_images(_images(det, 0), 1.0)
    held = det.image_state.quadrants
    assert not update.superseded and held[2] is None and all(held[q].seq == update.seq for q in (0, 1, 3))


@pytest.mark.parametrize("bad", [[], [4], [2, 1], [1, 1], "1", [-1]])
def test_forget_refuses_bad_quadrants(tiny_export, bad):
    det = StreamingDetector(tiny_export)
    with pytest.raises(ValueError):
        det.forget_images(quadrants=bad)


@pytest.mark.parametrize("timeout_s", [0.4, None])
def test_a_runner_on_the_tiny_export_stops_fusing_a_silent_camera(tiny_export, timeout_s):
    """End to end: CAM_BACK sends once, then only the other cameras; a slice of quadrant 2 (which CAM_BACK sees) names
    it in cameras_missing once its frame timed out, and fuses its old frame forever without the timeout."""
    det = StreamingDetector(tiny_export)
    runner = StreamingRunner(det, LaneConfig(schedule="phase-locked", camera_timeout_s=timeout_s))
    try:
        assert "CAM_BACK" in det.quadrant_cameras([2])
        runner.submit_images(_images(det, 0), 0.0).result(timeout=WAIT_S)
        others = {n: im for n, im in _images(det, 1).items() if n != "CAM_BACK"}

        def dropped() -> bool:
            state = det.image_state.quadrants[2]
            return state is not None and "CAM_BACK" in state.cameras_missing

        t0 = time.monotonic()
        # no slice: the lane is not locked and runs full updates of the newest frames, the others' kept fresh
        while time.monotonic() - t0 < 0.6 or (timeout_s is not None and not dropped()):
            assert time.monotonic() - t0 < WAIT_S
            runner.submit_images(others, time.monotonic() - t0)
            time.sleep(0.03)
        assert runner.phase_lock.cameras_timed_out == (1 if timeout_s else 0)
        assert runner.quadrants_cleared == runner.phase_lock.quadrants_cleared == 0  # CAM_BACK_LEFT still sees q2
        parts = split_sweep(load_bundled_sample().points, det.num_slices, det.config.start_deg)
        k = next(k for k in range(det.num_slices) if k * 4 // det.num_slices == 2)
        result = runner.submit_slice(parts[k], k, 0.6).result(timeout=WAIT_S)
        assert result.cameras_missing == (("CAM_BACK",) if timeout_s else ())
    finally:
        runner.close()
        det.close()


def test_a_slow_camera_is_not_timed_out_between_its_frames():
    """CAM_BACK at 1 Hz, under a 0.4 s timeout: once its period is known (its second frame) three of its periods
    count, so it is not dropped while it sends, and is dropped about three periods after it stops."""
    lane, det, _ = drive(0.4, lambda t: CAMERAS if (t * CAMERA_HZ) % CAMERA_HZ < 1 else
                         tuple(c for c in CAMERAS if c != "CAM_BACK"), seconds=8.0)  # fmt: skip
    assert lane.stats.cameras_timed_out == 1  # after its first frame only: its period was not known yet
    assert [lift for lift in det.lifts if lift[2] > 1.1 and 2 in lift[0] and "CAM_BACK" not in lift[1]] == []
    assert det.held[2] == SEES[2]
    lane, det, _ = drive(0.4, lambda t: CAMERAS if (t < 4 and (t * CAMERA_HZ) % CAMERA_HZ < 1) else
                         tuple(c for c in CAMERAS if c != "CAM_BACK"), seconds=8.0)  # fmt: skip
    assert lane.stats.cameras_timed_out == 2 and det.held[2] == {"CAM_BACK_LEFT"}
    dropped = [lift for lift in det.lifts if lift[0] == (2,) and "CAM_BACK" not in lift[1] and lift[2] > 1.1]
    assert 3.0 + 3 * 1.0 <= dropped[0][2] < 3.0 + 3 * 1.0 + 2 / LIDAR_HZ + 0.01  # its last frame came at 3.003 s


# ---- the rule itself (core/camera_timeout.py), against a naive reference ----------------------------------------
def _reference_expiries(times: list[float], timeout_s: float) -> list[float]:
    """Each frame's expiry, recomputed from scratch: intervals over which the camera had timed out (outages) count
    only where every interval of the last TIMEOUT_INTERVALS was one."""
    out = []
    intervals = []  # (seconds, outage)
    for i, t in enumerate(times):
        if i:
            intervals.append((t - times[i - 1], t >= out[-1]))
        recent = intervals[-TIMEOUT_INTERVALS:]
        usable = sorted(g for g, outage in recent if not outage) or sorted(g for g, _ in recent)
        if usable:
            mid = len(usable) // 2
            period = usable[mid] if len(usable) % 2 else (usable[mid - 1] + usable[mid]) / 2
        else:
            period = 0.0
        out.append(t + min(max(timeout_s, TIMEOUT_PERIODS * period), MAX_TIMEOUTS * timeout_s))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_the_expiry_matches_a_naive_reference(seed):
    rng = np.random.default_rng(seed)
    timeout = CameraTimeout(float(rng.uniform(0.05, 2.0)))
    gaps = rng.exponential(rng.uniform(0.01, 1.0), size=30)
    gaps[rng.integers(0, 30, 4)] += rng.uniform(1, 30, 4)  # outages
    times = [float(t) for t in np.cumsum(gaps)]
    expected = _reference_expiries(times, timeout.timeout_s)
    for t, want in zip(times, expected):
        assert timeout.seen("CAM", t) == pytest.approx(want)
    last = timeout.expires_s("CAM")
    assert timeout.out(["CAM", "OTHER"], last - 1e-6) == [] and timeout.out(["CAM"], last) == ["CAM"]


def test_an_outage_is_not_taken_for_the_cameras_period():
    timeout = CameraTimeout(1.0)
    t = [i / 12 for i in range(12)]  # 12 Hz
    t += [t[-1] + 4 + i / 12 for i in range(1, 4)]  # 4 s out, then 12 Hz again
    for x in t:
        expires = timeout.seen("CAM", x)
    assert expires == pytest.approx(t[-1] + 1.0)  # the 4 s interval did not count
    sparse = CameraTimeout(1.0)
    for x in [i / 12 for i in range(12)]:
        sparse.seen("CAM", x)
    # it drops to a frame every 4 s: each times out after the timeout while 12 Hz intervals are among its last five
    assert [sparse.seen("CAM", 1 + 4 * k) - (1 + 4 * k) for k in range(1, 5)] == [pytest.approx(1.0)] * 4
    # once all five are 4 s it is a slow camera: three periods, at most MAX_TIMEOUTS timeouts
    assert sparse.seen("CAM", 21) == pytest.approx(21 + min(12.0, MAX_TIMEOUTS * 1.0))


def test_one_long_outage_is_capped():
    timeout = CameraTimeout(0.5)
    timeout.seen("CAM", 0.0)
    assert timeout.seen("CAM", 100.0) == pytest.approx(100.0 + MAX_TIMEOUTS * 0.5)  # not 300 s


def test_without_a_timeout_nothing_expires():
    timeout = CameraTimeout(None)
    assert timeout.seen("CAM", 0.0) == math.inf and timeout.out(["CAM"], 1e12) == []


# ---- races and corners found in review ---------------------------------------------------------------------------
def test_a_swap_relifting_while_the_lane_drops_the_last_quadrant_leaves_no_cache(tiny_export):
    det = StreamingDetector(tiny_export)
    det.update_images(_images(det, 0), 1.0)
    det.forget_images(quadrants=[1, 2, 3])
    other = type(det.lut).load(tiny_export / "lut.npz", det.grid, len(det.camera_names))  # never "current": re-lifts
    lift = det._lift_quadrants

    def lift_then_lane_drops(*a, **k):  # quadrant 0's cameras time out while the swap re-lifts it
        out = lift(*a, **k)
        det.forget_images(quadrants=[0])
        return out

    det._lift_quadrants = lift_then_lane_drops
    det.set_calibration(other)
    assert det.image_state is None and det.image_timestamp is None


def test_before_the_lane_locks_a_quadrant_without_cameras_holds_no_image():
    """Cameras out before any slice: the full updates leave the quadrants none of whose cameras is left without an
    image BEV (as a locked lane does), not a BEV lifted from zeros and stamped as new; still so once locked."""
    clock = ManualClock()
    det = RecordingDetector(clock)
    lane = PhaseLockedImageLane(det, N, 0.0, None, 0.002, clock=clock, thread=False, camera_timeout_s=0.25)
    frame = np.zeros((2, 2, 3), np.uint8)
    events = [(t, lambda t=t: lane.submit_images({c: frame for c in (CAMERAS if t < 1.0 else CAMERAS[:2])}, t))
              for t in np.arange(0.0, 4.0, 1 / 12)]  # fmt: skip
    events += [(2.0 + (i + 1) / (N * LIDAR_HZ), lambda i=i: lane.observe_slice(i % N, 2.0 + (i + 1) / (N * LIDAR_HZ)))
               for i in range(int(2 * LIDAR_HZ * N))]  # fmt: skip
    play_events(lane, clock, sorted(events, key=lambda e: e[0]))
    assert lane._phase.locked and lane.stats.cameras_timed_out == 4 and lane.stats.quadrants_cleared == 2
    assert det.held[2] is None and det.held[3] is None  # CAMERAS[:2] are front cameras: nothing sees 2 and 3
    assert det.held[0] == SEES[0] & set(CAMERAS[:2]) and det.held[1] == SEES[1] & set(CAMERAS[:2])


def test_a_closed_detector_takes_no_calibration_and_an_update_under_way_installs_nothing(tiny_export):
    det = StreamingDetector(tiny_export)
    lift = det._lift_quadrants

    def lift_then_close(*a, **k):
        out = lift(*a, **k)
        det.close()
        return out

    det._lift_quadrants = lift_then_close
    update = det.update_images(_images(det, 0), 1.0)
    assert update.superseded and det.image_state is None
    with pytest.raises(DetectorClosed):
        det.set_calibration(load_bundled_sample().rig)


def test_the_lane_still_times_cameras_out_after_an_update_failed(tiny_export):
    """The detector closed under a running lane: the failed update's step raised, and the worker still wakes for the
    timeout with no other event coming."""
    det = StreamingDetector(tiny_export)
    runner = StreamingRunner(det, LaneConfig(schedule="phase-locked", camera_timeout_s=0.1))
    try:
        runner.submit_images(_images(det, 0), 0.0).result(timeout=WAIT_S)
        det.close()
        with pytest.raises(DetectorClosed):
            runner.submit_images(_images(det, 1), 0.05).result(timeout=WAIT_S)
        deadline = time.monotonic() + WAIT_S
        while runner.phase_lock.cameras_timed_out < len(det.camera_names):
            assert time.monotonic() < deadline
            time.sleep(0.01)
    finally:
        runner.close()
