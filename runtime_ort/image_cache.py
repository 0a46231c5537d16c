"""The detector's cached image BEV, one state per quadrant, and the checks of what an image update names
(its quadrants, its cameras' timestamps).

The cache is never changed in place: every install or re-lift swaps in a new `ImageCache` under the detector's
lock, so a slice that took a reference reads one consistent image BEV while the image lane goes on."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from streamdet.calibration.lut import Lut
from streamdet.core.json_input import is_finite_number, short_repr
from streamdet.core.sectors import NUM_QUADRANTS, check_quadrants

ALL_QUADRANTS: tuple[int, ...] = tuple(range(NUM_QUADRANTS))


@dataclass(frozen=True)
class QuadrantState:
    """The cached image BEV of one quadrant and what it was lifted from."""

    bev: np.ndarray  # (1, C, Yq, Xq) float32, or the image half (1, C0, Yh, Xh) (the manifest's image_layout)
    # (J', C, Hf, Wf) float32 feature maps of ``feature_cameras`` (zeros for a camera not given), kept to re-lift
    # when the calibration changes; a full update's quadrants share one array of every camera
    features: np.ndarray
    feature_cameras: tuple[str, ...]
    timestamp: float
    cameras_missing: tuple[str, ...]
    seq: int = 0  # the update_images call that made it (call order: a larger seq is a newer image set)
    lut: Lut | None = None  # the LUT the bev was lifted with
    # the update's camera_timestamps (sorted pairs; empty: none given) and its timestamp, kept to stamp the quadrant
    # again when a calibration swap re-lifts it with other cameras (quadrant_timestamp)
    camera_timestamps: tuple[tuple[str, float], ...] = ()
    update_timestamp: float | None = None


@dataclass(frozen=True, eq=False)
class ImageCache:
    """The cached image BEV: one state per quadrant (None: no image there yet). Never changed in place: every
    install or re-lift swaps in a new cache, so ``cache is before`` tells whether anything changed."""

    quadrants: tuple[QuadrantState | None, ...]  # quadrants 0..3

    @property
    def bev(self) -> np.ndarray:
        """(4, C, Yq, Xq) float32 of every quadrant (a copy; a quadrant without images is zeros here, where the
        detector's slices read its camera-less BEV, StreamingDetector.blank_image_bev)."""
        some = next(s for s in self.quadrants if s is not None)
        return np.concatenate([np.zeros_like(some.bev) if s is None else s.bev for s in self.quadrants])

    @property
    def newest(self) -> QuadrantState:
        """The quadrant state of the newest image set cached."""
        return max((s for s in self.quadrants if s is not None), key=lambda s: s.seq)

    @property
    def features(self) -> np.ndarray:
        return self.newest.features  # a full update's quadrants share it

    @property
    def seq(self) -> int:
        return self.newest.seq

    @property
    def timestamp(self) -> float:
        """The oldest quadrant's timestamp."""
        return min(s.timestamp for s in self.quadrants if s is not None)

    @property
    def lut(self) -> Lut | None:
        """The LUT every cached quadrant was lifted with; None while they differ."""
        luts = {id(s.lut): s.lut for s in self.quadrants if s is not None}
        return next(iter(luts.values())) if len(luts) == 1 else None


def check_camera_timestamps(stamps: Mapping[str, float] | None, images: Mapping[str, np.ndarray]) -> dict[str, float]:
    """{camera: finite seconds} for cameras among ``images``; ValueError naming the bad entry."""
    if stamps is None:
        return {}
    if not isinstance(stamps, Mapping):
        raise ValueError(f"camera_timestamps must be None or a dict of camera name -> seconds, got {type(stamps).__name__}")
    out = {}
    for name, value in stamps.items():
        if name not in images:
            raise ValueError(f"camera_timestamps names camera {name!r}, whose image this update was not given")
        if not is_finite_number(value):  # no OverflowError for 10**400
            raise ValueError(f"camera_timestamps[{name!r}] must be a finite number of seconds, got {short_repr(value)}")
        out[name] = float(value)
    return out


def quadrant_timestamp(lut_cameras: Sequence[str], camera_timestamps: Mapping[str, float], feature_cameras: Sequence[str],
                       timestamp: float) -> float:  # fmt: skip
    """A lifted quadrant's timestamp: the oldest capture time among the cameras its LUT reads (``lut_cameras``) whose
    features the lift had (``feature_cameras``) and whose time was given; ``timestamp`` (the update's) without any."""
    seen = [camera_timestamps[n] for n in lut_cameras if n in camera_timestamps and n in feature_cameras]
    return min(seen) if seen else timestamp


def quadrant_states(cache: ImageCache | None) -> tuple[QuadrantState | None, ...]:
    return (None,) * NUM_QUADRANTS if cache is None else cache.quadrants


def update_quadrants(quadrants: Sequence[int] | None) -> tuple[int, ...]:
    """The quadrants of an image update: None is all four; else a non-empty strictly increasing list of 0..3."""
    return ALL_QUADRANTS if quadrants is None else check_quadrants(quadrants)


def select_maps(features: np.ndarray, cameras: tuple[str, ...], wanted: tuple[str, ...]) -> np.ndarray:
    """The (max(1, len(wanted)), C, Hf, Wf) maps of ``wanted`` out of ``features`` of ``cameras``; zeros for the absent."""
    if cameras == wanted:
        return features
    out = np.zeros((max(1, len(wanted)), *features.shape[1:]), dtype=np.float32)
    for i, name in enumerate(wanted):
        if name in cameras:
            out[i] = features[cameras.index(name)]
    return out
