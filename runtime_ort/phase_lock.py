"""The rotation as the image lane sees it: when will the LiDAR's next slice of each quadrant arrive?

The phase-locked schedule (``LaneConfig.schedule = "phase-locked"``, ``phase_locked_lane.py``) lifts one quadrant
of the image BEV at a time, with the newest images, timed to finish just before the first slice that reads it
arrives. This module is the pure arithmetic behind it, on the runner's clock (seconds, any origin):

- ``RotationPhase`` learns the rotation from the slices' arrival times: the newest arrival anchors the phase, and the
  period is ``1 / lidar_hz`` when the rate is given, else the median of the periods the arrivals imply over up to
  two rotations (a slice index step of d is d / num_slices of a rotation, modulo a whole one); either way a rate
  within ``LIDAR_HZ_RANGE``. A slice that comes **out of order** (its index the anchor's again, or more than half a
  rotation ahead of it, far sooner than that step takes: a late, reordered or re-sent slice) is not taken: read as
  a step forward, it would count rotations that never passed and shrink the period.
- ``plan_lift`` picks the next lift among the upcoming **passes**: a pass is one slice of one rotation and one
  quadrant that slice reads, its deadline the slice's predicted arrival. The lane lifts a quadrant for the first
  slice that reads it, and again for a later slice of the same rotation only when newer frames came meanwhile (it
  skips passes with nothing new, ``phase_locked_lane.py``). A pass starts at ``deadline - duration - margin`` (as late
  as possible, so its images are the newest), or at once when that moment has passed but the lift can still end
  by the deadline; a pass that can no longer finish in time is **skipped** (its quadrant keeps its older BEV, slices read
  that and report its age). Nothing here ever waits for a slice or holds one back.
"""

from __future__ import annotations

import math
import numbers
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

from streamdet.core.sectors import NUM_QUADRANTS, check_num_slices, quadrants_of_sector

PERIOD_SAMPLES = 16  # period measurements the median is taken over
HISTORY_ROTATIONS = 2  # rotations of arrivals one period measurement spans (at most)
# LiDAR rotations per second that can be a spinning LiDAR's (on the runner's clock): a given rate outside is refused, a
# measured one outside is no rotation (a burst of late arrivals, or a stalled driver) and not taken. The bound keeps
# the pass scans short: a period of 1e-300 s never passed `now` in floats, and a tiny measured one (a burst of
# submits) made every plan walk (lift duration / period) rotations of passes, under the lane's lock.
LIDAR_HZ_RANGE = (0.5, 100.0)


def slice_quadrants(num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> tuple[tuple[int, int], ...]:
    """(slice index, quadrant) of every quadrant every slice of a rotation reads, in scan order."""
    check_num_slices(num_slices, start_deg)
    return tuple((k, q) for k in range(num_slices) for q in quadrants_of_sector(k, num_slices, start_deg, clockwise))


def check_lidar_hz(value: object, what: str) -> float | None:
    """``value`` (None, or LiDAR rotations per second within LIDAR_HZ_RANGE) as a float; ValueError naming ``what``."""
    if value is None:
        return None
    lo, hi = LIDAR_HZ_RANGE
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not lo <= value <= hi:  # no float(10**400)
        raise ValueError(f"{what} must be None or a finite rate > 0 Hz within {lo:g}..{hi:g} Hz (a spinning LiDAR's "
                         f"rotations per second, LIDAR_HZ_RANGE), got {value!r}")  # fmt: skip
    return float(value)


class RotationPhase:
    """Arrival times of the slices -> predicted arrival times of the coming ones. Not thread-safe (the lane locks)."""

    def __init__(self, num_slices: int, start_deg: float = 0.0, lidar_hz: float | None = None, clockwise: bool = False) -> None:
        lidar_hz = check_lidar_hz(lidar_hz, "lidar_hz")
        self.num_slices = num_slices
        self.slice_quadrants = slice_quadrants(num_slices, start_deg, clockwise)
        self.quadrant_order = tuple(dict.fromkeys(q for _, q in self.slice_quadrants))  # the order the LiDAR enters them
        self._fixed_period_s = None if lidar_hz is None else 1.0 / lidar_hz
        self._periods: deque[float] = deque(maxlen=PERIOD_SAMPLES)
        self._provisional_s = math.nan  # the period over less than a rotation of arrivals
        self._median_s = math.nan  # the median of _periods
        self._anchor: tuple[int, float] | None = None  # (slice index, arrival s) of the newest arrival
        # (position, arrival s) of the last arrivals of an unbroken run, position = slices since its first one
        self._history: deque[tuple[int, float]] = deque(maxlen=HISTORY_ROTATIONS * num_slices + 1)
        self._in_burst = False  # after a burst (``_burst``), until an arrival comes at a LiDAR's pace
        self._pauses = 0  # arrivals in a row that came as pauses (``observe``)

    def observe(self, slice_index: int, arrival_s: float) -> bool:
        """A slice ``slice_index`` arrived at ``arrival_s``; False where it is not taken: it arrived before the anchor,
        or out of order (``_out_of_order``).

        The period is measured over the whole history (up to HISTORY_ROTATIONS rotations), never between two
        neighbouring arrivals: a driver that hands over slices in bursts (a busy machine) would make those tiny. An
        arrival more than half a rotation later than its index step takes (a pause: the step may hide whole
        rotations) starts the history again; a slice a little early or late (a busy driver, slices handed over out of
        order) does not. A rotation's worth of arrivals faster than any LiDAR turns (a backlog handed over at once)
        starts it again too, from the first arrival at a LiDAR's pace. A rotation's worth of pauses in a row (a LiDAR
        that now turns far slower) drops the period learnt, unless ``lidar_hz`` fixed it."""
        if self._anchor is not None:
            k0, t0 = self._anchor
            if arrival_s < t0:
                return False
            steps = (slice_index - k0) % self.num_slices or self.num_slices  # the same index again: a whole rotation
            if self._out_of_order(steps, arrival_s - t0):
                return False
            paused = self.locked and arrival_s - t0 > self.period_s * (steps / self.num_slices + 0.5)
            self._pauses = self._pauses + 1 if paused else 0
            if paused:
                self._history.clear()  # a pause: the step may hide whole rotations
                if self._pauses >= self.num_slices and self._fixed_period_s is None:
                    # A rotation's worth of pauses in a row is no pause: the LiDAR turns more than 1 + n / 2 times
                    # slower than the period learnt, whose every step looks like one. That period is dropped and
                    # the new one learnt from the arrivals to come (kept, it would hold for good).
                    self._periods.clear()
                    self._median_s = math.nan
                    self._provisional_s = math.nan
                    self._pauses = 0
            elif self._burst():
                # A rotation's worth of arrivals faster than any LiDAR turns: a backlog handed over at once. Its
                # spacing, or its span averaged with the pause after it, is no rotation: the history starts again
                # with the first arrival at a LiDAR's pace, and a period guessed from the burst's start is dropped.
                self._history.clear()
                self._provisional_s = math.nan
                self._in_burst = True
            elif self._in_burst:
                self._history.clear()
                self._in_burst = (arrival_s - t0) * self.num_slices / steps < 1.0 / LIDAR_HZ_RANGE[1]
            pos = self._history[-1][0] + steps if self._history else 0
            self._history.append((pos, float(arrival_s)))
            first_pos, first_t = self._history[0]
            period = (arrival_s - first_t) * self.num_slices / (pos - first_pos) if pos > first_pos else math.nan
            # a period no LiDAR turns at (LIDAR_HZ_RANGE) is a burst of arrivals or a stall, not a rotation: not taken
            if 1.0 / LIDAR_HZ_RANGE[1] <= period <= 1.0 / LIDAR_HZ_RANGE[0]:
                if pos - first_pos >= self.num_slices:  # a whole rotation or more: a measurement
                    self._periods.append(period)
                    self._median_s = statistics.median(self._periods)  # read at every pass the lane plans
                else:  # less: only until the first measurement
                    self._provisional_s = period
        else:
            self._history.append((0, float(arrival_s)))
        self._anchor = (int(slice_index), float(arrival_s))
        return True

    def _out_of_order(self, steps: int, elapsed_s: float) -> bool:
        """Whether an index step of ``steps`` (1..num_slices) after ``elapsed_s`` is a slice behind the anchor rather
        than one ahead. Only a step of more than half a rotation can be either (the same index is a whole one): it is
        taken as behind when it came in less than half the time the step forward takes at the period known (a
        reordered or re-sent slice comes at once), or, with no period yet, faster than any LiDAR turns."""
        if 2 * steps <= self.num_slices:
            return False
        if self.locked:
            return elapsed_s < 0.5 * self.period_s * steps / self.num_slices
        return elapsed_s * self.num_slices / steps < 1.0 / LIDAR_HZ_RANGE[1]

    def _burst(self) -> bool:
        """Whether the last rotation's worth of arrivals in the history came faster than any LiDAR turns
        (LIDAR_HZ_RANGE). Within a rotation a busy driver's bursts are normal; over a whole one they average out."""
        if len(self._history) <= self.num_slices:
            return False
        (first_pos, first_t), (last_pos, last_t) = self._history[-self.num_slices - 1], self._history[-1]
        span = last_pos - first_pos  # >= num_slices: positions grow by at least one an arrival
        return (last_t - first_t) * self.num_slices / span < 1.0 / LIDAR_HZ_RANGE[1]

    @property
    def period_s(self) -> float:
        """Seconds per rotation (nan until known)."""
        if self._fixed_period_s is not None:
            return self._fixed_period_s
        return self._median_s if self._periods else self._provisional_s

    @property
    def measured_period_s(self) -> float:
        """Seconds per rotation the arrivals show (the median of the measurements; nan before a whole rotation), also
        where ``lidar_hz`` fixed the period the lane plans with."""
        return self._median_s if self._periods else math.nan

    @property
    def given_period_s(self) -> float | None:
        """Seconds per rotation of the ``lidar_hz`` given (None: learnt from the arrivals)."""
        return self._fixed_period_s

    @property
    def locked(self) -> bool:
        """True once a slice has arrived and the period is known."""
        return self._anchor is not None and math.isfinite(self.period_s)

    def deadline_s(self, slice_index: int, rotation: int) -> float:
        """Predicted arrival of slice ``slice_index`` in ``rotation`` (0: its first arrival after the anchor's;
        1: the one after; -1: the one before)."""
        k0, t0 = self._anchor  # type: ignore[misc]
        n = self.num_slices
        steps = (slice_index - k0) % n or n
        return t0 + (steps / n + rotation) * self.period_s

    def passes(self, after_s: float) -> Iterator[tuple[float, int, int]]:
        """(deadline s, slice index, quadrant) of every pass with deadline > ``after_s``, in deadline order, without end.

        The scan starts at the rotation before the one ``after_s`` falls in (a pass's deadline lies up to a period
        after its rotation's start), not at the anchor's: its work does not grow with the time since the last
        arrival over the period. It never starts before the anchor's previous rotation (rotation -1)."""
        x = (after_s - self._anchor[1]) / self.period_s  # type: ignore[index]
        rotation = max(-1, math.floor(x) - 1)
        while True:
            here = [(self.deadline_s(k, rotation), k, q) for k, q in self.slice_quadrants]
            yield from sorted(p for p in here if p[0] > after_s)
            rotation += 1


@dataclass(frozen=True)
class LiftPlan:
    quadrant: int
    slice_index: int  # the slice whose arrival is the deadline
    deadline_s: float  # predicted arrival of that slice
    start_s: float  # when to start the lift (<= now: at once)
    skipped: tuple[tuple[float, int, int], ...] = ()  # (deadline, slice, quadrant) passes too late to finish
    # True: the quadrant's newest frames could not be lifted by the deadline, its ready ones (``ready_s``) can
    ready: bool = False


def plan_lift(
    phase: RotationPhase, now_s: float, duration_s: Callable[[int], float], margin_s: float,
    done: Iterable[tuple[float, int, int]] = (), wanted: Callable[[int], bool] = lambda q: True,
    target: int | None = None, ready_s: Callable[[int], float | None] = lambda q: None,
) -> LiftPlan | None:  # fmt: skip
    """The next lift after ``now_s``, or None when no quadrant is ``wanted``.

    The pass with the earliest deadline, of a wanted quadrant, not ``done``, that can still finish
    (``now + duration <= deadline``); it starts at ``deadline - duration - margin`` (as late as possible: the
    newest frames) or at once. With ``target`` (the lane names a quadrant that has waited more than a rotation: it
    cannot keep up) only that quadrant's passes count and the lift starts at once: a quadrant whose lifts take
    longer is never starved by those whose lifts are shorter, and a saturated lane never idles. The passes before
    it that cannot finish any more are returned as ``skipped``.

    ``ready_s(q)``: expected seconds to lift quadrant q from the frames ready for it (encoded already: a camera whose
    newest frame is still to encode gives its newest encoded one), or None where that would lift nothing younger than
    q holds.
    A pass its newest frames cannot make but its ready ones can is planned with them (``ready``) rather than skipped:
    its slice reads the cameras whose new frames were ready, not an older lift.

    ``done`` holds (deadline, slice, quadrant) of passes already lifted or given up (a pass of the same slice and
    quadrant within half a rotation of one is the same: the predicted phase moves a little with every arrival).
    ``duration_s(q)``: expected seconds to lift quadrant q; ``wanted(q)``: False for a quadrant with nothing new to
    lift (its passes are passed over, neither planned nor skipped)."""
    wanted_now = {q for q in range(NUM_QUADRANTS) if wanted(q)}
    if target is not None:
        wanted_now &= {target}
    if not wanted_now:
        return None
    done_at: dict[tuple[int, int], list[float]] = {}  # (slice, quadrant) -> deadlines: one scan of ``done``, not one per pass
    for dd, dk, dq in done:
        done_at.setdefault((dk, dq), []).append(dd)
    half = phase.period_s / 2
    skipped = []
    for deadline, k, q in phase.passes(now_s):
        if q not in wanted_now or any(abs(dd - deadline) < half for dd in done_at.get((k, q), ())):
            continue
        if now_s + duration_s(q) <= deadline:  # the margin is the aim, the deadline the limit
            start = now_s if target is not None else max(deadline - duration_s(q) - margin_s, now_s)
            return LiftPlan(q, k, deadline, start, tuple(skipped))
        ready = ready_s(q)
        if ready is not None and now_s + ready <= deadline:
            start = now_s if target is not None else max(deadline - ready - margin_s, now_s)
            return LiftPlan(q, k, deadline, start, tuple(skipped), ready=True)
        skipped.append((deadline, k, q))
    raise AssertionError("unreachable: passes() never ends")
