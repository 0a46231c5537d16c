"""The checks of a call's arguments shared by the detector and its lanes: a slice index, a timestamp, a slice count.

One place for the words: ``StreamingDetector.detect_slice`` and ``StreamingRunner.submit_slice`` refuse a bad slice
index or timestamp with the same message (the runner before it queues anything, the detector when it runs)."""

from __future__ import annotations

import math
import time

import numpy as np

from streamdet.core.json_input import is_finite_number, short_repr
from streamdet.core.sectors import check_num_slices


def slice_index_problem(slice_index: object, num_slices: int | None) -> str | None:
    """Why ``slice_index`` is no slice of ``num_slices`` (None: any int >= 0, for a stand-in detector without a
    count); None if it is one. The words of detect_slice and of StreamingRunner.submit_slice."""
    top = num_slices if num_slices is not None else math.inf
    if isinstance(slice_index, bool) or not isinstance(slice_index, (int, np.integer)) or not 0 <= slice_index < top:
        return f"slice_index must be an int in [0, {num_slices if num_slices is not None else 'num_slices'}), got {short_repr(slice_index)}"
    return None


def timestamp_problem(value: object) -> str | None:
    """Why ``value`` is no call's timestamp (None, or a finite real number of seconds); None if it is one."""
    if value is None or is_finite_number(value):  # is_finite_number: no OverflowError for 10**400
        return None
    return f"timestamp must be None or a finite number of seconds, got {short_repr(value)}"


def call_timestamp(value: float | None) -> float:
    """A call's timestamp: None is now (time.monotonic()); anything else must be a finite real number of seconds."""
    problem = timestamp_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return time.monotonic() if value is None else float(value)


def slice_count(num_slices: int | None, default: int, start_deg: float) -> int:
    """A call's ``num_slices``: None is the detector's ``default``; anything else must be a slice count the sectors
    allow at ``start_deg`` (1, 2 or a multiple of 4: core/sectors.py)."""
    if num_slices is None:
        return default
    if isinstance(num_slices, bool):
        raise ValueError(f"num_slices must be None or an int (1, 2 or a multiple of 4), got {num_slices!r}")
    try:
        check_num_slices(num_slices, start_deg)
    except ValueError as e:
        raise ValueError(f"num_slices: {e}") from None
    return int(num_slices)
