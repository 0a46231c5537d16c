"""Clocks the player runs on: the wall clock for real replays, a virtual clock for deterministic tests.

Every clock counts seconds of its own time base (``now``) and can block a thread until a time (``sleep_until``).
`DriveClock` maps them to the drive's time: drive seconds = (clock seconds - origin) / time_scale, so
``--time-scale 2`` plays the drive twice as slowly and every latency, measured in drive time, is what a computer
twice as fast would see.

`FakeClock` is a discrete-event clock for threads: time stands still while any participant is working and jumps to
the earliest wake-up once every participant sleeps in the clock. The player tells it how many threads should be
asleep (itself while it waits for its next release, plus the busy workers of each lane), so a fake detector that
"takes" 30 ms by sleeping 30 ms on the clock finishes at exactly t + 30 ms whatever the machine does meanwhile.
At equal wake-up times workers go before the player, so a job ending at t is emitted before a release at t.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from typing import Protocol

WORKER, PLAYER = 0, 1  # wake-up priority at equal times: workers first


class Clock(Protocol):
    """Seconds of a time base, and a way to wait for a time of it."""

    def now(self) -> float: ...

    def sleep_until(self, t_s: float, priority: int = WORKER) -> None: ...


class WallClock:
    """``time.perf_counter`` seconds; ``sleep_until`` sleeps the thread."""

    def now(self) -> float:
        return time.perf_counter()

    def sleep_until(self, t_s: float, priority: int = WORKER) -> None:
        remaining = t_s - time.perf_counter()
        if remaining > 0:
            time.sleep(remaining)

    def sleep(self, seconds: float) -> None:
        self.sleep_until(self.now() + seconds)

    def set_participants(self, count: Callable[[], int]) -> None:
        """Unused by the wall clock (time passes by itself); present so the player treats both clocks alike."""


class FakeClock:
    """Virtual seconds that advance only when every participant sleeps in the clock (see the module doc)."""

    def __init__(self, start_s: float = 0.0, stall_timeout_s: float = 30.0) -> None:
        self._now = float(start_s)
        self._cond = threading.Condition()
        self._sleepers: list[tuple[float, int, int]] = []  # heap of (wake time, priority, ticket)
        self._tickets = itertools.count()
        self._participants: Callable[[], int] = lambda: 1
        self._stall_timeout_s = stall_timeout_s  # real seconds without progress before a test fails loudly

    def set_participants(self, count: Callable[[], int]) -> None:
        """``count()``: how many threads must be asleep in the clock before time may advance. It is called with the
        clock's lock held, so it must not take a lock that a thread poking the clock holds."""
        with self._cond:
            self._participants = count
            self._cond.notify_all()

    def now(self) -> float:
        with self._cond:
            return self._now

    def poke(self) -> None:
        """Someone's state changed (a job finished): re-check whether time may advance."""
        with self._cond:
            self._cond.notify_all()

    def sleep(self, seconds: float) -> None:
        with self._cond:
            wake = self._now + float(seconds)
        self.sleep_until(wake, WORKER)

    def sleep_until(self, t_s: float, priority: int = WORKER) -> None:
        with self._cond:
            entry = (max(float(t_s), self._now), int(priority), next(self._tickets))
            heapq.heappush(self._sleepers, entry)
            self._cond.notify_all()
            deadline = time.monotonic() + self._stall_timeout_s
            while not (self._sleepers[0] == entry and len(self._sleepers) >= self._participants()):
                if not self._cond.wait(timeout=0.05) and time.monotonic() > deadline:
                    raise RuntimeError(
                        f"FakeClock stalled at t={self._now:.6f} s: {len(self._sleepers)} thread(s) asleep, "
                        f"{self._participants()} expected"
                    )
            heapq.heappop(self._sleepers)
            self._now = entry[0]
            self._cond.notify_all()


class DriveClock:
    """The drive's time on a base clock: drive seconds = (base seconds - origin) / time_scale."""

    def __init__(self, base: Clock, time_scale: float = 1.0) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        self.base = base
        self.time_scale = float(time_scale)
        self.origin_s = base.now()

    def start(self, drive_s: float) -> None:
        """Make the base clock's present moment drive time ``drive_s``."""
        self.origin_s = self.base.now() - drive_s * self.time_scale

    def now(self) -> float:
        return (self.base.now() - self.origin_s) / self.time_scale

    def sleep_until(self, drive_s: float, priority: int = PLAYER) -> None:
        self.base.sleep_until(self.origin_s + drive_s * self.time_scale, priority)
