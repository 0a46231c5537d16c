"""The image lane of `StreamingRunner` under ``LaneConfig.schedule = "phase-locked"``.

Instead of encoding every camera and lifting all four quadrants whenever an image set arrives (the ``full``
schedule), this lane keeps the newest frame of every camera and lifts **one quadrant at a time**, the one the LiDAR
enters next, from the cameras that see it (``StreamingDetector.update_images(quadrants=...)``), timed by
``phase_lock.plan_lift`` to finish ``lift_margin_ms`` before the first slice of that quadrant arrives. A quadrant
whose cameras have no frame newer than the ones it was last lifted from is not lifted again; one whose cameras sent
newer frames after its lift is lifted again for its next slice (so a slice reads the newest frames that could be
lifted in time, and each quadrant is lifted at most once per new frame). Each camera frame is encoded once, however
many quadrants use it (``encode_images``), and ahead of its lifts: while the next lift is not due yet, the lane
encodes the frames that arrived (oldest first, when the encoding ends before that lift must start), so that a lift
is only a lift and can start later, with newer frames (cameras that fire one after the other, as the LiDAR
crosses their axes, deliver a frame every few milliseconds). Where the detector lifts per camera
(``DetectorConfig.camera_terms``, ``camera_terms.py``), encoding a frame ahead also makes its terms
(``prepare_terms``): the lift of a quadrant then only sums its cameras' terms and runs the rest of the lifter.

Degraded behaviour, in this order (each counted in ``PhaseLockStats``):

- **not locked yet** (no slice seen, or the rotation period not known yet): full updates of the newest frames, as
  the ``full`` schedule does (``full_updates``);
- **a pass the newest frames cannot make** because a camera's newest frame is still to encode, while the frames
  already encoded can (for that camera its newest encoded frame, of an image set a lift used, and never older than
  the one the quadrant holds) and are younger than the quadrant's BEV (by their oldest frame: the quadrant's age), is
  lifted from those (``ready_lifts``); the newest frames follow at a later pass. Only while the lane spent at most
  ``READY_BUSY_SHARE`` of the last rotation working and no quadrant is overdue: a lane short of time does not add
  lifts. Without it a camera whose frame came just before such a pass left the pass skipped, and its slice read a
  lift a camera period older (docs/replay.md, "Ready lifts");
- **a quadrant that cannot be lifted in time** (the expected lift, measured from the last lifts of that quadrant,
  would end after its first slice arrives) is skipped for that pass: it keeps its older BEV, which its slices read
  and whose age they report (``quadrants_skipped``; only passes with newer frames to lift count);
- **a quadrant that waited more than a rotation** for its newer frames (the lane cannot keep up) is lifted next,
  at once, for its earliest pass it can still make: round robin without idling, so that quadrants with fewer
  cameras (shorter lifts) never starve the others;
- **the slice lane is never blocked**: it runs on its own threads and reads whatever each quadrant holds; this lane
  never waits for a slice, only for time to pass or for frames and slices to arrive;
- **a backlog of slices** (``yield_at`` > 0, ``LaneConfig.image_lane_yield_slices``): while at least ``yield_at``
  slices wait in the slice lane's queue, the lane starts no encode, lift or full update (one already running
  finishes), so that where the lanes share cores the backlog gets them; it looks again every ``YIELD_POLL_S`` and at
  every event. A pass that can no longer finish in time once the backlog is gone is skipped as above (``yields``:
  the times it held back, ``yielded_ms``: for how long). One holding back lasts at most ``MAX_HOLD_S``; then it
  works as long again whatever the backlog (``holds_cut``), so that a slice lane that never catches up still leaves
  the images about half the time;
- **a camera that stops sending** (``camera_timeout_s``, ``LaneConfig.camera_timeout_s``): once it has sent no frame
  for that long on this lane's clock (or for three of its own frame periods where that is longer: core/camera_timeout.py),
  its last frame is dropped (``cameras_timed_out``) and every quadrant lifted with it is lifted again without it, as
  soon as it can be (its features zeros: ``SliceResult.cameras_missing`` names it), rather than its old frame being
  fused for as long as it stays out. A quadrant left with none of its cameras drops its image BEV at once, without
  waiting for its pass (``StreamingDetector.forget_images(quadrants=..., cameras_out=True)``, ``quadrants_cleared``): its slices read no
  image, as before the first one, and name its cameras in ``SliceResult.cameras_missing`` (the LiDAR-only fallback export where one is configured, else the camera-less BEV). Its next frame brings it back;
- **image sets**: an image set each of whose frames was replaced by a newer one before any lift used it fails
  its future with ``ImagesSuperseded``; otherwise its future holds the `ImageUpdate` of the first lift that used it.

``step(now)`` does what is due at ``now`` (at most one update, on the calling thread) and says when to call it
again: the worker thread calls it on the runner's clock, tests call it with a fake clock and a fake detector.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from streamdet.core.camera_timeout import CameraTimeout
from streamdet.core.sectors import NUM_QUADRANTS
from streamdet.runtime_ort.phase_lock import RotationPhase, plan_lift
from streamdet.runtime_ort.thread_priority import check_nice, start_worker
from streamdet.runtime_ort.worker_lane import cancel_future, claim_future, complete_future

LANE = "image-lane"  # the name its logs and errors give it
ERROR_LOG_INTERVAL_S = 10.0  # at most one log record of the worker's errors per this many seconds (a lasting failure)

log = logging.getLogger(__name__)
# A given lidar_hz whose period the arrivals' measured one is off by more than this share is logged as contradicted.
GIVEN_RATE_TOLERANCE = 0.25
# Skipped passes remembered so that none is counted twice (_newly_skipped): far more than the passes of the longest
# lift a plan gives up at once (a 3 s stall at 20 Hz x 8 slices: about 500).
SKIPS_REMEMBERED = 8192

DURATION_SAMPLES = 5  # lifts per quadrant whose second longest is the expected duration (robust to a noisy machine)
# how often a lane holding back for a backlog of slices looks at the slice queue again (a slice's arrival wakes it too)
YIELD_POLL_S = 0.001
# the longest one holding back lasts, and how long the lane then works whatever the backlog: a slice lane that never
# catches up must not leave the images to grow old without bound (a fixed time, not the rotation period: that is
# learnt from the slices' arrivals, which a backlog may have bunched)
MAX_HOLD_S = 0.1
# ready lifts (a pass its newest frames cannot make, lifted from the frames already encoded) only while the lane spent
# at most this share of the last rotation working: past it they push later lifts back (lane_sim across LiDAR rates,
# slice counts, camera rates and stage costs: docs/replay.md, "Ready lifts")
READY_BUSY_SHARE = 0.5


@dataclass
class PhaseLockStats:
    quadrant_lifts: int = 0  # per-quadrant updates run
    full_updates: int = 0  # full updates run before the rotation was locked
    quadrants_skipped: int = 0  # passes with newer frames that could not be lifted in time (older BEV kept)
    cameras_encoded: int = 0  # camera frames encoded (each once)
    encoded_ahead: int = 0  # of those, encoded on arrival, before the lift that used them was due
    given_rate_contradicted: int = 0  # 1: the slices arrive at a rate off the given lidar_hz (logged once)
    late_lifts: int = 0  # lifts that ended after their deadline, the predicted arrival (the duration estimate was short); the
    # slice itself may have come earlier or later (jitter, a wrong lidar_hz): its SliceResult.image_age_s says what it read
    yields: int = 0  # times the lane held back an update because slices waited (yield_at)
    yielded_ms: float = 0.0  # milliseconds it held back in all
    holds_cut: int = 0  # holdings back that reached their limit (MAX_HOLD_S), after which the lane worked as long
    cameras_timed_out: int = 0  # frames dropped because their camera sent nothing newer for camera_timeout_s
    quadrants_cleared: int = 0  # quadrants whose image BEV was dropped: every camera that sees them had timed out
    # lifts from a quadrant's ready frames for a pass its newest could not make (a camera's newest frame still to
    # encode: its newest encoded frame, of an image set a lift used, is lifted instead)
    ready_lifts: int = 0
    # slice arrivals not taken for the rotation's phase: behind the newest one (a late, reordered or re-sent slice,
    # phase_lock.RotationPhase); many point at the driver or at slices submitted from several threads
    slices_out_of_order: int = 0
    # steps of the worker that raised: an update's error also fails the futures of the image sets it was the first to
    # use; an encode ahead of its lift (the lift encodes the frame again) or the lane's planning has none: all are logged
    errors: int = 0


@dataclass(eq=False)
class _ImageSet:
    future: Future
    frames_left: int  # frames of this set still the newest of their camera
    used: bool = False
    closed: bool = False  # cancelled by close() / stop() already: a second shut leaves it (claimed once only)


@dataclass(eq=False)
class _Frame:
    seq: int  # frame number, increasing over all cameras
    image: np.ndarray
    timestamp: float
    owner: _ImageSet
    expires_s: float = math.inf  # when its camera counts as out unless a newer frame came (core/camera_timeout.py)
    features: np.ndarray | None = field(default=None, repr=False)  # (C, Hf, Wf) once encoded


class PhaseLockedImageLane:
    """Holds the newest frame of each camera and lifts quadrants phase-locked to the LiDAR's rotation."""

    def __init__(
        self, detector, num_slices: int, start_deg: float = 0.0, lidar_hz: float | None = None, margin_s: float = 0.002,
        clock: Callable[[], float] = time.monotonic, thread: bool = True,
        superseded: Callable[[], Exception] = lambda: RuntimeError("image set superseded by a newer one"),
        closed: Callable[[], Exception] = lambda: RuntimeError("image-lane: submit after close()"), nice: int = 0,
        backlog: Callable[[], int] | None = None, yield_at: int = 0, camera_timeout_s: float | None = None,
        clockwise: bool = False,
    ) -> None:  # fmt: skip
        """``detector``: a StreamingDetector (or one with its ``quadrant_cameras``, ``encode_images`` and
        ``update_images(images, timestamp, quadrants=, encoded=)``); ``clock``: the runner's seconds; ``thread``
        False: no worker, the caller drives ``step`` (tests); ``superseded`` / ``closed``: the errors of a superseded
        image set's future and of a submit after close (the runner's ImagesSuperseded and RunnerClosed); ``nice``:
        added to the worker thread's nice value (thread_priority.py); ``backlog``: the number of slices waiting in
        the slice lane's queue, and ``yield_at``: how many of them make this lane hold back (0: never; needs
        ``backlog``); ``camera_timeout_s``: seconds without a new frame after which a camera counts as out
        (core/camera_timeout.py; None: its last frame is kept however old); ``num_slices``, ``start_deg``,
        ``clockwise``: the LiDAR's scan layout (core/sectors.py), which tells the quadrants' order."""
        if isinstance(yield_at, bool) or not isinstance(yield_at, (int, np.integer)) or yield_at < 0:
            raise ValueError(f"image-lane: yield_at must be an int >= 0 (slices waiting; 0: never yield), got {yield_at!r}")
        if yield_at and backlog is None:
            raise ValueError(f"image-lane: yield_at={yield_at} needs a backlog (the slice lane's waiting slices)")
        self.detector = detector
        self._timeout = CameraTimeout(camera_timeout_s, "image-lane: camera_timeout_s")
        self._backlog = backlog
        self._yield_at = int(yield_at)
        self._yield_since: float | None = None  # when the current holding back began (None: not holding back)
        self._free_until = -math.inf  # after a holding back reached its limit: no holding back before this time
        self._superseded = superseded
        self._closed_error = closed
        self.margin_s = float(margin_s)
        self._nice = check_nice(nice, "image-lane: nice")
        self.clock = clock
        self.stats = PhaseLockStats()
        self.cpu_s = 0.0  # CPU seconds spent by this lane's updates (thread time of the thread running them)
        self.images_superseded = 0
        self._phase = RotationPhase(num_slices, start_deg, lidar_hz, clockwise)
        self._skips_counted: collections.OrderedDict = collections.OrderedDict()  # (deadline, slice, quadrant) counted
        self._cond = threading.Condition()
        self._frames: dict[str, _Frame] = {}
        # per camera whose newest frame is not encoded yet: its newest frame that is, of an image set a lift used (so
        # never one reported superseded; ``_ready``: a pass the newest frames cannot make in time is lifted from
        # these rather than skipped)
        self._previous: dict[str, _Frame] = {}
        self._seq = 0
        self._lifted: list[dict[str, int]] = [{} for _ in range(NUM_QUADRANTS)]  # camera -> frame seq, per quadrant
        self._full_lifted: dict[str, int] = {}
        self._lifted_s: list[float] = [-math.inf] * NUM_QUADRANTS  # per quadrant: its last lift's oldest frame time
        self._work: collections.deque = collections.deque(maxlen=1024)  # (end s, seconds) of the lane's recent updates and encodes
        # seconds of the last lifts of each quadrant (update_images alone), and of encoding one camera frame
        self._durations = [collections.deque(maxlen=DURATION_SAMPLES) for _ in range(NUM_QUADRANTS)]
        self._encode_s: collections.deque = collections.deque(maxlen=DURATION_SAMPLES)
        # (deadline, slice, quadrant) of the passes lifted or given up, at most four rotations' worth
        self._done: collections.deque = collections.deque(maxlen=4 * len(self._phase.slice_quadrants))
        # per quadrant: when a frame newer than its last lift first arrived (None: nothing new since)
        self._wanted_since: list[float | None] = [None] * NUM_QUADRANTS
        # the image sets an update is the first to use whose futures it has not completed yet (under _cond): close()
        # fails those still pending once the worker has ended, wherever their frames are
        self._settling: set[_ImageSet] = set()
        self._dirty = False
        self._closed = False
        self._error_logged_s = -math.inf  # when the worker last logged an error (time.monotonic)
        self._thread = start_worker(self._serve, "image-lane-phase-locked", self._nice) if thread else None

    # ---- events ---------------------------------------------------------------------------------
    def submit_images(self, images: Mapping[str, np.ndarray], timestamp: float,
                      camera_timestamps: Mapping[str, float] | None = None) -> Future:  # fmt: skip
        """Keep each camera's frame as the newest of its camera, stamped ``camera_timestamps[name]`` where given
        (cameras that fired at different moments), else ``timestamp``.

        The sets it supersedes fail once every new frame is in and the lane is woken, off the lock, each
        done-callback's error logged: a callback (slow, calling close(), raising SystemExit) neither half-installs
        this set nor loses its future."""
        stamps = dict(camera_timestamps or {})
        fut: Future = Future()
        superseded: list[Future] = []
        with self._cond:
            if self._closed:
                raise self._closed_error()
            owner = _ImageSet(fut, len(images))
            now = self.clock()
            for q in range(NUM_QUADRANTS):
                if self._wanted_since[q] is None and any(n in images for n in self.detector.quadrant_cameras([q])):
                    self._wanted_since[q] = now
            for name, image in images.items():
                self._seq += 1
                old = self._frames.get(name)
                expires = self._timeout.seen(name, now)
                self._frames[name] = _Frame(self._seq, image, float(stamps.get(name, timestamp)), owner, expires)
                if old is not None and old.features is not None and old.owner.used:
                    self._previous[name] = old  # (a used set is never superseded: its future holds an update)
                if old is not None and self._release(old.owner):
                    superseded.append(old.owner.future)
            self._dirty = True
            self._cond.notify_all()
        for old_future in superseded:
            complete_future(LANE, old_future, error=self._superseded())
        return fut

    def _release(self, owner: _ImageSet) -> bool:
        """(Under the lock.) One frame of ``owner`` is no longer the newest of its camera; once none is and none was
        used, the set is superseded: counted, and True, its future claimed here (its owner can no longer cancel it,
        so the count stays exact) for the caller to fail off the lock. A set its owner cancelled is not counted."""
        owner.frames_left -= 1
        if owner.frames_left == 0 and not owner.used and claim_future(owner.future):
            self.images_superseded += 1
            return True
        return False

    def observe_slice(self, slice_index: int, arrival_s: float) -> None:
        with self._cond:
            if not self._phase.observe(slice_index, arrival_s):
                self.stats.slices_out_of_order += 1
            self._check_given_rate()
            self._dirty = True
            self._cond.notify_all()

    def _check_given_rate(self) -> None:
        """(Under the lock.) Log once where a given ``lidar_hz`` contradicts the arrivals: the lane plans every lift with
        the rate it was given, so its lifts end at the wrong moments (10 Hz given for a 20 Hz LiDAR: every slice's
        image a rotation late), and no other figure says why."""
        given = self._phase.given_period_s
        if self.stats.given_rate_contradicted or given is None:
            return
        measured = self._phase.measured_period_s
        if math.isfinite(measured) and abs(measured / given - 1.0) > GIVEN_RATE_TOLERANCE:
            self.stats.given_rate_contradicted = 1
            log.warning("phase-locked lane: lidar_hz is %g Hz, the slices arrive at %.3g Hz; the lane plans with %g Hz "
                        "(give the LiDAR's rate, or None to learn it from the arrivals)", 1.0 / given, 1.0 / measured,
                        1.0 / given)  # fmt: skip

    # ---- the schedule ---------------------------------------------------------------------------
    def _expected_s(self, quadrant: int) -> float:
        """Expected seconds to update ``quadrant``: its lift plus encoding the frames of its cameras not encoded yet.
        Each is the second longest of the last measured (one outlier on a busy machine does not push every later
        lift early); a lift never measured yet counts a quarter of the full update's, or 0 (it starts at once)."""
        fresh = sum(1 for n in self.detector.quadrant_cameras([quadrant]) if n in self._frames and self._frames[n].features is None)
        return _robust_max(self._durations[quadrant]) + fresh * _robust_max(self._encode_s)

    def _ready(self, quadrant: int) -> dict[str, _Frame] | None:
        """(Under the lock.) The frames ready to lift ``quadrant`` without encoding: each camera's newest frame, or
        where that is not encoded yet its newest encoded one (``_previous``). None unless they differ from the newest
        frames (a camera's newest is still to encode), their oldest is newer than the oldest of the quadrant's last
        lift, every camera with a frame has one ready (a ready lift never leaves out a camera the newest frames have)
        and none is older than the frame of its camera the quadrant holds."""
        ready, waiting = {}, False
        for name in self.detector.quadrant_cameras([quadrant]):
            frame = self._frames.get(name)
            if frame is None:
                continue
            if frame.features is None:
                waiting = True
                frame = self._previous.get(name)
                if frame is None or frame.seq < self._lifted[quadrant].get(name, -1):
                    return None  # nothing ready, or older than the frame the quadrant holds of that camera
            ready[name] = frame
        # the quadrant's age is its oldest frame's: a ready lift that leaves that frame in makes it no younger, and
        # is not worth its CPU (it would push later lifts back where the lane is short of time)
        if not waiting or not ready or min(f.timestamp for f in ready.values()) <= self._lifted_s[quadrant]:
            return None
        return ready

    def _busy_share(self, now_s: float) -> float:
        """(Under the lock.) The share of the last rotation the lane spent on updates and encodes."""
        period = self._phase.period_s
        while self._work and self._work[0][0] <= now_s - period:
            self._work.popleft()
        return sum(min(d, e - (now_s - period)) for e, d in self._work) / period

    def _ready_s(self, quadrant: int) -> float | None:
        """Expected seconds to lift ``quadrant`` from its ready frames (its lifts' duration, nothing to encode); None
        without such a lift (``_ready``)."""
        return None if self._ready(quadrant) is None else _robust_max(self._durations[quadrant])

    def step(self, now_s: float) -> float | None:
        """Run what is due at ``now_s`` (at most one update, or one frame encoded ahead); the time to call again
        (None: at the next event)."""
        for old_future in self._expire(now_s):  # off the lock: their done-callbacks run here
            error = self._superseded()  # the runner's type (ImagesSuperseded), saying why
            complete_future(LANE, old_future, error=type(error)("image set dropped unused: its cameras' frames were "
                                                                "replaced or timed out (camera_timeout_s) before a lift used them"))  # fmt: skip
        wake = self._step(now_s)
        with self._cond:
            expiry = self._next_expiry_s()
        if expiry is None:
            return wake
        return expiry if wake is None else min(wake, expiry)

    def _expire(self, now_s: float) -> list[Future]:
        """Drop the frames of cameras that sent nothing newer for ``camera_timeout_s``; mark the quadrants lifted with
        them as wanting a lift. The futures of the image sets that leaves superseded, for the caller to fail."""
        if self._timeout.timeout_s is None:
            return []
        superseded: list[Future] = []
        with self._cond:
            gone = [n for n, f in self._frames.items() if now_s >= f.expires_s]
            for name in gone:
                frame = self._frames.pop(name)
                self.stats.cameras_timed_out += 1
                self._previous.pop(name, None)  # a camera that is out is not lifted from an older frame either
                if self._release(frame.owner):
                    superseded.append(frame.owner.future)
                for q in range(NUM_QUADRANTS):
                    seen = name in self._lifted[q] and name in self.detector.quadrant_cameras([q])
                    if seen and self._wanted_since[q] is None:
                        self._wanted_since[q] = now_s
        return superseded

    def _next_expiry_s(self) -> float | None:
        """(Under the lock.) When the oldest frame held times out; None without a timeout or frames."""
        if self._timeout.timeout_s is None or not self._frames:
            return None
        return min(f.expires_s for f in self._frames.values())

    def _step(self, now_s: float) -> float | None:
        # read before taking this lane's lock: the slice lane's own lock is never taken inside it
        busy = self._yield_at > 0 and self._backlog() >= self._yield_at
        with self._cond:
            if self._closed:  # close() from a done-callback this step ran (an image set it expired): no more updates
                return None
            if not self._frames and not any(self._lifted):
                self._hold(now_s, False)
                return None
            if not self._phase.locked:
                frames = dict(self._frames)
                # nothing newer, and no camera lifted before has timed out since
                lifted = self._full_lifted
                if all(lifted.get(n) == f.seq for n, f in frames.items()) and lifted.keys() <= frames.keys():
                    self._hold(now_s, False)
                    return None
                if self._hold(now_s, busy):
                    return now_s + YIELD_POLL_S
                quadrants, deadline = None, None
                self._wanted_since = [None] * NUM_QUADRANTS
            elif blind := self._blind():  # every camera of a quadrant timed out: drop its BEV now, no pass to wait for
                quadrants, frames, deadline = blind, {}, None
                for q in quadrants:
                    self._wanted_since[q] = None
            else:
                overdue = self._overdue(now_s)
                # a lane short of time (a quadrant overdue, or busy for most of the last rotation) spends no CPU on
                # ready lifts: each adds a lift, and later passes would then be skipped
                short = overdue is not None or self._busy_share(now_s) > READY_BUSY_SHARE
                ready = (lambda q: None) if short else self._ready_s
                plan = plan_lift(self._phase, now_s, self._expected_s, self.margin_s, self._done, self._has_new, overdue, ready)
                if plan is None:  # no quadrant has newer frames than it was lifted from
                    self._hold(now_s, False)
                    return None
                if plan.start_s > now_s:
                    ahead = self._encode_ahead(now_s, plan.start_s)
                    if ahead is None:
                        self._hold(now_s, False)
                        return plan.start_s
                    if self._hold(now_s, busy):
                        return now_s + YIELD_POLL_S
                    encode = ahead
                else:
                    if self._hold(now_s, busy):  # the pass stays planned; skipped later if it can no longer be made
                        return now_s + YIELD_POLL_S
                    encode = None
                    self._done.extend(plan.skipped)
                    self.stats.quadrants_skipped += self._newly_skipped(plan.skipped)
                    self._done.append((plan.deadline_s, plan.slice_index, plan.quadrant))
                    if plan.ready:  # the newest frames still wait for a later pass: the quadrant stays wanted
                        frames = self._ready(plan.quadrant)
                        assert frames, "a ready plan is made only where _ready gives frames (same lock, same state)"
                        self.stats.ready_lifts += 1
                    else:
                        self._wanted_since[plan.quadrant] = None  # frames that arrive during the lift set it again
                        cams = set(self.detector.quadrant_cameras([plan.quadrant]))
                        frames = {n: f for n, f in self._frames.items() if n in cams}
                    quadrants, deadline = (plan.quadrant,), plan.deadline_s
                if encode is not None:  # nothing due yet: encode a frame that arrived, off the lock
                    frames = {encode[0]: encode[1]}
                    quadrants, deadline = (), None
            # the image sets this update is the first to use: from here on none of them can be superseded
            owners = [] if quadrants == () else list({id(f.owner): f.owner for f in frames.values()
                                                      if not f.owner.used and not f.owner.closed}.values())  # fmt: skip
            for owner in owners:
                owner.used = True
            self._settling.update(owners)
        if quadrants == ():
            self._encode_only(frames)
            return now_s
        try:
            update = self._update(frames, quadrants, deadline)
        except BaseException as e:
            self._settle(owners, error=e)
            raise
        self._settle(owners, result=update)
        return now_s

    def _settle(self, owners: list[_ImageSet], result=None, error: BaseException | None = None) -> None:
        """Complete the futures of the image sets an update was the first to use (a cancelled one stays cancelled).
        Off the lock; a done-callback's error is logged, so every one of them is completed."""
        for owner in owners:
            if claim_future(owner.future):
                complete_future(LANE, owner.future, result, error)
        with self._cond:
            self._settling.difference_update(owners)

    def _hold(self, now_s: float, busy: bool) -> bool:
        """Whether to hold back an update now (``busy``: slices wait); counts the holding back. Under the lock."""
        if busy and now_s >= self._free_until:
            if self._yield_since is None:
                self._yield_since = now_s
                self.stats.yields += 1
                return True
            if now_s - self._yield_since < MAX_HOLD_S:
                return True
            # held back as long as it may: as long again without holding back, so the images get half the time
            self.stats.holds_cut += 1
            self._free_until = now_s + MAX_HOLD_S
        if self._yield_since is not None:
            self.stats.yielded_ms += max(0.0, now_s - self._yield_since) * 1e3
            self._yield_since = None
        return False

    def _encode_ahead(self, now_s: float, start_s: float) -> tuple[str, _Frame] | None:
        """(camera, frame) of the oldest frame not encoded yet, if encoding it ends before ``start_s`` (the next
        lift's start); else None."""
        pending = [(f.seq, n, f) for n, f in self._frames.items() if f.features is None]
        if not pending or now_s + _robust_max(self._encode_s) > start_s:
            return None
        _, name, frame = min(pending, key=lambda p: p[0])
        return name, frame

    def _encode_only(self, frames: dict[str, _Frame]) -> None:
        """Encode frames ahead of their lifts. Off the lock; a frame replaced meanwhile was encoded for nothing."""
        cpu0 = time.thread_time()
        t0 = self.clock()
        encoded = self.detector.encode_images({n: f.image for n, f in frames.items()})
        prepare = getattr(self.detector, "prepare_terms", None)
        if prepare is not None:  # per-camera lifts: the frame's terms now, so that its lifts only sum and finish
            prepare(encoded)
        t1 = self.clock()
        with self._cond:
            self._store_features(frames, encoded)
            self.stats.cameras_encoded += len(encoded)
            self.stats.encoded_ahead += len(encoded)
            self._encode_s.append((t1 - t0) / max(1, len(encoded)))
            self._work.append((t1, t1 - t0))
            self.cpu_s += time.thread_time() - cpu0

    def _store_features(self, frames: Mapping[str, _Frame], encoded: Mapping[str, np.ndarray]) -> None:
        """(Under the lock.) Give the frames their feature maps. A frame replaced while it was encoded, by a frame
        still to encode, becomes its camera's ``_previous`` when its set is used and it is newer than the one there
        (submit_images saw it without features)."""
        for name, feats in encoded.items():
            frame = frames[name]
            frame.features = feats
            newest, kept = self._frames.get(name), self._previous.get(name)
            if newest is not None and newest is not frame and newest.features is None and frame.owner.used \
                    and (kept is None or kept.seq < frame.seq):  # fmt: skip
                self._previous[name] = frame

    def _overdue(self, now_s: float) -> int | None:
        """The quadrant that has waited longest for its newer frames, if that is more than a rotation (the lane is
        saturated: it is lifted next, round robin in effect); else None (earliest deadline first)."""
        waiting = [(t, q) for q, t in enumerate(self._wanted_since) if t is not None and now_s - t > self._phase.period_s]
        return min(waiting)[1] if waiting else None

    def _blind(self) -> tuple[int, ...]:
        """(Under the lock.) The quadrants lifted with cameras none of which has a frame now (all timed out)."""
        return tuple(q for q in self._without(self._frames) if self._lifted[q])

    def _without(self, frames: Mapping[str, _Frame]) -> tuple[int, ...]:
        """The quadrants none of whose cameras has a frame in ``frames``."""
        return tuple(q for q in range(NUM_QUADRANTS) if not frames.keys() & set(self.detector.quadrant_cameras([q])))

    def _has_new(self, quadrant: int) -> bool:
        """Whether a camera that sees ``quadrant`` sent a frame after its last lift, or timed out since."""
        cams = self.detector.quadrant_cameras([quadrant])
        lifted = self._lifted[quadrant]
        return any(self._frames[n].seq != lifted.get(n) if n in self._frames else n in lifted for n in cams)

    def _update(self, frames: dict[str, _Frame], quadrants: tuple[int, ...] | None, deadline_s: float | None):
        """Encode the frames not encoded yet, then lift ``quadrants`` (None: all four) with them. Off the lock."""
        cpu0 = time.thread_time()
        t0 = self.clock()
        fresh = {n: f.image for n, f in frames.items() if f.features is None}
        if fresh:
            encoded = self.detector.encode_images(fresh)
            with self._cond:
                self._store_features(frames, encoded)
            self.stats.cameras_encoded += len(fresh)
        t1 = self.clock()
        images = {n: f.image for n, f in frames.items()}
        encoded = {n: f.features for n, f in frames.items()}
        timestamp = min(f.timestamp for f in frames.values()) if frames else None
        stamps = {n: f.timestamp for n, f in frames.items()}
        # each quadrant is as old as the oldest frame of its cameras: say so where the frames' times differ
        options = {"camera_timestamps": stamps} if len(set(stamps.values())) > 1 else {}
        cleared = not frames
        blind: tuple[int, ...] = ()  # quadrants of a full update none of whose cameras has a frame
        if frames:
            update = self.detector.update_images(images, timestamp, quadrants=quadrants, encoded=encoded, **options)
            if quadrants is None:
                blind = self._without(frames)
                if blind:  # no image there, as when locked (StreamingDetector's update cleared them already; a
                    self.detector.forget_images(quadrants=blind, cameras_out=True)  # detector that lifts them from zeros would not)
        else:  # every camera that sees these quadrants timed out: their slices read no image rather than old frames
            self.detector.forget_images(quadrants=quadrants, cameras_out=True)
            update = None
        t2 = self.clock()
        with self._cond:
            self._work.append((t2, t2 - t0))
            for q in range(NUM_QUADRANTS) if quadrants is None else quadrants:  # a quadrant cleared holds no frame
                self._lifted_s[q] = -math.inf if cleared or q in blind else min(f.timestamp for f in frames.values())
            if fresh:
                self._encode_s.append((t1 - t0) / len(fresh))
            self.cpu_s += time.thread_time() - cpu0
            lifted_now = {n: f.seq for n, f in frames.items()}  # a camera timed out since its last lift is left out
            if cleared:
                self.stats.quadrants_cleared += NUM_QUADRANTS if quadrants is None else len(quadrants)
                for q in range(NUM_QUADRANTS) if quadrants is None else quadrants:
                    self._lifted[q] = {}
                if quadrants is None:
                    self._full_lifted = {}
            elif quadrants is None:
                self.stats.full_updates += 1
                self.stats.quadrants_cleared += sum(1 for q in blind if self._lifted[q])
                self._full_lifted = lifted_now
                for q, durations in enumerate(self._durations):
                    self._lifted[q] = {} if q in blind else dict(lifted_now)
                    if not durations:
                        durations.append((t2 - t1) / NUM_QUADRANTS)
            else:
                self.stats.quadrant_lifts += 1
                self._durations[quadrants[0]].append(t2 - t1)
                self._lifted[quadrants[0]] = lifted_now
                if deadline_s is not None and t2 > deadline_s:
                    self.stats.late_lifts += 1
        return update

    def _newly_skipped(self, passes: tuple[tuple[float, int, int], ...]) -> int:
        """(Under the lock.) How many of ``passes`` were not counted as skipped before. A plan gives up every pass it
        cannot make, rotations ahead where a lift is expected to take that long; ``_done`` keeps only a few
        rotations of them, so the same far passes came back in the next plan and were counted twice."""
        new = 0
        # a pass is its slice's arrival, to within a slice's time: a deadline recomputed from a newer anchor moves a
        # little, never by half a slice (digits of the deadline itself would split passes at a rounding boundary)
        slot_s = self._phase.period_s / self._phase.num_slices
        for deadline, k, q in passes:
            key = (round(deadline / slot_s) if math.isfinite(slot_s) and slot_s > 0 else round(deadline, 6), k, q)
            if key not in self._skips_counted:
                self._skips_counted[key] = None
                new += 1
        while len(self._skips_counted) > SKIPS_REMEMBERED:
            self._skips_counted.popitem(last=False)
        return new

    # ---- the worker -----------------------------------------------------------------------------
    def _serve(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                self._dirty = False
            try:
                wake = self.step(self.clock())
            except BaseException as e:  # counted and logged; the lane goes on
                with self._cond:
                    wake = self._next_expiry_s()  # a camera timing out still wakes it
                self._note_error(e)
            with self._cond:
                if self._closed:
                    return
                if self._dirty:
                    continue
                timeout = None if wake is None else wake - self.clock()
                if timeout is None or timeout > 0:
                    self._cond.wait(timeout)

    def _note_error(self, error: BaseException) -> None:
        """Count a step's error and log it, the first and then at most one per ERROR_LOG_INTERVAL_S (with the count
        meanwhile): a failure on every step would flood the log."""
        now = time.monotonic()
        with self._cond:
            self.stats.errors += 1
            errors = self.stats.errors
            due = now - self._error_logged_s >= ERROR_LOG_INTERVAL_S
            if due:
                self._error_logged_s = now
        if due:
            log.error("%s: a step of the phase-locked schedule raised (%d errors so far; an update's error also "
                      "fails its image sets' futures); the lane goes on", LANE, errors, exc_info=error)  # fmt: skip

    def runs_on(self, thread: threading.Thread) -> bool:
        """Whether ``thread`` is this lane's worker."""
        return self._thread is not None and thread is self._thread

    def close(self, deadline: float | None = None, wait: bool = True) -> bool:
        """Stop the worker (a running update finishes); waiting image sets that were never used are cancelled, and
        once the worker has ended, those an update used but never completed (it was cut short) fail: then no image
        set's future is left pending. True when the worker has ended. ``wait`` False does not wait for it (as
        `stop`)."""
        return self._shut(deadline, join=wait)

    def stop(self) -> None:
        """close() without waiting for the worker, for a lane whose owner is gone (StreamingRunner's finalizer): this
        may run on any thread, the worker's too. A running update still completes the sets it uses."""
        self._shut(None, join=False)

    def _shut(self, deadline: float | None, join: bool) -> bool:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if join and self._thread is not None and self._thread is not threading.current_thread():
            # (from a done-callback run on the worker, the worker cannot wait for itself: it ends after this update)
            self._thread.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        ended = self._thread is None or not self._thread.is_alive()
        with self._cond:
            owners = {id(f.owner): f.owner for f in self._frames.values()}
            if ended:  # else the running update still completes the sets it uses
                owners.update({id(o): o for o in self._settling})
            # not those an earlier close() cancelled (a finalizer's stop() after close()): claiming a future twice makes
            # concurrent.futures log a CRITICAL "unexpected state"
            shut = [o for o in owners.values() if not o.used and not o.closed]
            for o in shut:
                o.closed = True
            waiting = [o.future for o in shut]
            unsettled = [o.future for o in owners.values() if o.used and ended and not o.future.done()]
        for fut in waiting:  # off the lock: their done-callbacks run here
            cancel_future(LANE, fut)
        for fut in unsettled:
            error = RuntimeError(f"{LANE}: closed; the update that used this image set ended without completing it")
            complete_future(LANE, fut, error=error)
        return ended


def _robust_max(seconds) -> float:
    """The second longest of a few durations (the longest when there is one, 0 when none)."""
    ordered = sorted(seconds)
    return ordered[-2] if len(ordered) >= 2 else (ordered[-1] if ordered else 0.0)
