"""The runtime's numpy stages timed alone (benchmarks/prepost.py): inputs as documented, every case reported."""

import numpy as np

from streamdet.benchmarks.prepost import (
    NUM_CANDIDATES,
    NUM_POINTS,
    candidates,
    format_prepost,
    measure_prepost,
    prepost_to_dict,
    real_sweep_points,
    uniform_quadrant_points,
)
from streamdet.benchmarks.timing import TimingConfig
from streamdet.calibration.grid import GridSpec

GRID = GridSpec(voxel_xy_m=0.4, voxel_z_m=2.0)


def test_inputs_are_what_the_cases_say():
    real = real_sweep_points()
    assert real.shape == (NUM_POINTS, 6) and real.dtype == np.float32
    uni = uniform_quadrant_points(GRID, 0)
    ox, oy = GRID.quadrant_origin_m(0)
    assert uni.shape == (NUM_POINTS, 6)
    assert np.all((uni[:, 0] >= ox) & (uni[:, 0] <= ox + 51.2) & (uni[:, 1] >= oy) & (uni[:, 1] <= oy + 51.2))
    boxes, scores, labels = candidates(GRID)
    assert boxes.shape == (1, NUM_CANDIDATES, 9) and scores.shape == labels.shape == (1, NUM_CANDIDATES)
    assert scores.min() > 0.1  # every candidate reaches NMS


def test_every_case_is_measured_and_reported():
    cases = measure_prepost(GRID, 20, 8000, timing=TimingConfig(repeat=2, warmup=0, budget_s=1.0))
    assert [c.stage for c in cases] == ["pre", "pre", "post", "post", "post", "post"]
    assert all(c.stats.count == 2 for c in cases)
    text = format_prepost(cases)
    assert text.count("\n") == len(cases) and "pillarize 30,000 points" in text
    doc = prepost_to_dict(cases)
    assert {"name", "stage", "budget_ms", "met", "median_ms", "p95_ms", "count"} <= set(doc[0])
