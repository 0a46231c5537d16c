"""When a camera that stopped sending counts as out: one rule for every feeder that keeps each camera's newest frame
(the phase-locked image lane, ``streamdet-bag run``, the ROS 2 node example), so that a dead camera's last frame is
not fused on for as long as it stays out.

A camera is out once it has sent no frame for ``timeout_s``, or for ``TIMEOUT_PERIODS`` of its own frame period
where that is longer, at most ``MAX_TIMEOUTS`` timeouts: a camera whose frame period is over a third of the timeout
is not timed out between two of its frames. The period is the median of its last ``TIMEOUT_INTERVALS`` frame
intervals, known from its second frame on; an interval over which the camera was out (an outage) does not count
while others do, so a camera that stops and comes back is not taken for a slow one. Only a camera all of whose
recent intervals were outages is (its first frame times out before its period is known). The times are the
caller's: the runner's clock for the lane, the messages' header stamps for a bag or a ROS node.
"""

from __future__ import annotations

import collections
import math
import numbers
import statistics

TIMEOUT_PERIODS = 3.0
TIMEOUT_INTERVALS = 5
MAX_TIMEOUTS = 10.0  # a slow camera's expiry is at most this many timeouts
DEFAULT_CAMERA_TIMEOUT_S = 1.0  # LaneConfig.camera_timeout_s, SourceConfig's, streamdet-bag run --camera-timeout-ms
MAX_CAMERA_TIMEOUT_S = 3600.0  # the CLIs' bound (an hour: longer is "never", which is None)


def check_camera_timeout(value: object, what: str) -> float | None:
    """``value`` as seconds (None stays None); ValueError quoting it unless None or a finite number > 0."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be None or a finite number of seconds > 0, got {value!r}")
    return float(value)


class CameraTimeout:
    """Each camera's frame intervals, and when its newest frame times out. Not thread-safe: its owner's lock guards
    it."""

    def __init__(self, timeout_s: float | None, what: str = "camera_timeout_s") -> None:
        self.timeout_s = check_camera_timeout(timeout_s, what)  # None: never
        # camera -> (newest frame's time, when it times out, its last intervals as (seconds, an outage))
        self._cameras: dict[str, tuple[float, float, collections.deque]] = {}
        self._sent: set[str] = set()  # cameras with a frame since the last check()

    def seen(self, camera: str, t_s: float) -> float:
        """Record a frame of ``camera`` at ``t_s``; when it times out unless a newer one comes (inf: never)."""
        if self.timeout_s is None:
            return math.inf
        last = self._cameras.get(camera)
        gaps = last[2] if last is not None else collections.deque(maxlen=TIMEOUT_INTERVALS)
        if last is not None:
            gaps.append((t_s - last[0], t_s >= last[1]))  # an outage: the frame before had timed out by now
        usable = [g for g, outage in gaps if not outage] or [g for g, _ in gaps]
        period = statistics.median(usable) if usable else 0.0
        expires = t_s + min(max(self.timeout_s, TIMEOUT_PERIODS * period), MAX_TIMEOUTS * self.timeout_s)
        self._cameras[camera] = (t_s, expires, gaps)
        self._sent.add(camera)
        return expires

    def expires_s(self, camera: str) -> float:
        """When the newest frame recorded of ``camera`` times out (inf: never, or none recorded)."""
        last = self._cameras.get(camera)
        return math.inf if last is None else last[1]

    def out(self, cameras, now_s: float) -> list[str]:
        """Those of ``cameras`` whose newest frame has timed out at ``now_s``."""
        return [c for c in cameras if now_s >= self.expires_s(c)]

    def check(self, cameras, now_s: float) -> tuple[list[str], list[str]]:
        """``out(cameras, now_s)``, and of those the ones that sent a frame since the last check: a camera timed out
        while sending has its frames stamped further behind ``now_s`` than the timeout (a clock not synchronised with
        the one ``now_s`` is read on?). For a feeder that checks at each cloud against the cloud's stamp."""
        out = self.out(cameras, now_s)
        lagging = [c for c in out if c in self._sent]
        self._sent.clear()
        return out, lagging
