"""What the image lane derives from a projection LUT, made once per LUT and kept while that LUT is in use.

- the per-quadrant LUTs (``calibration/quadrant_lut.py``): every per-quadrant lift and per-camera term reads them;
- the lifter's LUT feeds in the export's LUT layout (the K-slot arrays, or their compacted form:
  ``core/lut_layout.py``), which cost a pass over the LUT to make;
- the cameras a set of quadrants reads, which the phase-locked lane asks several hundred times a second while
  holding the GIL.

A calibration swap brings a new LUT: the views of the LUT in use and of the new one are kept (the image lane may
still finish an update under the old one), older ones are dropped. Thread-safe: the image lane, the slice lane's
planner and a calibration swap ask at once; a view is made outside the lock, so two threads may both make one and
the later one is kept (they are equal).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np

from streamdet.calibration.compact_lut import lifter_lut_feeds
from streamdet.calibration.lut import Lut
from streamdet.calibration.quadrant_lut import QuadrantLut, quadrant_luts
from streamdet.core.lut_layout import LUT_COMPACT
from streamdet.core.sectors import NUM_QUADRANTS


class LutViews:
    """The derived views of the LUTs an image lane uses (module docstring)."""

    def __init__(self, camera_names: Sequence[str], lut_layout: str) -> None:
        self._camera_names = tuple(camera_names)  # the export's camera order
        self._lut_layout = lut_layout
        self._lock = threading.Lock()
        self._quadrant_luts: dict[Lut, tuple[QuadrantLut, ...]] = {}
        self._cameras: tuple[Lut, dict[tuple[int, ...], tuple[str, ...]]] | None = None  # answers for one LUT
        self._feeds: dict[tuple[int, int], tuple[Lut | QuadrantLut, dict[str, np.ndarray]]] = {}
        self._closed = False

    def close(self) -> None:
        """Forget every view kept and keep none from now on (a closed detector's: views are still made on use, for a
        call that races the close, but not kept)."""
        with self._lock:
            self._closed = True
            self._quadrant_luts, self._cameras, self._feeds = {}, None, {}

    def quadrant_luts(self, lut: Lut, in_use: Lut | None) -> tuple[QuadrantLut, ...]:
        """The per-quadrant LUTs of ``lut``, made once; those of ``lut`` and of ``in_use`` (the detector's LUT now)
        are kept, any other LUT's dropped."""
        with self._lock:
            qluts = self._quadrant_luts.get(lut)
        if qluts is None:
            qluts = quadrant_luts(lut)
            with self._lock:
                if self._closed:
                    return qluts
                keep = [k for k in self._quadrant_luts if k is in_use and k is not lut]
                self._quadrant_luts = {**{k: self._quadrant_luts[k] for k in keep}, lut: qluts}
        return qluts

    def known_cameras(self, lut: Lut | None, quadrants: tuple) -> tuple[str, ...] | None:
        """``cameras``' kept answer for ``lut`` and these quadrants, None when there is none (no checks: the caller's
        fast path, before it validates ``quadrants``; only valid ones were ever kept)."""
        kept = self._cameras
        if kept is None or kept[0] is not lut:
            return None
        return kept[1].get(quadrants)

    def cameras(self, lut: Lut, quadrants: tuple[int, ...], in_use: Lut | None) -> tuple[str, ...]:
        """The cameras whose feature maps ``lut`` reads in ``quadrants`` (valid, strictly increasing), in the
        export's camera order; answers are kept for the LUT in use only."""
        cams = self.known_cameras(lut, quadrants)
        if cams is not None:
            return cams
        qluts = self.quadrant_luts(lut, in_use)
        seen = {name for q in quadrants for name in qluts[q].camera_names}
        cams = tuple(n for n in self._camera_names if n in seen)
        if lut is in_use:
            with self._lock:  # one tuple swapped whole: readers without the lock see an old or a new answer set
                kept = self._cameras
                if not self._closed:
                    self._cameras = (lut, {**(kept[1] if kept is not None and kept[0] is lut else {}), quadrants: cams})
        return cams

    def lifter_feeds(self, lut: Lut | QuadrantLut, maps: np.ndarray) -> dict[str, np.ndarray]:
        """The lifter's LUT inputs of ``lut`` for the (J, C, Hf, Wf) feature ``maps`` it lifts, in the export's LUT
        layout; the compacted form is made once per (LUT, J * Hf * Wf), the newest two LUTs' worth kept."""
        if self._lut_layout != LUT_COMPACT:
            return {"lut_index": lut.index, "lut_weight": lut.weight}
        j, _, hf, wf = maps.shape
        key = (id(lut), j * hf * wf)
        with self._lock:
            cached = self._feeds.get(key)
        if cached is None or cached[0] is not lut:  # an id is only unique while its object lives: the entry keeps it
            cached = (lut, lifter_lut_feeds(lut.index, lut.weight, j * hf * wf, compact=True))
            with self._lock:
                if self._closed:
                    return cached[1]
                if len(self._feeds) >= 2 * (NUM_QUADRANTS + 1):  # two LUTs' worth (full + per quadrant)
                    self._feeds.pop(next(iter(self._feeds)))
                self._feeds[key] = cached
        return cached[1]
