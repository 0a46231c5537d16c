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
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class AssembledSet:
    images: dict[str, np.ndarray]  # the newest frame of every camera
    timestamp: float  # the oldest frame's capture time (the set's label: a capture time of the drive)
    camera_timestamps: dict[str, float] | None  # each frame's capture time; None when they are all ``timestamp``


class SetAssembler:
    """Collects per-camera frames; ``offer`` returns a whole set when every camera has a newer frame."""

    def __init__(self, cameras: Sequence[str]) -> None:
        if not cameras:
            raise ValueError("SetAssembler needs at least one camera name")
        self.cameras = tuple(dict.fromkeys(cameras))
        self._newest: dict[str, tuple[np.ndarray, float]] = {}
        self._fresh: set[str] = set()  # cameras with a frame newer than the last set handed over

    def offer(self, images: Mapping[str, np.ndarray], capture_s: float) -> AssembledSet | None:
        unknown = [n for n in images if n not in self.cameras]
        if unknown:
            raise ValueError(f"SetAssembler: unknown cameras {unknown}; it collects {list(self.cameras)}")
        for name, image in images.items():
            self._newest[name] = (image, float(capture_s))
            self._fresh.add(name)
        if len(self._fresh) < len(self.cameras):
            return None
        self._fresh.clear()
        stamps = {n: self._newest[n][1] for n in self.cameras}
        oldest = min(stamps.values())
        same = all(t == oldest for t in stamps.values())
        return AssembledSet({n: self._newest[n][0] for n in self.cameras}, oldest, None if same else stamps)
