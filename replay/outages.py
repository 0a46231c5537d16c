"""Camera outages in a replayed drive: a camera that sends nothing for a while (a cable, a crashed driver), to see
what the runtime does with it (``streamdet-replay --camera-outage CAM@START-END``).

An outage removes the camera's frames captured in ``[start_s, end_s)`` of drive time from the drive's image sets
(a set left with no frame is dropped). Under either schedule the camera's last frame counts until
``LaneConfig.camera_timeout_s`` (the phase-locked lane keeps it; under ``full`` the camera sets wait for the camera
that long, assemble.py); then its features are zeros.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Sequence

from streamdet.replay.source import Drive

_SPEC = re.compile(r"^(?P<camera>[A-Za-z0-9_]+)@(?P<start>[^-]+)-(?P<end>[^-]*)$")


@dataclass(frozen=True)
class CameraOutage:
    camera: str
    start_s: float  # drive seconds, from the drive's start
    end_s: float = math.inf  # exclusive; inf: to the end of the drive

    def __post_init__(self) -> None:
        if not isinstance(self.camera, str) or not self.camera:
            raise ValueError(f"a camera outage names a camera, got {self.camera!r}")
        for name in ("start_s", "end_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v) or v < 0:
                raise ValueError(f"camera outage of {self.camera}: {name} must be a number of seconds >= 0, got {v!r}")
        if math.isinf(self.start_s) or not self.end_s > self.start_s:
            raise ValueError(f"camera outage of {self.camera}: it must end after it starts, got {self.start_s:g}-{self.end_s:g} s")

    @classmethod
    def parse(cls, spec: str) -> "CameraOutage":
        """``CAM@START-END`` in drive seconds, END empty for the rest of the drive: ``CAM_FRONT@3-8``, ``CAM_BACK@5-``."""
        m = _SPEC.match(spec.strip())
        if m is None:
            raise ValueError(f"a camera outage is CAM@START-END in drive seconds (END empty: to the end), got {spec!r}")
        try:
            start = float(m["start"])
            end = float(m["end"]) if m["end"] else math.inf
        except ValueError:
            raise ValueError(f"a camera outage is CAM@START-END in drive seconds (END empty: to the end), got {spec!r}") from None
        return cls(m["camera"], start, end)

    def __str__(self) -> str:
        return f"{self.camera}@{self.start_s:g}-{'' if math.isinf(self.end_s) else f'{self.end_s:g}'}"


def check_outage_cameras(outages: Sequence[CameraOutage], camera_names: Sequence[str]) -> None:
    """ValueError naming an outage's camera that the export does not have."""
    unknown = sorted({o.camera for o in outages} - set(camera_names))
    if unknown:
        raise ValueError(f"--camera-outage names {unknown}, not cameras of this export ({list(camera_names)})")


def apply_outages(drive: Drive, outages: Sequence[CameraOutage]) -> Drive:
    """``drive`` without the frames the outages remove; the drive itself where there are none."""
    if not outages:
        return drive
    sets = []
    removed = [0] * len(outages)  # frames each outage took out
    for image_set in drive.image_sets:
        hits = [i for i, o in enumerate(outages) if o.start_s <= image_set.capture_s < o.end_s and o.camera in image_set.images]
        for i in hits:
            removed[i] += 1
        out = {outages[i].camera for i in hits}
        images = {name: image for name, image in image_set.images.items() if name not in out}
        if images:
            sets.append(image_set if len(images) == len(image_set.images) else dataclasses.replace(image_set, images=images))
    # an outage that took out nothing (past the drive's end, or over a stretch without frames) is said, not silent
    last = max((image_set.capture_s for image_set in drive.image_sets), default=0.0)
    parts = [f"{o} ({n} frames)" if n else f"{o} (no frame in it; the drive's images end at {last:.2f} s)"
             for o, n in zip(outages, removed)]  # fmt: skip
    note = "camera outages: " + ", ".join(parts)
    return dataclasses.replace(drive, image_sets=tuple(sets), notes=(*drive.notes, note))
