"""``sensor_msgs/PointCloud2`` <-> the runtime's sweep (N, 5) and slices (N, 6), vectorised with numpy.

Reading builds one structured dtype from the message's ``fields`` (names, offsets, byte order) with the point
step as its item size, views the payload through it without copying, and copies only the columns the runtime
needs. So any field order, padding between fields or at the end of a point, row padding (``row_step`` greater
than ``width * point_step``), float32 / float64 / integer fields and either byte order cost the same.

Columns: ``x y z`` (metres, the cloud's frame), the intensity field (scaled into the 0..255 range nuScenes uses),
and the ring (``ring``, ``channel`` or ``line``; zeros when absent: the model does not read it). Points with a
non-finite coordinate (a non-dense cloud's NaN returns) are dropped whatever ``is_dense`` says.

Per-point time, under the names drivers use (``TIME_FIELD_NAMES``), in seconds after the header stamp (negative:
before it). ``time_unit="auto"`` takes integer fields as nanoseconds (Ouster ``t``) and float fields as seconds
(Velodyne ``time``), or nanoseconds when their magnitude exceeds 1e12 (an absolute nanosecond clock, Livox
``timestamp``); a time that is still above 1e6 s (~11 days) is absolute (Hesai ``timestamp``) and is made relative
to the header stamp. The unit and clock are judged from a typical (median) magnitude, so one corrupt time does
not turn a whole cloud's times into another unit. A point whose time is not finite, or lies further than
``CloudFields.max_time_offset_s`` from the header stamp, is dropped and counted (``Cloud.num_time_dropped``), as a
non-finite coordinate is: its time would otherwise become the scan time its slice is detected and published at.
When most of a cloud's timed points lie outside that window, the column is on another clock than the header (a
LiDAR on PTP in TAI with a UTC header: 37 s; GPS time: 18 s; a simulator's header stamp of 0) or in another unit, and
dropping them would blind the detector without a word: ``CloudClockError`` is raised instead, quoting the typical
offset. So is a float32 column holding an absolute clock: float32 resolves only minutes at today's epoch seconds, so
every point of a sweep would read the same, wrong, time. A node that does not need per-point times reads the cloud
with ``CloudFields(time=None)`` and never meets either.

Intensity is passed through as recorded (times ``intensity_scale``): a value outside 0..255, or one that overflows
float32 to inf, is left for the runtime's pillarize to drop and count with the other out-of-range reflectances.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from streamdet.core.json_input import is_finite_number
from streamdet.core.points import INTENSITY_SCALE, SWEEP_COLUMNS
from streamdet.core.sectors import check_num_slices, slice_index_of
from streamdet.core.slicing import feature_index, slice_features, split_sweep
from streamdet.runtime_ort.ros.header import (
    NS_PER_S,
    UINT8_MAX,
    RosMessageError,
    byte_view,
    header_frame_id,
    header_msg,
    header_stamp_ns,
    int_field,
    is_integer,
    shown,
)

# sensor_msgs/PointField datatypes -> numpy type codes (without byte order)
POINT_FIELD_TYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FLOAT32 = 7
UINT16 = 4
UINT16_MAX = 65535
TIME_FIELD_NAMES: tuple[str, ...] = ("t", "time", "timestamp", "time_stamp")  # Ouster, Velodyne, Hesai/Livox, others
RING_FIELD_NAMES: tuple[str, ...] = ("ring", "channel", "line")
TIME_UNITS_S: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ABSOLUTE_TIME_S = 1e6  # a per-point time above this many seconds is a clock reading, not an offset
NANOSECOND_CLOCK = 1e12  # a float time above this is nanoseconds
# How far (s, either side) a point's time may lie from its cloud's header stamp. Drivers stamp a cloud at the start
# or end of its sweep, so its points lie within one sweep period (0.05-0.2 s at 20-5 Hz); frames integrated for
# longer (a Livox at a low publish rate) or clocks in whole seconds reach a few seconds. A time beyond this is a
# corrupt value or another clock, and would move its slice's scan time (the detector's clock, and the stamp the
# detections are published with; a ROS stamp holds only int32 seconds) by as much: such points are dropped.
MAX_POINT_TIME_OFFSET_S = 5.0
TIME_SAMPLE = 4097  # values of a time column that decide its unit and clock (a strided sample: fast, and robust)
MSG = "sensor_msgs/PointCloud2"


class CloudClockError(RosMessageError):
    """A cloud's per-point time column cannot give the points' times after its header stamp: most of them lie further
    from the stamp than ``CloudFields.max_time_offset_s`` (another clock, or another unit), or it is a float32
    absolute clock. The message quotes the offset or the value and says what to set."""


@dataclass(frozen=True)
class CloudFields:
    """Which fields of a driver's cloud to read and how."""

    intensity: str = "intensity"  # the reflectance field
    intensity_scale: float = 1.0  # multiplies intensity into the 0..255 range of nuScenes (e.g. 255 for 0..1)
    time: str | None = "auto"  # per-point time field; "auto": the first of TIME_FIELD_NAMES; None: do not read one
    require_time: bool = True  # "auto" finding no time field is an error (False: the cloud is read without time)
    time_unit: str = "auto"  # "auto" | "s" | "ms" | "us" | "ns"
    ring: str | None = "auto"  # "auto": the first of RING_FIELD_NAMES, zeros if none; None: zeros
    max_time_offset_s: float = MAX_POINT_TIME_OFFSET_S  # points timed further from the header stamp are dropped

    def __post_init__(self) -> None:
        if self.time_unit != "auto" and self.time_unit not in TIME_UNITS_S:
            raise ValueError(f"CloudFields.time_unit must be 'auto' or one of {list(TIME_UNITS_S)}, got {self.time_unit!r}")
        if not (np.isfinite(self.intensity_scale) and self.intensity_scale > 0):
            raise ValueError(f"CloudFields.intensity_scale must be a positive number, got {self.intensity_scale!r}")
        if not (np.isfinite(self.max_time_offset_s) and self.max_time_offset_s > 0):
            raise ValueError(f"CloudFields.max_time_offset_s must be a positive number, got {self.max_time_offset_s!r}")


@dataclass(frozen=True, eq=False)
class Cloud:
    """One decoded cloud: the runtime's sweep layout plus per-point time."""

    stamp_ns: int  # header stamp
    frame_id: str
    points: np.ndarray  # (N, 5) float32 x, y, z, intensity (0..255), ring
    time_s: np.ndarray | None  # (N,) float64 seconds after the header stamp; None: the cloud has no time field
    num_dropped: int  # points removed for a non-finite coordinate
    num_time_dropped: int = 0  # points (with finite coordinates) removed for a non-finite or implausible time
    dropped_time_s: float | None = None  # the first such time (s after the stamp, as read): names the problem


@dataclass(frozen=True, eq=False)
class TimedSlice:
    """One slice for ``StreamingDetector.detect_slice``, with the time the sensor finished scanning it."""

    points: np.ndarray  # (N, 6) float32 x, y, z, reflectance (0..1), relative time (s), slice index
    index: int  # k of n, in scan order
    num_slices: int
    scan_time_ns: int  # cloud stamp + the latest point time of the slice (the stamp when times are unknown)
    cloud_stamp_ns: int
    frame_id: str


def decode_pointcloud2(msg: Any, fields: CloudFields = CloudFields()) -> Cloud:
    """A ``sensor_msgs/PointCloud2`` as the runtime's (N, 5) float32 sweep plus per-point time."""
    # uint32 fields: a negative size would reach np.ndarray's strides, None or inf int()'s TypeError / OverflowError
    height, width = int_field(msg.height, f"{MSG}.height"), int_field(msg.width, f"{MSG}.width")
    point_step, row_step = int_field(msg.point_step, f"{MSG}.point_step"), int_field(msg.row_step, f"{MSG}.row_step")
    stamp = header_stamp_ns(msg, MSG)  # a corrupt stamp is refused before any work
    frame_id = header_frame_id(msg, MSG)
    if not isinstance(msg.fields, (list, tuple)):
        kind = type(msg.fields).__name__
        raise RosMessageError(f"{MSG}.fields must be a list of sensor_msgs/PointField, got {kind} {shown(msg.fields)}")
    present = {f.name: f for f in msg.fields}
    if len(present) != len(msg.fields):  # which of two "x" fields is x? Refused rather than the last one taken
        names = [f.name for f in msg.fields]
        raise RosMessageError(f"PointCloud2 names a field twice: {sorted({n for n in names if names.count(n) > 1})} in {names}")
    names = {"x": "x", "y": "y", "z": "z", "intensity": fields.intensity}
    for role, name in names.items():
        if name not in present:
            raise RosMessageError(f"PointCloud2 has no {name!r} field ({role}); it has {list(present)}")
    time_name = _resolve(fields.time, TIME_FIELD_NAMES, present, "per-point time" if fields.require_time else None)
    ring_name = _resolve(fields.ring, RING_FIELD_NAMES, present, None)
    used = [("x", "x"), ("y", "y"), ("z", "z"), ("intensity", fields.intensity)]
    used += [("time", time_name)] if time_name else []
    used += [("ring", ring_name)] if ring_name else []
    if not isinstance(msg.is_bigendian, (bool, np.bool_)):  # the str 'false' is truthy: every value byte-swapped
        raise RosMessageError(f"{MSG}.is_bigendian must be a bool, got {shown(msg.is_bigendian)}")
    order = ">" if msg.is_bigendian else "<"
    dtype = _point_dtype(present, used, order, point_step)
    payload = byte_view(msg.data, f"{MSG}.data")
    num = height * width
    if num == 0:
        return _empty_cloud(frame_id, stamp, time_name is not None)
    if row_step < width * point_step:
        raise RosMessageError(f"PointCloud2 row_step {row_step} < width {width} x point_step {point_step}")
    need = (height - 1) * row_step + width * point_step
    if payload.size < need:
        raise RosMessageError(f"PointCloud2 data holds {payload.size} bytes; {height} rows of {width} points need {need}")
    # A strided view: rows row_step apart, points point_step apart; no copy until the columns below.
    grid = np.ndarray((height, width), dtype=dtype, buffer=payload, strides=(row_step, point_step))  # (H, W)

    def column(role: str) -> np.ndarray:
        return grid[role].reshape(num)  # (N,), a view when the rows are unpadded

    points = np.empty((num, SWEEP_COLUMNS), dtype=np.float32)
    # a float64 value beyond float32 (or an intensity scaled past it) becomes inf by design: a coordinate is then
    # dropped below, an intensity by pillarize's range check; the overflow warning would only be noise
    with np.errstate(over="ignore"):
        points[:, 0] = column("x")
        points[:, 1] = column("y")
        points[:, 2] = column("z")
        points[:, 3] = column("intensity")
        if fields.intensity_scale != 1.0:
            points[:, 3] *= np.float32(fields.intensity_scale)
    if ring_name:
        points[:, 4] = column("ring")
    else:
        points[:, 4] = 0.0
    time_s, unit = _times_s(column("time"), fields.time_unit, stamp, time_name) if time_name else (None, "")
    keep = np.isfinite(points[:, :3]).all(axis=1)
    dropped = num - int(np.count_nonzero(keep))
    time_dropped, bad_time = 0, None
    if time_s is not None:
        plausible = np.abs(time_s) <= fields.max_time_offset_s  # False for NaN
        bad = keep & ~plausible
        time_dropped = int(np.count_nonzero(bad))
        if time_dropped:
            _check_clock(time_s, keep, plausible, fields, time_name, unit, stamp, frame_id)
            bad_time = float(time_s[np.argmax(bad)])
            keep &= plausible
    if dropped or time_dropped:
        points = points[keep]
        time_s = time_s[keep] if time_s is not None else None
    return Cloud(stamp, frame_id, points, time_s, dropped, time_dropped, bad_time)


def split_cloud(cloud: Cloud, num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> list[TimedSlice]:
    """A full-sweep cloud cut into the runtime's ``num_slices`` slices by azimuth (``split_sweep``; ``start_deg``,
    ``clockwise``: the sensor's scan layout, ``DetectorConfig``'s), each stamped with its scan time from the
    per-point times."""
    check_num_slices(num_slices, start_deg)
    parts = split_sweep(cloud.points, num_slices, start_deg, clockwise=clockwise)
    if cloud.time_s is None:
        return [TimedSlice(p, k, num_slices, cloud.stamp_ns, cloud.stamp_ns, cloud.frame_id) for k, p in enumerate(parts)]
    k_of_point = slice_index_of(cloud.points[:, 0], cloud.points[:, 1], num_slices, start_deg, clockwise)
    latest = np.full(num_slices, -np.inf)
    np.maximum.at(latest, k_of_point, cloud.time_s)
    return [
        TimedSlice(p, k, num_slices, _scan_time_ns(cloud.stamp_ns, latest[k]), cloud.stamp_ns, cloud.frame_id)
        for k, p in enumerate(parts)
    ]


def slice_from_message(
    cloud: Cloud, num_slices: int, start_deg: float = 0.0, index: int | None = None, sweep_duration_s: float = 0.05,
    clockwise: bool = False,
) -> TimedSlice:
    """One message that already holds one slice (a driver publishing partial scans) as a runtime slice.

    ``index`` None: the sector holding most of the points. Every point of the message is kept, also those a few
    columns over the sector border (with the slice's own index feature): the slice graph crops to the sector's
    quadrants itself. ``start_deg``, ``clockwise``: the sensor's scan layout (``DetectorConfig``'s).
    """
    check_num_slices(num_slices, start_deg)
    # a NaN, infinite or non-positive duration makes every point's time column NaN, inf or negative, and pillarize
    # then drops the whole slice: refused here, where the cause is still the argument
    if not (is_finite_number(sweep_duration_s) and sweep_duration_s > 0):
        raise ValueError(
            f"slice_from_message: sweep_duration_s must be a finite number of seconds > 0, got {shown(sweep_duration_s)}"
        )
    if index is not None and not (is_integer(index) and 0 <= index < num_slices):  # True is not slice 1
        raise ValueError(f"slice_from_message: slice index must be in 0..{num_slices - 1} (an integer), got {shown(index)}")
    pts = cloud.points
    k_of_point = slice_index_of(pts[:, 0], pts[:, 1], num_slices, start_deg, clockwise)
    if index is None:
        if len(pts) == 0:
            raise RosMessageError("slice_from_message: an empty cloud names no sector; pass index")
        index = int(np.bincount(k_of_point, minlength=num_slices).argmax())
    out = np.empty((len(pts), SWEEP_COLUMNS + 1), dtype=np.float32)  # (N, 6)
    out[:, :3] = pts[:, :3]
    out[:, 3] = pts[:, 3] / INTENSITY_SCALE
    out[:, 4] = slice_features(pts, num_slices, sweep_duration_s)[0]  # as split_sweep's, whatever the layout
    out[:, 5] = feature_index(int(index), num_slices, start_deg, clockwise)
    latest = float(cloud.time_s.max()) if cloud.time_s is not None and len(pts) else -np.inf
    return TimedSlice(out, int(index), num_slices, _scan_time_ns(cloud.stamp_ns, latest), cloud.stamp_ns, cloud.frame_id)


def pointcloud2_message(
    points: np.ndarray, stamp_ns: int, frame_id: str, time_s: np.ndarray | None = None
) -> dict:
    """A little-endian dense ``sensor_msgs/PointCloud2`` dict of a (N, 5) sweep (x, y, z, intensity, ring), with
    a float32 ``time`` field (seconds after the stamp, Velodyne's convention) when ``time_s`` is given.

    The layout of the Velodyne and Ouster drivers' clouds: float32 x, y, z, intensity at 0, 4, 8, 12, ``ring`` a
    uint16 at 16 (consumers such as a ring outlier filter read it so), ``time`` at 20; 24 bytes a point (20 without
    time). The ring column must hold whole numbers in 0..65535 (ValueError otherwise)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != SWEEP_COLUMNS:
        raise ValueError(f"points must be (N, {SWEEP_COLUMNS}) x, y, z, intensity, ring; got shape {points.shape}")
    ring = points[:, 4]
    bad = ~(np.isfinite(ring) & (ring == np.round(ring)) & (ring >= 0) & (ring <= UINT16_MAX))
    if bad.any():
        raise ValueError(f"points' ring column must hold whole numbers in 0..{UINT16_MAX} (a uint16 field), got "
                         f"{ring[bad][0]!r} at row {int(np.flatnonzero(bad)[0])}")  # fmt: skip
    names = ["x", "y", "z", "intensity", "ring"] + (["time"] if time_s is not None else [])
    formats = ["<f4", "<f4", "<f4", "<f4", "<u2"] + (["<f4"] if time_s is not None else [])
    offsets = [0, 4, 8, 12, 16] + ([20] if time_s is not None else [])
    step = 24 if time_s is not None else 20  # 4-byte aligned: two bytes of padding after the ring
    rec = np.zeros(len(points), dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step}))
    for j, name in enumerate(names[:SWEEP_COLUMNS]):
        rec[name] = points[:, j]
    if time_s is not None:
        time_s = np.asarray(time_s)
        if time_s.shape != (len(points),):
            raise ValueError(f"time_s must be ({len(points)},), got shape {time_s.shape}")
        rec["time"] = time_s
    types = {"<f4": FLOAT32, "<u2": UINT16}
    return {
        "header": header_msg(stamp_ns, frame_id),
        "height": 1,
        "width": len(points),
        "fields": [{"name": n, "offset": o, "datatype": types[f], "count": 1} for n, f, o in zip(names, formats, offsets)],
        "is_bigendian": False,
        "point_step": step,
        "row_step": step * len(points),
        "data": rec.tobytes(),
        "is_dense": bool(np.isfinite(points[:, :3]).all()),
    }


# ---- internals ---------------------------------------------------------------------------------------------


def _resolve(wanted: str | None, candidates: Sequence[str], present: dict, required_as: str | None) -> str | None:
    """The field name to read: ``wanted``, or the first candidate present when ``wanted`` is "auto"."""
    if wanted is None:
        return None
    if wanted != "auto":
        if wanted not in present:
            raise RosMessageError(f"PointCloud2 has no {wanted!r} field; it has {list(present)}")
        return wanted
    for name in candidates:
        if name in present:
            return name
    if required_as is not None:
        raise RosMessageError(
            f"PointCloud2 has no {required_as} field (looked for {list(candidates)}); it has {list(present)}; "
            "name it with CloudFields(time=...) or read the cloud without time (CloudFields(require_time=False))"
        )
    return None


def _point_dtype(present: dict, used: list[tuple[str, str]], order: str, point_step: int) -> np.dtype:
    names, formats, offsets = [], [], []
    for role, name in used:
        field = present[name]
        where = f"{MSG} field {name!r}"
        datatype, count = int_field(field.datatype, f"{where} datatype", 0, UINT8_MAX), int_field(field.count, f"{where} count")
        offset = int_field(field.offset, f"{where} offset")
        if datatype not in POINT_FIELD_TYPES:
            raise RosMessageError(f"PointCloud2 field {name!r} has unknown datatype {datatype} (sensor_msgs/PointField 1..8)")
        if count != 1:
            raise RosMessageError(f"PointCloud2 field {name!r} has count {count}; streamdet reads scalar fields (count 1)")
        code = np.dtype(order + POINT_FIELD_TYPES[datatype])
        if offset + code.itemsize > point_step:
            raise RosMessageError(f"PointCloud2 field {name!r} at offset {offset} ({code}) does not fit point_step {point_step}")
        names.append(role)
        formats.append(code)
        offsets.append(offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def _times_s(raw: np.ndarray, unit: str, stamp: int, name: str) -> tuple[np.ndarray, str]:
    """The column in seconds after the header stamp, and the unit it was read in."""
    integer = np.issubdtype(raw.dtype, np.integer)
    magnitude = _typical_magnitude(raw)  # decides the unit and whether the column is a clock
    if unit == "auto":
        unit = "ns" if integer or magnitude > NANOSECOND_CLOCK else "s"
    absolute = magnitude * TIME_UNITS_S[unit] > ABSOLUTE_TIME_S
    if integer and absolute:
        # an absolute integer clock: subtract in integer nanoseconds, exact
        ns_per_unit = round(TIME_UNITS_S[unit] * NS_PER_S)
        return (raw.astype(np.int64) * np.int64(ns_per_unit) - np.int64(stamp)).astype(np.float64) * 1e-9, unit
    if absolute and raw.dtype.itemsize < 8:
        # float32 keeps 24 bits: past ~1e6 s its step is a good part of a sweep, at epoch seconds it is minutes, so
        # every point would read one time, off by up to half a step, and still pass the window check
        step_s = float(np.spacing(np.float32(magnitude))) * TIME_UNITS_S[unit]
        raise CloudClockError(
            f"{MSG} at stamp {stamp} ns: per-point time field {name!r} is {raw.dtype.newbyteorder('=')} holding an "
            f"absolute clock (typical value {magnitude:.10g}, read as {unit}), where float32 resolves only {step_s:g} s: "
            "the points' times are lost. Set CloudFields(time=None) where per-point times are not needed, have the driver "
            "publish times relative to the header stamp (or as float64 / integer ns), or name the column's unit with "
            "CloudFields(time_unit=...) if it is not seconds"
        )
    seconds = raw.astype(np.float64) * TIME_UNITS_S[unit]
    if absolute:
        seconds -= stamp / NS_PER_S
    return seconds, unit


def _check_clock(time_s: np.ndarray, keep: np.ndarray, plausible: np.ndarray, fields: CloudFields, name: str, unit: str,
                 stamp: int, frame_id: str) -> None:  # fmt: skip
    """CloudClockError when more than half of the points with a finite time (and coordinates) lie outside the window.

    A few such points are corrupt values, dropped and counted; most of them is a whole column on another clock or in
    another unit, and dropping them would leave an empty or gutted cloud that detects nothing, silently."""
    timed = keep & np.isfinite(time_s)
    off = timed & ~plausible
    num_off, num_timed = int(np.count_nonzero(off)), int(np.count_nonzero(timed))
    if 2 * num_off <= num_timed:
        return
    typical = float(np.median(time_s[off]))
    how = " (time_unit 'auto')" if fields.time_unit == "auto" else ""
    raise CloudClockError(
        f"{MSG} at stamp {stamp} ns in {frame_id!r}: {num_off} of {num_timed} timed points have a per-point time (field "
        f"{name!r}, read as {unit}{how}) more than {fields.max_time_offset_s:g} s from the header stamp, typically "
        f"{typical:+.6g} s: the LiDAR's clock is not the header's (TAI runs 37 s ahead of UTC, GPS time 18 s; a header "
        "stamp of 0), or the column is in another unit. Set CloudFields(time=None) where per-point times are not needed, "
        "or fix the driver's clock, or name the unit with CloudFields(time_unit=...)"
    )


def _typical_magnitude(column: np.ndarray) -> float:
    """Median |value| of a strided sample of a column, non-finite values ignored; 0 for an empty or all-NaN one.

    The median, not the largest value: one corrupt time (1e20 in a column of seconds after the stamp) must not make
    the whole column read as an absolute nanosecond clock; that point alone is then dropped as implausible.
    """
    sample = column[:: max(1, -(-column.size // TIME_SAMPLE))].astype(np.float64)
    sample = np.abs(sample[np.isfinite(sample)])
    return float(np.median(sample)) if sample.size else 0.0


def _scan_time_ns(stamp_ns: int, latest_s: float) -> int:
    return int(stamp_ns) if not np.isfinite(latest_s) else int(stamp_ns) + int(round(latest_s * NS_PER_S))


def _empty_cloud(frame_id: str, stamp: int, has_time: bool) -> Cloud:
    return Cloud(stamp, frame_id, np.zeros((0, SWEEP_COLUMNS), np.float32),
                 np.zeros(0) if has_time else None, 0)  # fmt: skip
