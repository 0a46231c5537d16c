"""What every message adapter shares: ``builtin_interfaces/Time`` and ``std_msgs/Header`` (stamps as integer
nanoseconds, headers as dicts), ``uint8[]`` payloads as numpy views, and the checks of integer fields.

A malformed field is refused with a ``RosMessageError`` (a ValueError) naming the message, the field and the value:
a decoder (rclpy, mcap-ros2-support, rosbags) hands over Python or numpy integers, so anything else (None, a float, a
string, a value past the field's type) is a corrupt or hand-built message, never something to coerce."""

from __future__ import annotations

from typing import Any

import numpy as np

from streamdet.core.json_input import short_repr

NS_PER_S = 1_000_000_000
# builtin_interfaces/Time and Duration hold ``int32 sec``: a stamp outside this range cannot be encoded (CDR packs
# it with struct 'i'), so it is refused here with the value rather than as a struct.error deep in the writer
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
UINT8_MAX, UINT32_MAX = 2**8 - 1, 2**32 - 1


class RosMessageError(ValueError):
    """A ROS message the adapters cannot read or write: a malformed field, or a value its field cannot hold. Every
    adapter refuses a message with this class (or a subclass), so a node catches it per message, logs it and goes on,
    while an error of its own code (a TypeError, a wrong argument's plain ValueError) still stops it. A ValueError,
    so callers written against ``except ValueError`` keep working."""


def shown(value: Any) -> str:
    """``value`` for a one-line error: cut short (a 10**400, a long list) and on one line (numpy's array repr wraps)."""
    return " ".join(short_repr(value).split())


def is_integer(value: Any) -> bool:
    """A Python or numpy integer, not a bool (``True`` would read as 1)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def int_field(value: Any, what: str, low: int = 0, high: int = UINT32_MAX) -> int:
    """``value`` as an int when it is an integer in ``low..high`` (the field's ROS type); else a RosMessageError naming
    ``what`` (message type and field) and the value. ``int()`` would take 2.7, '3' and True, and raise TypeError,
    OverflowError or its own message for None, inf and nan."""
    if not (is_integer(value) and low <= value <= high):
        raise RosMessageError(f"{what} must be an integer in {low}..{high}, got {shown(value)}")
    return int(value)


def stamp_ns(stamp: Any, what: str = "builtin_interfaces/Time") -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (``int32 sec``, ``uint32 nanosec`` below 1e9).

    ``what`` names the stamp in an error (``"sensor_msgs/PointCloud2 header.stamp"``)."""
    try:
        sec, nanosec = stamp.sec, stamp.nanosec
    except AttributeError:
        raise RosMessageError(f"expected a builtin_interfaces/Time with sec and nanosec, got {type(stamp).__name__}") from None
    sec = int_field(sec, f"{what}.sec", INT32_MIN, INT32_MAX)
    nanosec = int_field(nanosec, f"{what}.nanosec", 0, NS_PER_S - 1)
    return sec * NS_PER_S + nanosec


def header_stamp_ns(msg: Any, message: str | None = None) -> int:
    """Integer nanoseconds of ``msg.header.stamp``; ``message`` (``"sensor_msgs/PointCloud2"``) names it in an error."""
    return stamp_ns(msg.header.stamp, f"{message} header.stamp" if message else "std_msgs/Header.stamp")


def time_msg(ns: int) -> dict:
    """A ``builtin_interfaces/Time`` dict of integer nanoseconds (negative times round toward minus infinity)."""
    if not is_integer(ns):  # int() would take 2.7 or '3' and raise its own errors for None and nan
        raise RosMessageError(f"a ROS 2 stamp is whole nanoseconds, got {shown(ns)}")
    sec, nanosec = divmod(int(ns), NS_PER_S)
    if not INT32_MIN <= sec <= INT32_MAX:
        raise RosMessageError(f"time {int(ns)} ns does not fit a ROS 2 stamp: {sec} s is outside int32 seconds")
    return {"sec": sec, "nanosec": nanosec}


def duration_msg(seconds: float) -> dict:
    """A ``builtin_interfaces/Duration`` dict of a non-negative number of seconds."""
    if not (is_integer(seconds) or isinstance(seconds, (float, np.floating))):  # '1' or None: TypeError below
        raise RosMessageError(f"a builtin_interfaces/Duration must be a number of seconds, got {shown(seconds)}")
    if not seconds >= 0:
        raise RosMessageError(f"a duration must be >= 0 s, got {seconds!r}")
    if not seconds <= INT32_MAX:  # int32 sec; also refuses inf before round() would raise OverflowError
        raise RosMessageError(f"a builtin_interfaces/Duration holds at most {INT32_MAX} s (int32 sec), got {seconds!r} s")
    sec, nanosec = divmod(round(seconds * NS_PER_S), NS_PER_S)
    return {"sec": int(sec), "nanosec": int(nanosec)}


def header_frame_id(msg: Any, message: str | None = None) -> str:
    """``msg.header.frame_id``, a non-empty str; ``message`` (``"sensor_msgs/PointCloud2"``) names it in an error.
    str() would turn None into the frame 'None', in which the detections would then be published."""
    frame_id = msg.header.frame_id
    if not isinstance(frame_id, str) or not frame_id:
        raise RosMessageError(f"{message or 'std_msgs/Header'} header.frame_id must be a non-empty string, got {shown(frame_id)}")
    return frame_id


def header_msg(ns: int, frame_id: str) -> dict:
    """A ``std_msgs/Header`` dict."""
    if not isinstance(frame_id, str) or not frame_id:  # str(None) would name a frame 'None'
        raise RosMessageError(f"std_msgs/Header.frame_id must be a non-empty string, got {shown(frame_id)}")
    return {"stamp": time_msg(ns), "frame_id": frame_id}


def byte_view(data: Any, what: str = "uint8[] payload") -> np.ndarray:
    """A uint8 view of a ``uint8[]`` payload: bytes, bytearray, array.array, memoryview, a numpy array, or a list of
    ints 0..255; anything else is refused naming ``what`` (``"sensor_msgs/PointCloud2.data"``) and its type.

    Elements are the payload's bytes: an array of wider integers (``np.array(list(msg.data))`` is int64) is taken by
    its values, each 0..255, never reinterpreted as its raw bytes (eight per value: a cloud decoded to garbage)."""
    if not isinstance(data, (np.ndarray, list, tuple)):
        try:
            view = memoryview(data)
        except TypeError:  # no buffer: None, a str, a number
            view = None
        if view is not None and view.itemsize == 1 and view.c_contiguous:
            return np.frombuffer(data, dtype=np.uint8)
        if view is not None:
            data = np.asarray(view)  # an array.array of wider items, or a strided view: by its values below
    if isinstance(data, np.ndarray):
        if data.dtype in (np.uint8, np.int8):  # the bytes themselves (int8: the same bits)
            return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
        if data.dtype.kind in "iu" and (data.size == 0 or (int(data.min()) >= 0 and int(data.max()) <= UINT8_MAX)):
            return data.astype(np.uint8).reshape(-1)
    elif isinstance(data, (list, tuple)):
        # a list of ints (slow path), checked first: np.asarray(..., dtype=np.uint8) would wrap 256 and truncate 1.5
        if all(is_integer(v) and 0 <= v <= UINT8_MAX for v in data):
            return np.asarray(data, dtype=np.uint8).reshape(-1)
    raise RosMessageError(f"{what} must be bytes, a uint8 array or integers 0..255, got {type(data).__name__} "
                          f"{getattr(data, 'dtype', '')} {shown(data)}")  # fmt: skip
