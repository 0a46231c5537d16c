"""Done-callbacks of the futures a lane drops, supersedes, completes or cancels (audit C4, C5, S1): they run with no
lane lock held, and whatever they do (raise SystemExit, take long, call close()) the submit that triggered them
still queues its own job and returns its future, the counters stay exact, and no other future is left pending.
Every wait here has a timeout: a hang fails."""

from __future__ import annotations

import logging
import sys
import threading
from concurrent.futures import Future, as_completed, wait
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.benchmarks.lane_sim import ManualClock
from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, SliceDropped, StreamingRunner
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane
from streamdet.runtime_ort.worker_lane import WorkerLane, claim_future

from lane_fakes import CAMERAS, StandInDetector
from thread_helpers import returns_within

WAIT_S = 10.0  # nothing here waits this long when it works
POINTS = np.zeros((2, 6), np.float32)


class HandlerAbort(BaseException):
    """A BaseException that is neither SystemExit nor KeyboardInterrupt (one a regression would not mistake for
    the test runner's own)."""


RAISED = [SystemExit(3), HandlerAbort("handler gave up")]


def _raise(error: BaseException):
    def callback(_future: Future) -> None:
        raise error

    return callback


def _returns_within(fn, seconds: float = WAIT_S):
    return returns_within(fn, seconds)


def _images() -> dict[str, np.ndarray]:
    return {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}


# ---- stand-ins ---------------------------------------------------------------------------------------------------
class GatedDetector(StandInDetector):
    """A StreamingDetector stand-in for both lanes and both image schedules: the first slice and the first image
    update wait for ``gate``; every camera sees every quadrant; ``updated[t]`` is set once an image update stamped
    ``t`` ran."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.started = threading.Event()
        self.updated: dict[float, threading.Event] = {t: threading.Event() for t in (0.0, 1.0, 2.0)}

    def _hold(self) -> None:
        if not self.started.is_set():
            self.started.set()
            assert self.gate.wait(WAIT_S), "the test never opened the gate"

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        self._hold()
        self.updated.setdefault(timestamp, threading.Event()).set()
        return timestamp

    def detect_slice(self, points, slice_index, timestamp=None):
        self._hold()
        return SimpleNamespace(slice_index=slice_index)


class FakeDetector:
    """The phase-locked lane's detector on a fake clock (as tests/test_runtime_phase_lock.py's): records lifts."""

    camera_names = CAMERAS

    def __init__(self) -> None:
        self.lifts: list[float] = []

    def quadrant_cameras(self, quadrants):
        return CAMERAS

    def encode_images(self, images):
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        self.lifts.append(timestamp)
        return SimpleNamespace(timestamp=timestamp, quadrants=tuple(quadrants) if quadrants else (0, 1, 2, 3))


def _fake_lane() -> PhaseLockedImageLane:
    return PhaseLockedImageLane(FakeDetector(), 8, clock=ManualClock(), thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip


def _gated_lane(capacity: int | None) -> tuple[WorkerLane, threading.Event, Future]:
    """A one-worker lane whose first job holds the worker until the gate opens."""
    lane = WorkerLane("test-lane", 1, capacity, (lambda: SliceDropped("dropped")) if capacity else None)
    gate, started = threading.Event(), threading.Event()

    def first():
        started.set()
        assert gate.wait(WAIT_S), "the test never opened the gate"
        return "first"

    fut = lane.submit(first)
    assert started.wait(WAIT_S)
    return lane, gate, fut


# ---- C4: WorkerLane.submit -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("raised", RAISED)
def test_a_raising_drop_callback_never_fails_the_submit_nor_loses_its_job(raised, caplog):
    lane, gate, first = _gated_lane(capacity=1)
    waiting = lane.submit(lambda: "waiting")
    waiting.add_done_callback(_raise(raised))
    with caplog.at_level(logging.ERROR):
        newest = lane.submit(lambda: "newest")  # the queue is full: `waiting` is dropped
    assert isinstance(waiting.exception(0), SliceDropped) and lane.dropped == 1
    assert "test-lane: a done-callback" in caplog.text
    gate.set()
    assert first.result(WAIT_S) == "first" and newest.result(WAIT_S) == "newest"
    assert lane.close(None)


@pytest.mark.parametrize("raised", RAISED)
def test_a_raising_supersede_callback_never_fails_the_submit_and_every_stale_job_is_counted(raised):
    """Two stale jobs superseded by one submit: the first one's callback raises and tries to cancel the second,
    which is already the lane's (not cancellable): both counted, both failed, the counter equal to the failures."""
    lane, gate, first = _gated_lane(capacity=None)
    a, b = lane.submit(lambda: "a", kind="images"), lane.submit(lambda: "b", kind="images")
    cancelled_b = []

    def callback(_f: Future) -> None:
        cancelled_b.append(b.cancel())
        raise raised

    a.add_done_callback(callback)
    newest = lane.submit(lambda: "newest", kind="images", supersede=lambda: ImagesSuperseded("stale"))
    assert cancelled_b == [False]
    assert isinstance(a.exception(0), ImagesSuperseded) and isinstance(b.exception(0), ImagesSuperseded)
    assert lane.superseded == 2
    gate.set()
    assert first.result(WAIT_S) == "first" and newest.result(WAIT_S) == "newest"
    assert lane.close(None)


def test_a_job_its_owner_cancelled_is_neither_dropped_nor_counted():
    lane, gate, first = _gated_lane(capacity=1)
    waiting = lane.submit(lambda: "waiting")
    assert waiting.cancel()
    kept = lane.submit(lambda: "kept")  # the cancelled job held no place: nothing dropped
    assert lane.dropped == 0 and waiting.cancelled()
    newest = lane.submit(lambda: "newest")  # now `kept` is dropped, once
    assert isinstance(kept.exception(0), SliceDropped) and lane.dropped == 1
    gate.set()
    assert first.result(WAIT_S) == "first" and newest.result(WAIT_S) == "newest"
    assert lane.close(None)


def test_claim_future_takes_only_a_pending_future(caplog):
    pending, cancelled, finished = Future(), Future(), Future()
    cancelled.cancel()
    finished.set_result("owner's")
    with caplog.at_level(logging.CRITICAL, logger="concurrent.futures"):
        assert [claim_future(f) for f in (pending, cancelled, finished)] == [True, False, False]
    assert pending.running() and not pending.cancel()  # the lane's now: its owner can no longer cancel it
    assert cancelled.cancelled() and finished.result(0) == "owner's"
    assert "unexpected state" not in caplog.text


def test_a_slow_drop_callback_never_stalls_the_workers():
    """The callback runs in the submitter's thread and waits for the new job to run: that needs the job queued
    before the callback runs and the lane's lock free while it runs."""
    lane, gate, first = _gated_lane(capacity=1)
    newest_ran = threading.Event()
    seen = []

    def callback(_f: Future) -> None:
        gate.set()
        seen.append(newest_ran.wait(WAIT_S))

    lane.submit(lambda: "waiting").add_done_callback(callback)
    newest = _returns_within(lambda: lane.submit(newest_ran.set), 2 * WAIT_S)
    assert seen == [True]
    assert first.result(WAIT_S) == "first" and newest.done()
    assert lane.close(None)


# ---- S1: a drop or supersede callback that closes the runner ------------------------------------------------------
def test_a_drop_callback_that_closes_the_runner_does_not_deadlock():
    det = GatedDetector()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=1, coalesce_slices=1))
    running = runner.submit_slice(POINTS, 0, 0.0)
    assert det.started.wait(WAIT_S)
    waiting = runner.submit_slice(POINTS, 1, 0.0)
    closed = []

    def close_runner(_f: Future) -> None:
        det.gate.set()
        closed.append(runner.close(timeout=WAIT_S))

    waiting.add_done_callback(close_runner)
    newest = _returns_within(lambda: runner.submit_slice(POINTS, 2, 0.0), 2 * WAIT_S)
    assert closed == [True]  # the newest slice was queued before the callback ran, so close() ran it
    assert running.result(0).slice_index == 0 and newest.result(0).slice_index == 2
    assert isinstance(waiting.exception(0), SliceDropped) and runner.slices_dropped == 1


def _superseded_set_closes_the_runner(schedule: str) -> tuple[StreamingRunner, Future, Future, Future, list]:
    """Set 0 is in its (gated) update, set 1 waits, set 2 supersedes set 1, whose done-callback opens the gate and
    closes the runner. (runner, set 0, set 1, set 2, what close() returned)."""
    det = GatedDetector()
    runner = StreamingRunner(det, LaneConfig(schedule=schedule))
    first = runner.submit_images(_images(), 0.0)
    assert det.started.wait(WAIT_S)
    waiting = runner.submit_images(_images(), 1.0)
    closed: list = []

    def close_runner(_f: Future) -> None:
        det.gate.set()
        closed.append(runner.close(timeout=WAIT_S))

    waiting.add_done_callback(close_runner)
    newest = _returns_within(lambda: runner.submit_images(_images(), 2.0), 2 * WAIT_S)
    return runner, first, waiting, newest, closed


def test_a_supersede_callback_that_closes_the_full_schedule_runner_does_not_deadlock():
    runner, running, waiting, newest, closed = _superseded_set_closes_the_runner("full")
    assert closed == [True]
    assert running.result(0) == 0.0 and newest.result(0) == 2.0
    assert isinstance(waiting.exception(0), ImagesSuperseded) and runner.images_superseded == 1


def test_a_supersede_callback_that_closes_the_phase_locked_runner_does_not_deadlock():
    """The lane's worker is in the update of set 0 (gated); set 1 waits; set 2 supersedes it, and set 1's callback
    opens the gate and closes the runner: the worker finishes set 0's update and ends, set 2 (never used) is
    cancelled, nothing is left pending (set 0 is used: not superseded)."""
    runner, used, waiting, newest, closed = _superseded_set_closes_the_runner("phase-locked")
    assert closed == [True]
    assert used.result(0) == 0.0 and isinstance(waiting.exception(0), ImagesSuperseded)
    # the worker may have lifted set 2 between the gate opening and close(): lifted, or cancelled, never pending
    assert newest.cancelled() or newest.result(0) == 2.0
    assert runner.images_superseded == 1


def test_a_slow_supersede_callback_never_stalls_the_phase_locked_lane():
    """The callback waits for the lane to lift the new set: that needs every new frame installed and the lane
    woken before it runs, and the lane's lock free while it runs."""
    det = GatedDetector()
    with StreamingRunner(det, LaneConfig(schedule="phase-locked")) as runner:
        used = runner.submit_images(_images(), 0.0)
        assert det.started.wait(WAIT_S)
        waiting = runner.submit_images(_images(), 1.0)
        seen = []

        def wait_for_newest(_f: Future) -> None:
            det.gate.set()
            seen.append(det.updated[2.0].wait(WAIT_S))

        waiting.add_done_callback(wait_for_newest)
        newest = _returns_within(lambda: runner.submit_images(_images(), 2.0), 2 * WAIT_S)
        assert seen == [True]
        assert used.result(WAIT_S) == 0.0 and newest.result(WAIT_S) == 2.0
        assert runner.close(timeout=WAIT_S)


# ---- C5: the phase-locked lane -------------------------------------------------------------------------------------
@pytest.mark.parametrize("raised", RAISED)
def test_one_image_sets_raising_callback_never_leaves_another_unresolved(raised, caplog):
    """One full update is the first to use sets A and B (cameras that fired separately): A's callback raises, B
    still gets the update."""
    lane = _fake_lane()
    a = lane.submit_images({c: _images()[c] for c in CAMERAS[:3]}, 1.0)
    b = lane.submit_images({c: _images()[c] for c in CAMERAS[3:]}, 1.1)
    a.add_done_callback(_raise(raised))
    with caplog.at_level(logging.ERROR):
        assert lane.step(0.0) == 0.0  # not locked yet: a full update of both sets, no error out of the step
    assert a.result(0).timestamp == 1.0 and b.result(0).timestamp == 1.0 and lane.detector.lifts == [1.0]
    assert "image-lane: a done-callback" in caplog.text
    assert lane.close()


@pytest.mark.parametrize("raised", RAISED)
def test_a_superseded_sets_raising_callback_never_half_installs_the_new_set(raised, caplog):
    lane = _fake_lane()
    old = lane.submit_images({c: _images()[c] for c in CAMERAS[:3]}, 1.0)
    old.add_done_callback(_raise(raised))
    lane._dirty = False  # as the worker leaves it once it has looked
    with caplog.at_level(logging.ERROR):
        new = lane.submit_images(_images(), 2.0)
    assert isinstance(new, Future) and not new.done()
    assert {n: (f.timestamp, f.owner.future) for n, f in lane._frames.items()} == {c: (2.0, new) for c in CAMERAS}
    assert isinstance(old.exception(0), ImagesSuperseded) and lane.images_superseded == 1 and lane._dirty
    assert "image-lane: a done-callback" in caplog.text
    lane.step(0.0)
    assert new.result(0).timestamp == 2.0
    assert lane.close()


def test_a_set_its_owner_cancelled_is_not_counted_superseded():
    lane = _fake_lane()
    old = lane.submit_images(_images(), 1.0)
    assert old.cancel()
    new = lane.submit_images(_images(), 2.0)
    assert old.cancelled() and lane.images_superseded == 0 and not new.done()
    assert lane.close() and new.cancelled()


def test_close_cancels_every_waiting_set_though_a_callback_raises():
    lane = _fake_lane()
    first = lane.submit_images({c: _images()[c] for c in CAMERAS[:3]}, 1.0)
    second = lane.submit_images({c: _images()[c] for c in CAMERAS[3:]}, 1.1)
    first.add_done_callback(_raise(SystemExit(3)))
    second.add_done_callback(_raise(SystemExit(4)))
    assert lane.close()
    assert first.cancelled() and second.cancelled()


def test_close_fails_a_set_an_update_used_but_never_completed():
    """An update cut short between marking its sets used and completing them (an interrupt landing in it) leaves
    them pending; close() fails them, though a newer set has replaced their frames, and cancels the newer one."""
    lane = _fake_lane()
    used = lane.submit_images(_images(), 1.0)

    def interrupted(owners, result=None, error=None):
        raise HandlerAbort("interrupted before the futures were completed")

    lane._settle = interrupted
    with pytest.raises(HandlerAbort):
        lane.step(0.0)
    newer = lane.submit_images(_images(), 2.0)  # `used` was used: replaced, not superseded
    assert not used.done() and lane.images_superseded == 0
    assert lane.close()
    with pytest.raises(RuntimeError, match="image-lane: closed; the update that used this image set ended without"):
        used.result(0)
    assert newer.cancelled()


def test_after_close_no_image_set_is_pending():
    """The phase-locked runner's worker: sets used, superseded and waiting, callbacks raising on each; after
    close() every future is done."""
    det = GatedDetector()
    runner = StreamingRunner(det, LaneConfig(schedule="phase-locked"))

    def submit(cameras, t: float) -> Future:
        fut = runner.submit_images({c: _images()[c] for c in cameras}, t)
        fut.add_done_callback(lambda _f: sys.exit(5))  # while it is pending: a done one would call it here
        return fut

    futures = [submit(CAMERAS, 0.0)]
    assert det.started.wait(WAIT_S)
    futures += [submit(CAMERAS[:3], 1.0), submit(CAMERAS[:3], 1.5), submit(CAMERAS[3:], 1.7)]
    det.gate.set()
    assert _returns_within(lambda: runner.close(timeout=WAIT_S), 2 * WAIT_S)
    assert all(f.done() for f in futures), [f for f in futures if not f.done()]
    assert futures[0].result(0) == 0.0 and isinstance(futures[1].exception(0), ImagesSuperseded)


# ---- concurrent.futures.wait / as_completed see every future a lane cancels or skips --------------------------------
# Future.cancel() alone leaves a future they never count as done (only set_running_or_notify_cancel tells them): a
# caller waiting on the runner's futures with wait() hung until its timeout on every one close() cancelled.
def _seen_done(futures) -> bool:
    done, pending = wait(futures, timeout=WAIT_S)
    return not pending and set(done) == set(futures)


def test_wait_sees_the_jobs_close_cancels_done():
    lane, gate, first = _gated_lane(capacity=None)
    queued = [lane.submit(lambda: "queued") for _ in range(3)]
    assert not lane.close(deadline=0.0)  # the first job still runs: the queued ones are cancelled
    assert all(f.cancelled() for f in queued)
    assert _returns_within(lambda: _seen_done(queued), 2 * WAIT_S)
    assert len(list(_returns_within(lambda: list(as_completed(queued, timeout=WAIT_S)), 2 * WAIT_S))) == 3
    gate.set()
    assert first.result(WAIT_S) == "first"


@pytest.mark.parametrize("taken_off_by", ["submit", "worker", "close"])
def test_wait_sees_a_job_its_owner_cancelled_done(taken_off_by):
    lane, gate, first = _gated_lane(capacity=None)
    cancelled = lane.submit(lambda: "never")
    assert cancelled.cancel()
    if taken_off_by == "submit":
        lane.submit(lambda: "next")
    elif taken_off_by == "worker":
        gate.set()
    else:
        lane.close(deadline=0.0)
    assert _returns_within(lambda: _seen_done([cancelled]), 2 * WAIT_S)
    gate.set()
    assert first.result(WAIT_S) == "first"
    lane.close()


@pytest.mark.parametrize("owner_cancels", [False, True])
def test_wait_sees_the_image_sets_the_phase_locked_close_cancels_done(owner_cancels):
    lane = _fake_lane()
    sets = [lane.submit_images({c: _images()[c] for c in cameras}, t) for cameras, t in ((CAMERAS[:3], 1.0), (CAMERAS[3:], 1.1))]
    if owner_cancels:
        assert sets[0].cancel()
    assert lane.close()
    assert all(f.cancelled() for f in sets)
    assert _returns_within(lambda: _seen_done(sets), 2 * WAIT_S)


def test_wait_sees_a_superseded_set_its_owner_cancelled_done():
    lane = _fake_lane()
    old = lane.submit_images(_images(), 1.0)
    assert old.cancel()
    lane.submit_images(_images(), 2.0)  # replaces every frame of the cancelled set
    assert _returns_within(lambda: _seen_done([old]), 2 * WAIT_S)
    lane.close()
