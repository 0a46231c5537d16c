"""What the detector's calls return: `ImageUpdate` (an image-lane update), `SliceResult` (one slice's detections
and where they came from) and `SweepResult` (a whole sweep, slice by slice)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.runtime_ort.postprocess import Detections


@dataclass(frozen=True)
class ImageUpdate:
    """What one `update_images` call did."""

    timestamp: float
    cameras_used: tuple[str, ...]
    cameras_missing: tuple[str, ...]  # their features were zeros in this update
    # True when a newer image set (an update_images call that started later) was installed first in every quadrant
    # this one lifted: it was encoded but replaced nothing (an older set never overwrites a newer one); also when the
    # set was dropped while it lifted (forget_images, set_calibration(relift=False)) or the calibration was swapped
    # more than detector.MAX_RELIFTS_PER_UPDATE times during it
    superseded: bool = False
    quadrants: tuple[int, ...] = (0, 1, 2, 3)  # the quadrants of the image BEV this update lifted
    seq: int = 0  # the call's number (call order), as QuadrantState.seq; StreamingDetector.forget_images(through=seq)
    # the quadrants it dropped the image BEV of instead of lifting them, none of their cameras being given (their
    # slices then read the fallback or the camera-less BEV, as before the first image)
    cleared: tuple[int, ...] = ()


@dataclass(frozen=True)
class SliceResult:
    """The detections of one slice and where they came from."""

    detections: Detections  # LiDAR frame, after uncrop, threshold and per-class NMS
    slice_index: int
    num_slices: int
    timestamp: float
    # timestamp of the cached image BEV of the slice's quadrant(s), the oldest where it reads several (a quadrant
    # without images reads the camera-less BEV, StreamingDetector.blank_image_bev); None: none of them had images. With ``fallback`` the fused graph did not run:
    # it is the BEV that was too old (or missing) and its age says why
    image_timestamp: float | None
    num_points: int
    num_pillars: int
    num_nonfinite_dropped: int  # NaN / inf points removed before pillarising
    # finite points outside the grid range or outside the slice's quadrant(s) (e.g. another slice's points). Points
    # in the slice's quadrants but outside its sector are kept: the slice graph sees its quadrants whole.
    num_outside_dropped: int = 0
    num_points_dropped: int = 0  # points lost to the pillar caps (max_points_per_pillar, max_pillars)
    # rows of the slice graph's output (boxes) with a NaN or inf, dropped: a graph overflowing (logged once)
    num_nonfinite_outputs: int = 0
    # timestamp - image_timestamp: how old the images behind the quadrant(s) it read were at the slice's own
    # timestamp (both labels of the caller's clock); None without images. The oldest quadrant read counts.
    image_age_s: float | None = None
    # True: the LiDAR-only fallback's slice graph ran (DetectorConfig.fallback_export_dir), not the fused one
    fallback: bool = False
    # the slices detected together with this one in one slice-graph run (in scan order, this one included) when the
    # slice lane had fallen behind (LaneConfig.coalesce_slices, runtime_ort/coalesce.py); () for a run of its own
    coalesced: tuple[int, ...] = ()
    # cameras the slice's quadrant(s) read whose features were zeros: not given to the image update that made their
    # BEV (a camera out: missing from the image set under "full", silent for LaneConfig.camera_timeout_s under
    # "phase-locked"), and every camera of a quadrant without an image BEV because none of them had a frame (an
    # update given none of them, or all timed out); () when every camera they read was there, and for a quadrant
    # without images for another reason (none yet, forget_images). image_age_s does not show a camera missing from a
    # lifted quadrant: its age is that of the cameras that were given
    cameras_missing: tuple[str, ...] = ()
    # StreamingRunner's clock (time.monotonic()): when submit_slice took the slice, and when its result was made (before
    # its future completes and runs callbacks); None for the detector's own calls. latency_s is their difference
    submitted_s: float | None = None
    completed_s: float | None = None

    @property
    def latency_s(self) -> float | None:
        """Seconds from submit_slice to the result (queue wait, a pair hold, the run); None outside a runner."""
        if self.submitted_s is None or self.completed_s is None:
            return None
        return self.completed_s - self.submitted_s


@dataclass(frozen=True, eq=False)
class SweepResult:
    """What ``detect_sweep_slices`` did with one sweep."""

    detections: Detections  # every slice's detections merged with per-class NMS (what detect_sweep returns)
    slices: tuple[SliceResult, ...]  # in scan order
    points: tuple[np.ndarray, ...]  # (N_k, 6) float32 points of each slice
