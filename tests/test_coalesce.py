"""Coalesced slices: which slices may share one slice-graph run (against a naive rule), how a run's detections go
back to its slices (against a naive loop), the detector's `detect_slices` (parity with a run of one slice and with
the same points as one wider slice) and the slice lane's coalescing policy (against a naive walk of the queue)."""

from __future__ import annotations

import math
import threading
from concurrent.futures import CancelledError

import numpy as np
import pytest

from streamdet.core.boxes import BOX_DIM
from streamdet.core.slicing import split_sweep
from streamdet.runtime_ort.coalesce import can_coalesce, check_coalesced, split_by_slice
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.detector_results import SliceResult
from streamdet.runtime_ort.lanes import LaneConfig, SliceDropped, StreamingRunner
from streamdet.runtime_ort.postprocess import Detections

WAIT_S = 30.0  # generous: the machine is shared; nothing here waits this long when it works


def naive_same_quadrant(a: int, b: int, n: int) -> bool:
    """Slices a, b of n (start 0 deg) lie in the same quadrant, b right after a: by the sectors' degrees."""
    width = 360.0 / n
    lo_a, lo_b = a * width, b * width
    return b == a + 1 and b < n and n >= 4 and math.floor(lo_a / 90.0) == math.floor(lo_b / 90.0)


@pytest.mark.parametrize("n", [1, 2, 4, 8, 16, 32])
def test_can_coalesce_matches_the_sectors(n):
    for a in range(n):
        for b in range(n):
            assert can_coalesce(a, b, n) == naive_same_quadrant(a, b, n), (a, b, n)


@pytest.mark.parametrize("n,start", [(8, 90.0), (16, 270.0)])
def test_can_coalesce_follows_the_start_angle(n, start):
    per_quadrant = n // 4
    for a in range(n - 1):  # with sectors aligned to the quadrants the start angle shifts nothing within a rotation
        assert can_coalesce(a, a + 1, n, start) == ((a + 1) % per_quadrant != 0)


@pytest.mark.parametrize("bad", [(), (1, 0), (0, 2), (1, 2), (7, 8), (-1, 0), (True,), (0.0,), ("0",), (0, 1, 2)])
def test_check_coalesced_refuses_what_cannot_share_a_run(bad):
    with pytest.raises(ValueError, match="slice"):
        check_coalesced(bad, 8)


def test_check_coalesced_accepts_runs_inside_a_quadrant():
    assert check_coalesced((np.int64(2), 3), 8) == (2, 3)
    assert check_coalesced(tuple(range(8, 16)), 32) == tuple(range(8, 16))
    assert check_coalesced((5,), 8) == (5,)


def _boxes(rng: np.random.Generator, m: int) -> Detections:
    boxes = np.zeros((m, BOX_DIM), np.float32)
    boxes[:, :2] = rng.uniform(-50, 50, (m, 2))
    boxes[:, 3:6] = 1.0
    return Detections(boxes, rng.uniform(0, 1, m).astype(np.float32), rng.integers(0, 8, m))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("run", [(0,), (0, 1), (2, 3), (4, 5, 6, 7)])
def test_split_by_slice_against_a_naive_loop(seed, run):
    n = 8 if len(run) <= 2 else 16
    dets = _boxes(np.random.default_rng(seed), 60)
    parts = split_by_slice(dets, run, n)
    assert len(parts) == len(run)
    width = 360.0 / n
    want = [[] for _ in run]
    for i, (x, y) in enumerate(dets.boxes[:, :2]):
        k = int((math.degrees(math.atan2(y, x)) % 360.0) // width)
        want[run.index(k) if k in run else len(run) - 1].append(i)
    for part, rows in zip(parts, want):
        np.testing.assert_array_equal(part.boxes, dets.boxes[rows])
        np.testing.assert_array_equal(part.scores, dets.scores[rows])
    assert sum(len(p) for p in parts) == len(dets)


def test_split_by_slice_of_nothing():
    parts = split_by_slice(Detections.empty(), (0, 1), 8)
    assert [len(p) for p in parts] == [0, 0]


# ---- the detector ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def detector(tiny_export):
    return StreamingDetector(tiny_export, DetectorConfig(precision="fp32"))


def _sweep(seed: int, n: int = 6000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = rng.uniform(3, 40, n)
    a = rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-2, 1, n), rng.uniform(0, 255, n),
                     rng.integers(0, 32, n)], axis=1).astype(np.float32)  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_detect_slices_of_one_is_detect_slice(detector, seed):
    slices = split_sweep(_sweep(seed), 8)
    for k in (0, 5):
        one = detector.detect_slice(slices[k], k, 1.0)
        (alone,) = detector.detect_slices([slices[k]], [k], [1.0])
        np.testing.assert_array_equal(one.detections.boxes, alone.detections.boxes)
        assert (one.num_pillars, one.coalesced, alone.coalesced) == (alone.num_pillars, (), ())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("first", [0, 4])
def test_a_coalesced_run_is_the_wider_slice_split_by_sector(detector, seed, first):
    """Slices 2j, 2j+1 of 8 in one run see what slice j of 4 sees (same quadrant, same points, same sector): their
    detections together are its detections, split by the boxes' centres."""
    slices = split_sweep(_sweep(seed), 8)
    j = first // 2
    a, b = detector.detect_slices([slices[first], slices[first + 1]], [first, first + 1], [2.0, 2.0125])
    wide = detector.detect_slice(np.concatenate([slices[first], slices[first + 1]]), j, 2.0125, num_slices=4)
    got = np.concatenate([a.detections.boxes, b.detections.boxes])
    assert len(got) == len(wide.detections)
    assert {tuple(r) for r in got.round(4)} == {tuple(r) for r in wide.detections.boxes.round(4)}
    assert (a.slice_index, b.slice_index, a.coalesced, b.coalesced) == (first, first + 1, (first, first + 1), (first, first + 1))
    assert (a.timestamp, b.timestamp) == (2.0, 2.0125)
    assert (a.num_points, b.num_points) == (len(slices[first]), len(slices[first + 1]))
    assert (a.num_pillars, b.num_pillars) == (0, wide.num_pillars)  # the run's count once, on its last slice
    parts = split_by_slice(Detections(got, np.zeros(len(got)), np.zeros(len(got), np.int64)), (first, first + 1), 8)
    assert [len(p) for p in parts] == [len(a.detections), len(b.detections)]


def test_detect_slices_refuses_bad_input(detector):
    pts = split_sweep(_sweep(0), 8)
    with pytest.raises(ValueError, match="consecutive slices of 8 in one quadrant"):
        detector.detect_slices([pts[1], pts[2]], [1, 2], [0.0, 0.0])
    with pytest.raises(ValueError, match="one points array and one timestamp per slice"):
        detector.detect_slices([pts[0]], [0, 1], [0.0, 0.0])
    with pytest.raises(ValueError, match="float32"):
        detector.detect_slices([pts[0], pts[1].astype(np.float64)], [0, 1], [0.0, 0.0])
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        detector.detect_slices([pts[0], pts[1][:, :5]], [0, 1], [0.0, 0.0])
    with pytest.raises(ValueError, match="timestamp"):
        detector.detect_slices([pts[0], pts[1]], [0, 1], [0.0, float("nan")])
    with pytest.raises(ValueError, match="slice"):
        detector.detect_slices([], [], [])


def test_detect_slices_of_empty_slices(detector):
    empty = np.zeros((0, 6), np.float32)
    a, b = detector.detect_slices([empty, empty], [2, 3], [0.0, 0.0])
    assert len(a.detections) == len(b.detections) == 0 and a.coalesced == (2, 3)


# ---- the slice lane ----------------------------------------------------------------------------


class _Config:
    start_deg = 0.0
    clockwise = False


class GatedSliceDetector:
    """A StreamingDetector stand-in whose first slice holds the lane until the gate opens; records every run."""

    uses_images = False
    num_slices = 8
    config = _Config()

    def __init__(self, fail_runs_of: int | None = None) -> None:
        self.gate = threading.Event()
        self.started = threading.Event()
        self.runs: list[tuple[int, ...]] = []
        self.fail_runs_of = fail_runs_of

    def _hold(self) -> None:
        if not self.started.is_set():
            self.started.set()
            assert self.gate.wait(WAIT_S), "the test never opened the gate"

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None) -> SliceResult:
        self._hold()
        if not isinstance(points, np.ndarray) or points.dtype != np.float32:
            raise ValueError("points must be float32")
        self.runs.append((slice_index,))
        return _result(slice_index, timestamp, ())

    def detect_slices(self, points, slice_indices, timestamps, num_slices=None):
        self._hold()
        ks = tuple(int(k) for k in slice_indices)
        self.runs.append(ks)
        if self.fail_runs_of == len(ks):
            raise RuntimeError("graph failed")
        return tuple(_result(k, t, ks) for k, t in zip(ks, timestamps))


def _result(k, t, run) -> SliceResult:
    return SliceResult(Detections.empty(), k, 8, t, None, 0, 0, 0, coalesced=run)


def naive_runs(first: int, waiting: list[int], most: int, n: int = 8) -> list[tuple[int, ...]]:
    """The runs one worker makes: the held slice alone, then the waiting ones in order, each run taking the next
    waiting slice while it is the next slice of the same quadrant and the run is shorter than ``most``."""
    runs, queue = [(first,)], list(waiting)
    while queue:
        run = [queue.pop(0)]
        while queue and len(run) < most and naive_same_quadrant(run[-1], queue[0], n):
            run.append(queue.pop(0))
        runs.append(tuple(run))
    return runs


POINTS = np.zeros((3, 6), np.float32)


@pytest.mark.parametrize("most", [1, 2, 4])
@pytest.mark.parametrize("waiting", [[1, 2, 3, 4, 5, 6, 7], [2, 3, 4], [3, 4, 5, 6], [6, 7, 0, 1], [4, 6, 7]])
def test_a_busy_lane_coalesces_the_waiting_slices(most, waiting):
    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=most)) as runner:
        first = runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        futures = [runner.submit_slice(POINTS, k, 0.01 * (i + 1)) for i, k in enumerate(waiting)]
        det.gate.set()
        results = [f.result(WAIT_S) for f in [first, *futures]]
    want = naive_runs(0, waiting, most)
    assert det.runs == want
    assert [r.slice_index for r in results] == [0, *waiting]
    assert runner.slices_coalesced == sum(len(r) - 1 for r in want)
    assert runner.slices_dropped == 0


def test_no_slice_joins_a_run_while_another_worker_is_free():
    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=2, coalesce_slices=4)) as runner:
        first = runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        second = runner.submit_slice(POINTS, 1, 0.01)  # the free worker takes it alone
        assert second.result(WAIT_S).coalesced == ()
        det.gate.set()
        assert first.result(WAIT_S).coalesced == ()
    assert runner.slices_coalesced == 0


def test_a_bad_slice_never_joins_a_run():
    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=2)) as runner:
        runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        good = runner.submit_slice(POINTS, 2, 0.01)
        bad = runner.submit_slice(POINTS.astype(np.float64), 3, 0.02)
        nan_stamp = runner.submit_slice(POINTS, 4, float("nan"))
        after = runner.submit_slice(POINTS, 5, 0.03)
        det.gate.set()
        assert good.result(WAIT_S).coalesced == ()
        with pytest.raises(ValueError, match="float32"):
            bad.result(WAIT_S)
        with pytest.raises(ValueError, match="timestamp must be None or a finite number"):
            nan_stamp.result(0)  # refused at submit, never queued
        assert after.result(WAIT_S).coalesced == ()
    assert det.runs == [(0,), (2,), (5,)]  # 3 failed its own checks, 4 (NaN stamp) its submit; 5 alone


def test_a_failed_run_fails_every_slice_of_it():
    det = GatedSliceDetector(fail_runs_of=2)
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=2)) as runner:
        runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        a, b = runner.submit_slice(POINTS, 2, 0.01), runner.submit_slice(POINTS, 3, 0.02)
        det.gate.set()
        for f in (a, b):
            with pytest.raises(RuntimeError, match="graph failed"):
                f.result(WAIT_S)


def test_a_cancelled_slice_is_left_out_of_the_run():
    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=4)) as runner:
        runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        futures = [runner.submit_slice(POINTS, k, 0.01 * k) for k in (4, 5, 6)]
        assert futures[1].cancel()
        det.gate.set()
        with pytest.raises(CancelledError):
            futures[1].result(WAIT_S)
        assert futures[0].result(WAIT_S).slice_index == 4 and futures[2].result(WAIT_S).slice_index == 6
    assert (4, 5) not in det.runs and 5 not in {k for run in det.runs for k in run}


def test_coalescing_still_drops_from_a_full_queue():
    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=2, coalesce_slices=2)) as runner:
        runner.submit_slice(POINTS, 0, 0.0)
        assert det.started.wait(WAIT_S)
        futures = [runner.submit_slice(POINTS, k, 0.01 * k) for k in (2, 3, 4)]
        with pytest.raises(SliceDropped):
            futures[0].result(WAIT_S)
        det.gate.set()
        assert [f.result(WAIT_S).coalesced for f in futures[1:]] == [(), ()]  # 3 and 4: different quadrants
    assert runner.slices_dropped == 1


@pytest.mark.parametrize("bad", [0, 65, True, 1.5, "2", None])
def test_lane_config_refuses_a_bad_coalesce_count(bad):
    with pytest.raises(ValueError, match="coalesce_slices"):
        LaneConfig(coalesce_slices=bad)


# ---- the offline benchmark ---------------------------------------------------------------------


@pytest.mark.parametrize("n,most", [(8, 1), (8, 2), (8, 4), (32, 3), (32, 8), (4, 2), (2, 2), (1, 4)])
def test_runs_of_groups_consecutive_slices_of_a_quadrant(n, most):
    from streamdet.benchmarks.coalesce_map import runs_of

    runs = runs_of(n, most)
    assert [k for run in runs for k in run] == list(range(n))
    for run in runs:
        assert 1 <= len(run) <= most
        check_coalesced(run, n)  # each run is one the detector takes
    for a, b in zip(runs, runs[1:]):  # a run ends only when it is full or the quadrant changes
        assert len(a) == most or not can_coalesce(a[-1], b[0], n)


def test_coalesce_map_scores_slices_alone_and_in_runs(tiny_export, tiny_train_data):
    import re

    from click.testing import CliRunner

    from streamdet.benchmarks.coalesce_map import main

    args = ["--data", str(tiny_train_data), "--export-dir", str(tiny_export), "--samples", "2", "--runs", "1,2"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert re.findall(r"runs of up to (\d) slice\(s\): 2 samples, mAP [\d.]+", result.output) == ["1", "2"]
    bad = CliRunner().invoke(main, [*args[:-1], "0,2"])
    assert bad.exit_code != 0 and "ints >= 1" in bad.output


def test_a_failing_join_rule_fails_its_jobs_and_keeps_the_worker():
    """The lane's own join rule raising (a bug) reaches the callers through the futures; the worker serves on."""
    import threading as th

    from streamdet.runtime_ort.lanes import JobBatching, WorkerLane

    gate, running = th.Event(), th.Event()

    def broken(a, b):
        raise KeyError("broken join rule")

    def hold():
        running.set()
        return gate.wait(WAIT_S)

    lane = WorkerLane("test", 1, None, batch=JobBatching(joins=broken, run=lambda ps: ps, most=2))
    try:
        first = lane.submit(hold, payload=0)
        assert running.wait(WAIT_S)  # taken alone: nothing waited behind it
        second = lane.submit(lambda: "second", payload=1)  # taken with third waiting: the rule is asked and fails
        third = lane.submit(lambda: "third", payload=2)  # then taken alone: nothing behind it
        gate.set()
        assert first.result(WAIT_S) is True
        with pytest.raises(KeyError, match="broken join rule"):
            second.result(WAIT_S)
        assert third.result(WAIT_S) == "third"
    finally:
        lane.close()
