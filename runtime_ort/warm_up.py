"""Warming a `StreamingDetector` up before the first real data (``StreamingDetector.warm_up``).

onnxruntime's first two runs of a graph are slower than the ones after (its memory arena and pattern planning;
measured on the lifter graph: docs/replay.md, section "Notes"). A vehicle process whose first
real image update pays that queues its first slices behind it. ``warm_up`` runs every graph of the export twice on
dummy inputs (black images through the full and the per-quadrant image updates, a synthetic ring of points through
every slice), then drops the dummy image BEV and the latency statistics; the LUT, calibration and sessions stay.
"""

from __future__ import annotations

import logging
import warnings
from typing import TYPE_CHECKING

import numpy as np

from streamdet.core.points import SWEEP_COLUMNS
from streamdet.runtime_ort.pipeline import update_by_quadrant

if TYPE_CHECKING:
    from streamdet.runtime_ort.detector import StreamingDetector

log = logging.getLogger(__name__)

DUMMY_POINTS = 8192  # points of the dummy sweep: enough pillars in every slice


def dummy_sweep(x_range_m: tuple[float, float], num_points: int = DUMMY_POINTS, seed: int = 0) -> np.ndarray:
    """(N, 5) float32 x, y, z, intensity, ring: points on the ground and on walls all around the sensor, within
    ``x_range_m`` (the grid's half-width), so that every slice has pillars."""
    rng = np.random.default_rng(seed)
    reach = 0.9 * float(x_range_m[1])
    azimuth = rng.uniform(-np.pi, np.pi, num_points)
    radius = rng.uniform(2.0, reach, num_points)
    points = np.zeros((num_points, SWEEP_COLUMNS), np.float32)
    points[:, 0] = radius * np.cos(azimuth)
    points[:, 1] = radius * np.sin(azimuth)
    points[:, 2] = rng.uniform(-1.8, 1.0, num_points)
    points[:, 3] = rng.uniform(0.0, 1.0, num_points)
    points[:, 4] = rng.integers(0, 32, num_points)
    return points


def warm_up(det: StreamingDetector, rounds: int = 2) -> None:
    """Run ``det``'s graphs ``rounds`` times on dummy inputs, then forget them (see the module doc)."""
    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 1:
        raise ValueError(f"warm_up rounds must be an int >= 1, got {rounds!r}")
    if det.image_state is not None:  # its black images would replace (and then drop) the real BEV slices read
        raise ValueError("warm_up runs before the first update_images: this detector holds real images already")
    sweep = dummy_sweep(det.grid.x_range_m)
    first_seq = det._image_seq  # update_images calls before this one's (none, but for a racing thread)
    own: set[int] = set()  # the seqs of warm_up's own image updates
    for _ in range(rounds):
        if det.uses_images:
            img = det.image
            black = {name: np.zeros((img.height, img.width, 3), np.uint8) for name in det.camera_names}
            full = det.update_images(black, timestamp=0.0)
            by_quadrant = update_by_quadrant(det, black, 0.0)  # the phase-locked lane's calls and sizes
            own.update([full.seq, *(u.seq for u in by_quadrant)])
        det.detect_sweep(sweep, timestamp=0.0)
    if own:
        det.forget_images(through=max(own))  # only the black images: a real set that came after them stays
        replaced = [seq for seq in range(first_seq + 1, max(own)) if seq not in own]
        if replaced:  # a lane started before warm_up: its first images lost to the black ones
            msg = (f"{len(replaced)} update_images call(s) from another thread ran during warm_up: their images were "
                   "dropped with its black ones; call warm_up before starting the lanes")  # fmt: skip
            log.warning("%s: %s", det.export_dir, msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
    det.stats.reset()
