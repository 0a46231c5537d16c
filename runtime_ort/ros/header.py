"""What every message adapter shares: ``builtin_interfaces/Time`` and ``std_msgs/Header`` (stamps as integer
nanoseconds, headers as dicts) and ``uint8[]`` payloads as numpy views."""

from __future__ import annotations

from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000
# builtin_interfaces/Time and Duration hold ``int32 sec``: a stamp outside this range cannot be encoded (CDR packs
# it with struct 'i'), so it is refused here with the value rather than as a struct.error deep in the writer
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (``sec``, ``nanosec``)."""
    try:
        sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    except AttributeError:
        raise ValueError(f"expected a builtin_interfaces/Time with sec and nanosec, got {type(stamp).__name__}") from None
    if not 0 <= nanosec < NS_PER_S:
        raise ValueError(f"builtin_interfaces/Time.nanosec must be in [0, 1e9), got {nanosec}")
    return sec * NS_PER_S + nanosec


def header_stamp_ns(msg: Any) -> int:
    """Integer nanoseconds of ``msg.header.stamp``."""
    return stamp_ns(msg.header.stamp)


def time_msg(ns: int) -> dict:
    """A ``builtin_interfaces/Time`` dict of integer nanoseconds (negative times round toward minus infinity)."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    if not INT32_MIN <= sec <= INT32_MAX:
        raise ValueError(f"time {int(ns)} ns does not fit a ROS 2 stamp: {sec} s is outside int32 seconds")
    return {"sec": sec, "nanosec": nanosec}


def duration_msg(seconds: float) -> dict:
    """A ``builtin_interfaces/Duration`` dict of a non-negative number of seconds."""
    if not seconds >= 0:
        raise ValueError(f"a duration must be >= 0 s, got {seconds!r}")
    if not seconds <= INT32_MAX:  # int32 sec; also refuses inf before round() would raise OverflowError
        raise ValueError(f"a builtin_interfaces/Duration holds at most {INT32_MAX} s (int32 sec), got {seconds!r} s")
    sec, nanosec = divmod(round(seconds * NS_PER_S), NS_PER_S)
    return {"sec": int(sec), "nanosec": int(nanosec)}


def header_msg(ns: int, frame_id: str) -> dict:
    """A ``std_msgs/Header`` dict."""
    return {"stamp": time_msg(ns), "frame_id": str(frame_id)}


def byte_view(data: Any) -> np.ndarray:
    """A uint8 view of a ``uint8[]`` payload: bytes, bytearray, array.array, memoryview or a numpy array."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8)  # a list of ints (slow path)
