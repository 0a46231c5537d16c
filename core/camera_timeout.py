"""When a camera that stopped sending counts as out: one rule for every feeder that keeps each camera's newest frame
(the phase-locked image lane, ``streamdet-bag run``, the ROS 2 node example), so that a dead camera's last frame is
not fused on for as long as it stays out.

A camera is out once it has sent no frame for ``timeout_s``, or for ``TIMEOUT_PERIODS`` of its own frame period
where that is longer (the median of its last ``TIMEOUT_INTERVALS`` frame intervals, known from its second frame on):
a camera whose frame period is over a third of the timeout is not timed out between two of its frames. The times are the
caller's: the runner's clock for the lane, the messages' header stamps for a bag or a ROS node.
"""

from __future__ import annotations

import collections
import math
import numbers
import statistics

TIMEOUT_PERIODS = 3.0
TIMEOUT_INTERVALS = 5
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
    """Each camera's frame times, and when its newest frame times out. Not thread-safe: its owner's lock guards it."""

    def __init__(self, timeout_s: float | None, what: str = "camera_timeout_s") -> None:
        self.timeout_s = check_camera_timeout(timeout_s, what)  # None: never
        self._times: dict[str, collections.deque] = {}

    def seen(self, camera: str, t_s: float) -> float:
        """Record a frame of ``camera`` at ``t_s``; when it times out unless a newer one comes (inf: never)."""
        if self.timeout_s is None:
            return math.inf
        times = self._times.setdefault(camera, collections.deque(maxlen=TIMEOUT_INTERVALS + 1))
        times.append(t_s)
        return self.expires_s(camera)

    def expires_s(self, camera: str) -> float:
        """When the newest frame recorded of ``camera`` times out (inf: never, or none recorded)."""
        times = self._times.get(camera)
        if self.timeout_s is None or not times:
            return math.inf
        ordered = list(times)
        gaps = [b - a for a, b in zip(ordered, ordered[1:])]
        period = statistics.median(gaps) if gaps else 0.0
        return ordered[-1] + max(self.timeout_s, TIMEOUT_PERIODS * period)

    def out(self, cameras, now_s: float) -> list[str]:
        """Those of ``cameras`` whose newest frame has timed out at ``now_s``."""
        return [c for c in cameras if now_s >= self.expires_s(c)]
