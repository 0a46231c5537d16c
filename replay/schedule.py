"""When the player hands each piece of data to the detector: the release schedule of a drive.

A slice is released the moment its last point has been scanned: the rotation start plus the latest firing time
of its points (the data's per-point times; without them the azimuth's fraction of the rotation, the sensor turning
as the scan layout says: ``start_deg``, ``clockwise``, ``core/sectors.py``). An empty slice is released when the
sensor leaves its sector. A full sweep (``num_slices`` 1) is released when the rotation ends. Image sets are
released at their capture time plus a fixed delivery delay (``camera_delivery_s``, default 0: exposure, readout,
transfer and decoding not modelled); their timestamp stays the capture time, as a camera driver stamps it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.core.sectors import slice_index_of
from streamdet.core.slicing import relative_time_s, split_sweep
from streamdet.replay.source import Drive, ImageSet, LidarSweep

SLICE, IMAGES = "slice", "images"


@dataclass(frozen=True, eq=False)
class TimedSlice:
    sweep: int  # LidarSweep.index
    slice_index: int
    num_slices: int
    scan_end_s: float  # drive time its last point was scanned = its release
    points: np.ndarray  # (N, 6) float32 slice layout (x, y, z, r, t, s)


@dataclass(frozen=True, eq=False)
class Release:
    """One thing the player hands over at ``time_s``: a slice or an image set."""

    time_s: float
    kind: str  # SLICE | IMAGES
    item: TimedSlice | ImageSet


# Bounds of the replay's rates and times, for the library and its CLI alike: far past any real rig, short of a value
# that allocates gigabytes of triggers or overflows a clock.
MIN_RATE_HZ = 0.1  # a rotation or trigger every 10 s (1e-300 Hz asked numpy for an array of 1e300 trigger times)
MAX_RATE_HZ = 1000.0  # LiDAR rotations or camera triggers per second
MAX_DELIVERY_S = 10.0  # a camera frame 10 s late is no camera
MIN_TIME_SCALE = 0.01  # a drive second played in 10 wall ms (1e-300 reported latencies of 1e296 ms as a result)
MAX_TIME_SCALE = 1000.0  # a drive second played over 1000 wall seconds


def check_rate(value: float, name: str) -> float:
    """LiDAR rotations or camera triggers per second (``name``): a number in MIN_RATE_HZ..MAX_RATE_HZ."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and MIN_RATE_HZ <= value <= MAX_RATE_HZ):
        raise ValueError(f"{name} must be a rate in {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz, got {value!r}")
    return float(value)


def check_delivery(value: float, name: str = "camera delivery delay", unit: str = "seconds") -> float:
    """A camera delivery delay (``name``, in ``unit``: "seconds" or "ms"): a finite number in 0..MAX_DELIVERY_S."""
    top = MAX_DELIVERY_S * (1e3 if unit == "ms" else 1.0)
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0 <= value <= top):
        raise ValueError(f"{name} must be a number of {unit} in 0..{top:g}, got {value!r}")
    return float(value)


def check_time_scale(value: float, name: str = "time scale") -> float:
    """Wall seconds per drive second: a number in MIN_TIME_SCALE..MAX_TIME_SCALE."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and MIN_TIME_SCALE <= value <= MAX_TIME_SCALE):
        raise ValueError(f"{name} must be a number in {MIN_TIME_SCALE:g}..{MAX_TIME_SCALE:g}, got {value!r}")
    return float(value)


def slice_sweep(sweep: LidarSweep, num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> list[TimedSlice]:
    """The sweep's slices in scan order (the layout ``start_deg``, ``clockwise``) with their release times.

    Non-finite points (a NaN / inf coordinate, intensity or per-point time) are handled as streamdet-eval handles
    them, so that the replay's offline and streaming scores stay comparable with eval's on the same files: a point
    with a finite azimuth goes into its slice like any other, and the detector drops and counts it
    (``SliceResult.num_nonfinite_dropped``); a point whose x or y is NaN has no azimuth, hence no slice, and is in
    none (``split_sweep``, eval's too). None of them times a release (`LidarSweep.timing_rows`): a
    slice whose points all lack a finite time is released when the sensor leaves its sector, as an empty one is.
    A NaN time is no firing time, and a clipped inf would release its slice at the rotation's end.
    """
    period = sweep.duration_s
    points = np.asarray(sweep.points)
    slices = split_sweep(points, num_slices, start_deg, sweep_duration_s=period, clockwise=clockwise)
    timed = sweep.timing_rows()
    every = bool(timed.all())
    pts = points if every else points[timed]
    if sweep.point_time_s is not None:
        times = np.asarray(sweep.point_time_s, dtype=np.float64)
        times = times if every else times[timed]
    else:
        times = relative_time_s(pts, start_deg, period, clockwise)
    k_of_point = slice_index_of(pts[:, 0], pts[:, 1], num_slices, start_deg, clockwise)
    latest = np.full(num_slices, -np.inf)
    np.maximum.at(latest, k_of_point, times)
    sector_end = period * (np.arange(num_slices) + 1) / num_slices  # where the sensor leaves each sector
    if num_slices == 1:
        latest[:] = period  # the whole rotation, whatever the points say
    release = np.where(np.isfinite(latest), np.minimum(latest, period), sector_end)
    return [TimedSlice(sweep.index, k, num_slices, sweep.start_s + float(release[k]), slices[k]) for k in range(num_slices)]


def release_schedule(
    drive: Drive, num_slices: int, start_deg: float = 0.0, images: bool = True, camera_delivery_s: float = 0.0,
    clockwise: bool = False,
) -> list[Release]:
    """Every release of the drive in time order; at equal times slices go before image sets. An image set is
    released ``camera_delivery_s`` after its capture (a real camera's exposure, readout and transport); it keeps its
    capture time as its timestamp."""
    check_delivery(camera_delivery_s)
    out = [Release(s.scan_end_s, SLICE, s) for sweep in drive.sweeps for s in slice_sweep(sweep, num_slices, start_deg, clockwise)]
    if images:
        out += [Release(s.capture_s + camera_delivery_s, IMAGES, s) for s in drive.image_sets]
    return sorted(out, key=lambda r: (r.time_s, r.kind != SLICE))
