"""Lower the scheduling priority of the calling thread: the image lane yields the CPU to the slice lane.

On a machine whose cores the two lanes share, a slice that arrives while the image lane is running competes with it
for a core; the operating system's scheduler decides who waits. ``LaneConfig.image_lane_nice`` raises the image
lane's worker thread's nice value (Linux keeps one per thread), so that a slice's work is served first and the image
lane runs in the time the slices leave. Only raising is offered (0..19): it needs no privilege, and a vehicle's
real-time priorities are the deployment's business (``chrt``, ``SCHED_FIFO``), not the library's.
"""

from __future__ import annotations

import os
import sys
import threading

import numpy as np

MAX_NICE = 19


def check_nice(nice: object, what: str) -> int:
    """``nice`` (an int, or a numpy integer as the other int fields of LaneConfig take) as an int in 0..19;
    ValueError naming ``what`` otherwise, or where the platform has no per-thread nice values (a nonzero value
    anywhere but Linux)."""
    if isinstance(nice, bool) or not isinstance(nice, (int, np.integer)) or not 0 <= nice <= MAX_NICE:
        raise ValueError(f"{what} must be an int in 0..{MAX_NICE} (0: unchanged), got {nice!r}")
    nice = int(nice)  # os.setpriority and the arithmetic on it want a Python int
    if nice and not sys.platform.startswith("linux"):
        raise ValueError(f"{what}={nice}: per-thread nice values need Linux (this is {sys.platform}); use 0")
    return nice


def lower_thread_priority(nice: int) -> None:
    """Add ``nice`` (0..19) to the calling thread's nice value (Linux: the thread alone, not the process). 0: nothing."""
    if nice:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(MAX_NICE, os.getpriority(os.PRIO_PROCESS, tid) + nice))


def start_worker(target, name: str, nice: int = 0) -> threading.Thread:
    """Start a daemon thread ``name`` that adds ``nice`` to its own nice value, then runs ``target()``. Returns once
    the priority is set; if setting it failed, the thread ends without running ``target`` and the OSError is raised
    here, in the caller's thread (a lane never runs silently at a priority other than the one asked for)."""
    ready = threading.Event()
    failed: list[OSError] = []

    def run() -> None:
        try:
            lower_thread_priority(nice)
        except OSError as e:
            failed.append(e)
            return
        finally:
            ready.set()
        target()

    thread = threading.Thread(target=run, name=name, daemon=True)
    try:
        thread.start()
    except RuntimeError as e:  # "can't start new thread": a memory, pids or stack limit; an OSError, as the nice one
        raise OSError(f"{name}: could not start the thread ({e}): fewer workers, or a higher memory / pids limit") from e
    ready.wait()
    if failed:
        raise OSError(f"{name}: could not add {nice} to the thread's nice value: {failed[0]}") from failed[0]
    return thread
