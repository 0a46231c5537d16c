"""The Python heap of a real-time process: keeping the garbage collector's full collections out of the lanes.

CPython's cyclic collector runs a **full (generation 2) collection** when enough objects have survived since the
last one, and it holds the GIL while it walks every tracked object. The lanes' graph runs release the GIL, but the
work between them (pillarising, post-processing, the callbacks, the LiDAR driver's thread) stops for the whole
collection: in a process that loaded a large heap at start-up (datasets, tables, a ROS node's message types) one
collection stalls every Python thread for tens of milliseconds, and a burst of slices released after the stall can
overflow the slice queue (docs/replay.md, "Full garbage collections stall the lanes", measures it).

``frozen_heap()`` is the usual remedy (CPython's ``gc.freeze``, Python >= 3.7): collect once, then move every object
alive now into a permanent generation that later collections skip. The objects made afterwards are still
collected, so cycles made while running are not leaked; only the heap of the start-up is exempt. Call it once the
process has loaded what it keeps (after opening the detector and warming it up), around the loop that feeds the
runtime. ``GcPauses`` measures what the collector cost meanwhile (counts and pause times per generation).

The runtime never calls either itself: the heap belongs to the process that embeds it.

The C heap is another matter: a calibration swap builds a new LUT through large temporary arrays, and glibc's
allocator keeps the freed pages mapped, so a process's resident memory climbed with every swap
(benchmarks/RESULTS.md, "Memory after calibration swaps"). ``release_free_memory`` hands them back (glibc's
``malloc_trim``); the detector calls it after each swap and on ``close()``. A no-op where the C library has no such
call (musl, macOS, Windows). (The climb from one detector to the next, once blamed on the allocator too, was a
reference cycle that kept closed detectors alive until a full collection: tests/test_runtime_heap.py keeps a closed
detector freed by reference counts alone.)
"""

from __future__ import annotations

import gc
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator

NUM_GENERATIONS = 3


def _malloc_trim():
    """glibc's malloc_trim, or None where the C library has none."""
    try:
        import ctypes
        import ctypes.util

        name = ctypes.util.find_library("c")
        return None if name is None else getattr(ctypes.CDLL(name), "malloc_trim", None)
    except (OSError, AttributeError, ImportError):
        return None


_TRIM = _malloc_trim()


def release_free_memory() -> bool:
    """Return the C heap's free pages to the operating system (glibc ``malloc_trim(0)``); False where this C library
    cannot. It holds each allocator arena's lock while it walks it, so other threads' allocations wait that long:
    call it after rare, large frees (a calibration swap, a detector closed), not per slice."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


# Open frozen_heap blocks, any thread: gc.unfreeze() thaws every frozen object, an enclosing block's too, so only the
# last block to close may call it (a node wrapping its spin loop, and a helper that wraps its own work, nest)
_frozen_lock = threading.Lock()
_frozen_depth = 0


@contextmanager
def frozen_heap(enabled: bool = True) -> Iterator[None]:
    """Collect, freeze every object alive now out of later collections (``gc.freeze``), run the body, then
    unfreeze. ``enabled`` False: the body runs with the heap as it is (to measure the difference).

    Blocks nest, and may overlap in several threads: each entry collects and freezes what is alive then, and the heap
    is unfrozen when the last open block exits (a ``gc.freeze`` the process made itself is thawed with it)."""
    global _frozen_depth
    if not enabled:
        yield
        return
    gc.collect()  # outside the lock: a finaliser it runs may enter a block itself
    with _frozen_lock:
        gc.freeze()
        _frozen_depth += 1
    try:
        yield
    finally:
        with _frozen_lock:
            _frozen_depth -= 1
            if _frozen_depth == 0:
                gc.unfreeze()


@dataclass
class GenerationPauses:
    collections: int = 0
    total_ms: float = 0.0
    max_ms: float = 0.0


@dataclass
class GcPauses:
    """Collections of the cyclic collector while active (``with GcPauses() as pauses:``), per generation 0..2.

    A pause is the wall time from the collector's start callback to its stop callback: every Python thread waits
    that long. Callbacks of collections that started before ``__enter__`` are ignored."""

    generations: list[GenerationPauses] = field(default_factory=lambda: [GenerationPauses() for _ in range(NUM_GENERATIONS)])

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._start: float | None = None

    def _callback(self, phase: str, info: dict) -> None:
        now = time.perf_counter()
        if phase == "start":
            self._start = now
            return
        start, self._start = self._start, None
        if start is None:
            return
        ms = (now - start) * 1e3
        with self._lock:
            g = self.generations[min(int(info.get("generation", NUM_GENERATIONS - 1)), NUM_GENERATIONS - 1)]
            g.collections += 1
            g.total_ms += ms
            g.max_ms = max(g.max_ms, ms)

    def __enter__(self) -> "GcPauses":
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *exc) -> None:
        try:
            gc.callbacks.remove(self._callback)
        except ValueError:  # removed by someone else: nothing to undo
            pass

    @property
    def max_ms(self) -> float:
        """The longest pause of any generation (0 when none ran)."""
        return max(g.max_ms for g in self.generations)

    def to_dict(self) -> dict:
        """{"gen0": {"collections", "total_ms", "max_ms"}, "gen1": ..., "gen2": ...}."""
        with self._lock:
            return {f"gen{i}": {"collections": g.collections, "total_ms": g.total_ms, "max_ms": g.max_ms}
                    for i, g in enumerate(self.generations)}  # fmt: skip
