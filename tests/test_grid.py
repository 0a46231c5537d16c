"""Grid, quadrant and sector conventions (calibration/grid.py) against naive references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.calibration.grid import GridSpec
from streamdet.core.sectors import azimuth_deg, check_num_slices, quadrants_of_sector, sector_bounds_deg, slice_index_of


def test_paper_grid_sizes():
    g = GridSpec()
    assert (g.nx, g.ny, g.nz) == (512, 512, 16)
    assert (g.quadrant_nx, g.quadrant_ny) == (256, 256)


@pytest.mark.parametrize("q,expected_sign", [(0, (1, 1)), (1, (-1, 1)), (2, (-1, -1)), (3, (1, -1))])
def test_quadrant_origin_and_offset_agree(q, expected_sign):
    g = GridSpec(x_range_m=(-4.0, 4.0), y_range_m=(-4.0, 4.0), voxel_xy_m=1.0)
    x0, y0 = g.quadrant_origin_m(q)
    row0, col0 = g.quadrant_offset_cells(q)
    assert x0 == g.x_range_m[0] + col0 * g.voxel_xy_m
    assert y0 == g.y_range_m[0] + row0 * g.voxel_xy_m
    centres = g.voxel_centers(q)  # (Z, Yq, Xq, 3)
    sx, sy = expected_sign
    assert np.all(np.sign(centres[..., 0]) == sx) and np.all(np.sign(centres[..., 1]) == sy)
    assert np.all(g.quadrant_of_xy(centres[..., 0], centres[..., 1]) == q)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_slice_index_matches_naive(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50, 50, size=(2000, 2))
    for n in (1, 2, 4, 8, 16, 32):
        got = slice_index_of(xy[:, 0], xy[:, 1], n)
        for (x, y), k in zip(xy[:50], got[:50]):
            a = math.degrees(math.atan2(y, x)) % 360.0
            lo, hi = sector_bounds_deg(int(k), n)
            assert lo <= a < hi
        # a point's slice lies in the quadrants of that slice
        q = GridSpec().quadrant_of_xy(xy[:, 0], xy[:, 1])
        for k in range(n):
            assert set(np.unique(q[got == k])) <= set(quadrants_of_sector(k, n))


def test_quadrants_of_sector():
    assert quadrants_of_sector(0, 1) == (0, 1, 2, 3)
    assert quadrants_of_sector(0, 2) == (0, 1)
    assert quadrants_of_sector(1, 2) == (2, 3)
    assert [quadrants_of_sector(k, 8) for k in range(8)] == [(0,), (0,), (1,), (1,), (2,), (2,), (3,), (3,)]
    assert quadrants_of_sector(0, 4, start_deg=90.0) == (1,)


def test_azimuth_wraps():
    assert azimuth_deg(np.array([1.0]), np.array([-1e-12]))[0] < 360.0
    assert azimuth_deg(np.array([0.0]), np.array([1.0]))[0] == pytest.approx(90.0)


@pytest.mark.parametrize("bad", [0, 3, 6, -4, 2.5, True, 4100, 8192, 10**12])
def test_bad_slice_counts(bad):
    with pytest.raises(ValueError, match="slices"):
        check_num_slices(bad)


def test_the_slice_count_cap_is_the_schemas_and_the_slice_index_bound():
    import json
    from importlib.resources import files

    from streamdet.core.points import MAX_SLICE_INDEX
    from streamdet.core.sectors import MAX_NUM_SLICES

    check_num_slices(MAX_NUM_SLICES)
    schema = json.loads(files("streamdet.runtime_ort").joinpath("manifest.schema.json").read_text())
    assert schema["properties"]["num_slices"]["maximum"] == MAX_NUM_SLICES == MAX_SLICE_INDEX + 1


def test_bad_start_angle():
    with pytest.raises(ValueError, match="multiple of 90"):
        check_num_slices(8, start_deg=10.0)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"x_range_m": (-10.0, 12.0)}, "symmetric"),
        ({"voxel_xy_m": 0.3}, "whole number"),
        ({"voxel_xy_m": 0.0}, "> 0"),
        ({"z_range_m": (5.0, -3.0)}, "max > min"),
        ({"x_range_m": (-float("nan"), 1.0)}, "finite"),
    ],
)
def test_bad_grids(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GridSpec(**kwargs)


def test_round_trip_dict():
    g = GridSpec(voxel_xy_m=0.4)
    assert GridSpec.from_dict(g.to_dict()) == g
