"""The slice rows' pillars: the paper's "30,000 points", taken from the bundled nuScenes sweep and pillarized by the
runtime, on the map each row runs on.

- uncropped rows (one map the size of the whole grid): every pillar of the 30,000 points;
- cropped rows (one quadrant): the pillars of the quadrant that holds the most of them, the worst of the four.

Real points rather than a synthetic tensor because the pillar count is what the pillar net and the scatter cost,
and a LiDAR sweep is dense near the car: its 30,000 points fill about 4,300 of the small preset's 0.4 m pillars,
not one pillar per point. Cropping a slice to a quadrant crops its points too, which is what makes the paper's
cropped row a quarter of the uncropped one (161.6 / 40.43 GMAC).

numpy only, so ``flops_report`` (the GMAC counter) and the timed rows read the same pillars.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.benchmarks.prepost import NUM_POINTS, real_sweep_points
from streamdet.calibration.grid import GridSpec
from streamdet.core.sectors import NUM_QUADRANTS
from streamdet.runtime_ort.pillarize import Pillars, pillarize

QUADRANTS = tuple(range(NUM_QUADRANTS))


@dataclass(frozen=True)
class SweepPillars:
    features: np.ndarray  # (P, M, 11) float32, padding rows 0
    mask: np.ndarray  # (P, M) float32
    index: np.ndarray  # (P,) int64, row * map_nx + col on the row's map, increasing
    map_ny: int
    map_nx: int
    quadrant: int | None  # the cropped row's quadrant; None for the whole grid

    @property
    def num_pillars(self) -> int:
        return len(self.index)


def whole_grid_pillars(grid: GridSpec, max_points_per_pillar: int, max_pillars: int, num_points: int = NUM_POINTS) -> SweepPillars:
    """Every pillar of ``num_points`` sweep points, indexed on one (ny, nx) map of the whole grid."""
    made = pillarize(real_sweep_points(num_points), grid, QUADRANTS, max_points_per_pillar, max_pillars)
    cells = grid.quadrant_ny * grid.quadrant_nx
    qi, local = np.divmod(made.index, cells)  # (P,) quadrant position and cell within it
    row, col = np.divmod(local, grid.quadrant_nx)
    offsets = np.array([grid.quadrant_offset_cells(q) for q in QUADRANTS], dtype=np.int64)  # (4, 2) row0, col0
    full = (offsets[qi, 0] + row) * grid.nx + offsets[qi, 1] + col  # (P,)
    order = np.argsort(full, kind="stable")
    return SweepPillars(made.features[order], made.mask[order], full[order], grid.ny, grid.nx, None)


def busiest_quadrant_pillars(grid: GridSpec, max_points_per_pillar: int, max_pillars: int, num_points: int = NUM_POINTS) -> SweepPillars:
    """The pillars of the quadrant holding the most of them (the first of equals), on that quadrant's map."""
    points = real_sweep_points(num_points)
    made: list[Pillars] = [pillarize(points, grid, (q,), max_points_per_pillar, max_pillars) for q in QUADRANTS]
    q = int(np.argmax([m.num_pillars for m in made]))
    p = made[q]
    return SweepPillars(p.features, p.mask, p.index, grid.quadrant_ny, grid.quadrant_nx, q)
