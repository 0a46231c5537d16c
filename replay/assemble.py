"""Whole image sets from cameras that fire one after the other, for an image lane that updates from every camera.

Under the ``lidar-synced`` trigger model (``triggers.py``) each camera's frame arrives on its own, as the LiDAR
crosses its axis. The ``full`` image-lane schedule (and the full-sweep and sequential modes) encode every camera
and lift all four quadrants per update, as they do for simultaneous triggers; handing them every single frame
would run that whole update six times per camera period. The player batches instead, the way a vehicle's driver
collects a camera cycle: a set is handed over the moment every camera has delivered a frame newer than the ones of
the last set handed over (when the cycle's last camera fires), holding the newest frame of every camera, each with
its own capture time (so each quadrant of the update is as old as its own cameras' frames,
``StreamingDetector.update_images(camera_timestamps=)``). That is one full update per camera period, the work
the ``full`` schedule does under simultaneous triggers. With simultaneous triggers every set is whole and is
handed over at once, unchanged.

A camera that stops (``streamdet-replay --camera-outage``) would hold every later set back: with ``timeout_s`` a
camera silent that long in drive time (the rule of core/camera_timeout.py; one never heard from counts from the
first frame offered) is left out, and the sets are made of the others, as a vehicle's driver collecting camera
cycles would do. Without it (None) the sets wait for every camera.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from streamdet.core.camera_timeout import CameraTimeout


@dataclass(frozen=True, eq=False)
class AssembledSet:
    images: dict[str, np.ndarray]  # the newest frame of every camera
    timestamp: float  # the oldest frame's capture time (the set's label: a capture time of the drive)
    camera_timestamps: dict[str, float] | None  # each frame's capture time; None when they are all ``timestamp``


class SetAssembler:
    """Collects per-camera frames; ``offer`` returns a whole set when every camera has a newer frame."""

    def __init__(self, cameras: Sequence[str], timeout_s: float | None = None) -> None:
        if not cameras:
            raise ValueError("SetAssembler needs at least one camera name")
        self.cameras = tuple(dict.fromkeys(cameras))
        self._newest: dict[str, tuple[np.ndarray, float]] = {}
        self._fresh: set[str] = set()  # cameras with a frame newer than the last set handed over
        self._timeout = CameraTimeout(timeout_s, "SetAssembler timeout_s")
        self._start_s: float | None = None  # the first frame's capture time

    def offer(self, images: Mapping[str, np.ndarray], capture_s: float) -> AssembledSet | None:
        unknown = [n for n in images if n not in self.cameras]
        if unknown:
            raise ValueError(f"SetAssembler: unknown cameras {unknown}; it collects {list(self.cameras)}")
        for name, image in images.items():
            self._newest[name] = (image, float(capture_s))
            self._fresh.add(name)
            self._timeout.seen(name, float(capture_s))
        if self._start_s is None:
            self._start_s = float(capture_s)
        live = [n for n in self.cameras if not self._out(n, float(capture_s))]
        if not live or any(n not in self._fresh for n in live):
            return None
        self._fresh.clear()
        stamps = {n: self._newest[n][1] for n in live}
        oldest = min(stamps.values())
        same = all(t == oldest for t in stamps.values())
        return AssembledSet({n: self._newest[n][0] for n in live}, oldest, None if same else stamps)

    def _out(self, camera: str, now_s: float) -> bool:
        """Whether ``camera`` has been silent for the timeout at ``now_s`` (never, without one)."""
        if self._timeout.timeout_s is None:
            return False
        if camera in self._newest:
            return now_s >= self._timeout.expires_s(camera)
        return now_s >= self._start_s + self._timeout.timeout_s
