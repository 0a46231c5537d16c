"""pillarize against a pure-Python reference that applies the contract point by point in exact arithmetic."""

from __future__ import annotations

import importlib
import importlib.resources
import math
from fractions import Fraction

import numpy as np
import pytest

from streamdet.calibration.grid import GridSpec
from streamdet.core.points import MAX_POINT_TIME_S, MAX_SLICE_INDEX
from streamdet.core.sectors import quadrants_of_sector, slice_index_of
from streamdet.runtime_ort.pillarize import PILLAR_FEATURE_DIM, Pillars, pillarize

pillarize_module = importlib.import_module("streamdet.runtime_ort.pillarize")  # the module, not the function

PAPER = GridSpec()
SMALL = GridSpec(x_range_m=(-4.0, 4.0), y_range_m=(-4.0, 4.0), z_range_m=(-1.0, 1.0), voxel_xy_m=0.5, voxel_z_m=0.5)
ODD = GridSpec(x_range_m=(-3.0, 3.0), y_range_m=(-2.4, 2.4), z_range_m=(-2.0, 3.0), voxel_xy_m=0.3, voxel_z_m=0.5)


def naive_pillarize(points, grid, quadrants, m_max, max_pillars):
    """The contract, literally: exact decimal cell borders, dicts of lists, one point at a time."""
    voxel = Fraction(str(grid.voxel_xy_m))
    x_min, y_min = Fraction(str(grid.x_range_m[0])), Fraction(str(grid.y_range_m[0]))
    z_min, z_max = Fraction(str(grid.z_range_m[0])), Fraction(str(grid.z_range_m[1]))
    yq, xq = grid.quadrant_ny, grid.quadrant_nx
    pillars: dict[int, list[np.ndarray]] = {}
    nonfinite = outside = out_of_range = 0
    for p in points:
        if not all(math.isfinite(float(v)) for v in p):
            nonfinite += 1
            continue
        x, y, z = Fraction(float(p[0])), Fraction(float(p[1])), Fraction(float(p[2]))
        col = math.floor((x - x_min) / voxel)
        row = math.floor((y - y_min) / voxel)
        if not (0 <= col < grid.nx and 0 <= row < grid.ny and z_min <= z < z_max):
            outside += 1
            continue
        q = int(grid.quadrant_of_xy(np.float64(p[0]), np.float64(p[1])))
        if q not in quadrants:
            outside += 1
            continue
        r, t, k = float(p[3]), float(p[4]), float(p[5])
        if not (0.0 <= r <= 1.0 and 0.0 <= t <= MAX_POINT_TIME_S and 0.0 <= k <= MAX_SLICE_INDEX):
            outside += 1
            out_of_range += 1
            continue
        row0, col0 = grid.quadrant_offset_cells(q)
        assert 0 <= row - row0 < yq and 0 <= col - col0 < xq, "cell and quadrant disagree"
        flat = quadrants.index(q) * yq * xq + (row - row0) * xq + (col - col0)
        pillars.setdefault(flat, []).append(p.astype(np.float64))
    ranked = sorted(pillars, key=lambda f: (-len(pillars[f]), f))
    chosen = sorted(ranked[:max_pillars])
    features = np.zeros((len(chosen), m_max, PILLAR_FEATURE_DIM))
    mask = np.zeros((len(chosen), m_max))
    kept_points = 0
    for i, flat in enumerate(chosen):
        pts = pillars[flat][:m_max]
        kept_points += len(pts)
        mean = np.mean([pt[:3] for pt in pts], axis=0)
        qi, local = divmod(flat, yq * xq)
        row0, col0 = grid.quadrant_offset_cells(quadrants[qi])
        cx = grid.x_range_m[0] + (col0 + local % xq + 0.5) * grid.voxel_xy_m
        cy = grid.y_range_m[0] + (row0 + local // xq + 0.5) * grid.voxel_xy_m
        for j, pt in enumerate(pts):
            features[i, j, :6] = pt
            features[i, j, 6:9] = pt[:3] - mean
            features[i, j, 9:11] = pt[0] - cx, pt[1] - cy
            mask[i, j] = 1
    in_grid = sum(len(v) for v in pillars.values())
    index = np.array(chosen, np.int64)
    return features, mask, index, in_grid - kept_points, len(pillars) - len(chosen), nonfinite, outside, out_of_range


def assert_matches_reference(out: Pillars, points, grid, quadrants, m_max, max_pillars):
    features, mask, index, pts_dropped, pil_dropped, nonfinite, outside, out_of_range = naive_pillarize(
        points, grid, tuple(quadrants), m_max, max_pillars
    )
    assert out.num_out_of_range_dropped == out_of_range
    assert out.features.dtype == np.float32 and out.mask.dtype == np.float32 and out.index.dtype == np.int64
    assert out.features.shape == (len(index), m_max, PILLAR_FEATURE_DIM)
    assert out.mask.shape == (len(index), m_max) and out.index.shape == (len(index),)
    np.testing.assert_array_equal(out.index, index)
    np.testing.assert_array_equal(out.mask, mask)
    np.testing.assert_allclose(out.features, features, rtol=0, atol=2e-5)
    assert (out.num_points_dropped, out.num_pillars_dropped) == (pts_dropped, pil_dropped)
    assert (out.num_nonfinite_dropped, out.num_outside_dropped) == (nonfinite, outside)
    accounted = mask.sum() + pts_dropped + nonfinite + outside
    assert accounted == len(points)


def random_points(rng, n, grid, margin_m=1.0):
    """Points over the grid and a margin beyond it, bunched so that pillars hold several points."""
    pts = np.empty((n, 6), np.float32)
    centres = rng.uniform(
        [grid.x_range_m[0] - margin_m, grid.y_range_m[0] - margin_m],
        [grid.x_range_m[1] + margin_m, grid.y_range_m[1] + margin_m],
        size=(max(n // 8, 1), 2),
    )
    pts[:, :2] = centres[rng.integers(0, len(centres), n)] + rng.normal(0, grid.voxel_xy_m, (n, 2))
    pts[:, 2] = rng.uniform(grid.z_range_m[0] - 0.5, grid.z_range_m[1] + 0.5, n)
    pts[:, 3] = rng.uniform(0, 1, n)
    pts[:, 4] = rng.uniform(0, 0.05, n)
    pts[:, 5] = rng.integers(0, 8, n)
    return pts


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "grid, quadrants, m_max, max_pillars",
    [
        (SMALL, (0,), 4, 1000),
        (SMALL, (1, 2), 3, 1000),
        (SMALL, (0, 1, 2, 3), 32, 1000),
        (SMALL, (0, 1, 2, 3), 2, 7),  # both caps overflow
        (ODD, (2, 3), 5, 1000),
        (PAPER, (3,), 20, 30000),  # 65536 cells: the largest map set sorted as 16-bit keys
        (PAPER, (0, 3), 20, 30000),  # 131072 cells: the wider sort key
    ],
)
def test_matches_naive_reference(seed, grid, quadrants, m_max, max_pillars):
    rng = np.random.default_rng(seed)
    points = random_points(rng, 1500, grid)
    out = pillarize(points, grid, quadrants, m_max, max_pillars)
    assert_matches_reference(out, points, grid, quadrants, m_max, max_pillars)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_points_with_features_out_of_range_are_dropped_and_counted(seed):
    """A reflectance outside 0..1, a time outside 0..MAX_POINT_TIME_S or a slice index outside 0..MAX_SLICE_INDEX
    drops the point as outside, whichever column it is and however far (a corrupted record: 1e30)."""
    rng = np.random.default_rng(seed)
    points = random_points(rng, 1500, SMALL)
    bad = rng.choice(len(points), 300, replace=False)
    column = rng.integers(3, 6, bad.size)
    values = np.array([-1e30, -0.01, 1.01, 1e30, MAX_POINT_TIME_S + 0.5, MAX_SLICE_INDEX + 1, -1.0], np.float32)
    points[bad, column] = values[rng.integers(0, len(values), bad.size)]
    points[rng.choice(len(points), 20), 3] = rng.choice([0.0, 1.0], 20)  # the bounds themselves are in range
    points[rng.choice(len(points), 20), 5] = MAX_SLICE_INDEX
    out = pillarize(points, SMALL, (0, 1, 2, 3), 8, 1000)
    assert_matches_reference(out, points, SMALL, (0, 1, 2, 3), 8, 1000)
    assert out.num_out_of_range_dropped > 0 and np.abs(out.features[..., 3:5]).max() <= MAX_POINT_TIME_S
    assert out.features[..., 5].max() <= MAX_SLICE_INDEX


def test_the_slice_index_bound_is_the_schemas_slice_count():
    import json
    from importlib.resources import files

    schema = json.loads(files("streamdet.runtime_ort").joinpath("manifest.schema.json").read_text())
    assert schema["properties"]["num_slices"]["maximum"] == MAX_SLICE_INDEX + 1


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("crop", [True, False])
@pytest.mark.parametrize("grid, quadrants", [(SMALL, (0, 1, 2, 3)), (ODD, (1,)), (PAPER, (2, 3))])
def test_sort_paths_agree(seed, crop, grid, quadrants, monkeypatch):
    """The 16-bit radix sort and the wide key sort group the same points in the same order."""
    points = random_points(np.random.default_rng(seed), 3000, grid)
    narrow = pillarize(points, grid, quadrants, 6, 200, crop=crop)
    monkeypatch.setattr(pillarize_module, "_UINT16_KEYS", 0)
    wide = pillarize(points, grid, quadrants, 6, 200, crop=crop)
    for field in ("features", "mask", "index"):
        np.testing.assert_array_equal(getattr(narrow, field), getattr(wide, field))
    assert narrow.num_points_dropped == wide.num_points_dropped and narrow.num_pillars_dropped == wide.num_pillars_dropped


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overflow_keeps_first_points_and_fullest_pillars(seed):
    rng = np.random.default_rng(seed)
    # Pillar A (cell (0, 0) of quadrant 0) gets 5 points, B and C 3 each (tie), D 1.
    cells = {"A": (0.25, 0.25), "B": (1.25, 0.25), "C": (0.25, 1.25), "D": (2.25, 2.25)}
    labels = ["A"] * 5 + ["B"] * 3 + ["C"] * 3 + ["D"]
    rng.shuffle(labels)
    points = np.zeros((len(labels), 6), np.float32)
    points[:, :2] = [cells[c] for c in labels]
    points[:, 5] = np.arange(len(labels))  # the input position, to check which points were kept
    out = pillarize(points, SMALL, (0,), 2, 2)
    xq = SMALL.quadrant_nx
    # A wins on count; B (flat 2) beats C (flat 2 * xq) on the tie.
    np.testing.assert_array_equal(out.index, [0, 2])
    for i, name in enumerate("AB"):
        first_two = [k for k, c in enumerate(labels) if c == name][:2]
        np.testing.assert_array_equal(out.features[i, :, 5], first_two)
    assert out.num_pillars_dropped == 2 and out.num_points_dropped == len(labels) - 4
    assert xq * 2 not in out.index.tolist()
    assert_matches_reference(out, points, SMALL, (0,), 2, 2)


@pytest.mark.parametrize("grid", [PAPER, SMALL])
def test_points_on_cell_borders_and_quadrant_axes(grid):
    """Points exactly on borders go to the cell above (half-open cells); axes go to the non-negative side."""
    half_x, half_y = grid.x_range_m[1], grid.y_range_m[1]
    tiny_negative = np.nextafter(np.float32(0), np.float32(-1))
    # Every cell border as float32 (exact where the decimal border is representable: 0, whole metres).
    borders = np.float32(np.arange(-grid.nx // 2, grid.nx // 2 + 1) * grid.voxel_xy_m)
    specials = np.array([0.0, -0.0, tiny_negative, 1.0, -1.0], np.float32)
    a, b = np.meshgrid(np.concatenate([borders, specials]), specials)  # lines along x at special y
    points = np.zeros((2 * a.size, 6), np.float32)
    points[: a.size, 0], points[: a.size, 1] = a.ravel(), b.ravel()
    points[a.size :, 0], points[a.size :, 1] = b.ravel(), a.ravel()  # and along y
    points[:, 2] = grid.z_range_m[0]  # z on its lower bound is inside
    out = pillarize(points, grid, (0, 1, 2, 3), 64, 100000)
    assert_matches_reference(out, points, grid, (0, 1, 2, 3), 64, 100000)
    # The origin (also as -0.0) is in quadrant 0's cell (0, 0); a tiny negative x is quadrant 1's last column.
    at_origin = (points[:, 0] == 0) & (points[:, 1] == 0)
    assert out.index[0] == 0 and out.mask[0].sum() == at_origin.sum() >= 4
    single = np.zeros((1, 6), np.float32)
    single[0, 0] = tiny_negative
    xq = grid.quadrant_nx
    np.testing.assert_array_equal(pillarize(single, grid, (0, 1), 4, 10).index, [1 * grid.quadrant_ny * xq + xq - 1])
    assert pillarize(single, grid, (0,), 4, 10).num_outside_dropped == 1
    # z on the upper bound, x or y on the positive range end, and beyond, are outside.
    edge = np.zeros((4, 6), np.float32)
    edge[:, 0] = [half_x, 0.0, 0.0, np.float32(-half_x) * np.float32(1.0000001)]
    edge[:, 1] = [0.0, half_y, 0.0, 0.0]
    edge[:, 2] = [0.0, 0.0, grid.z_range_m[1], 0.0]
    out = pillarize(edge, grid, (0, 1, 2, 3), 4, 10)
    assert out.num_outside_dropped == 4 and out.num_pillars == 0


def test_empty_input_gives_zero_pillars_with_contract_shapes():
    out = pillarize(np.zeros((0, 6), np.float32), PAPER, (0,), 20, 30000)
    assert out.features.shape == (0, 20, 11) and out.features.dtype == np.float32
    assert out.mask.shape == (0, 20) and out.mask.dtype == np.float32
    assert out.index.shape == (0,) and out.index.dtype == np.int64
    assert (out.num_points_dropped, out.num_pillars_dropped, out.num_nonfinite_dropped) == (0, 0, 0)
    assert set(out.as_feeds()) == {"pillar_features", "pillar_mask", "pillar_index"}


def test_nonfinite_points_are_dropped_and_counted():
    points = np.full((50, 6), np.nan, np.float32)
    out = pillarize(points, PAPER, (0, 1, 2, 3), 20, 100)
    assert out.num_pillars == 0 and out.num_nonfinite_dropped == 50
    rng = np.random.default_rng(0)
    points = random_points(rng, 300, SMALL)
    points[::7, rng.integers(0, 6)] = np.inf
    points[3::11, 2] = -np.inf
    points[5::13, 4] = np.nan
    out = pillarize(points, SMALL, (0, 1, 2, 3), 8, 1000)
    assert out.num_nonfinite_dropped == int((~np.isfinite(points).all(axis=1)).sum()) > 0
    assert_matches_reference(out, points, SMALL, (0, 1, 2, 3), 8, 1000)


def test_far_points_do_not_overflow_cell_indices():
    points = np.zeros((4, 6), np.float32)
    points[:, 0] = [3e38, -3e38, 1e20, 0.1]
    points[:, 1] = [0.1, 0.1, 0.1, -3e38]
    out = pillarize(points, PAPER, (0, 1, 2, 3), 20, 100)
    assert out.num_outside_dropped == 4 and out.num_pillars == 0


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((10, 5), np.float32), r"\(10, 5\)"),
        (np.zeros((10,), np.float32), r"\(10,\)"),
        (np.zeros((2, 10, 6), np.float32), r"\(2, 10, 6\)"),
        (np.zeros((10, 6), np.float64), "float64"),
        ([[0.0] * 6], "list"),
    ],
)
def test_malformed_points_raise_naming_the_shape(points, match):
    with pytest.raises(ValueError, match=match):
        pillarize(points, PAPER, (0,), 20, 100)


@pytest.mark.parametrize("quadrants", [(), (1, 0), (0, 0), (4,), (-1,), (0.5,)])
def test_bad_quadrants_raise(quadrants):
    with pytest.raises(ValueError, match="quadrants"):
        pillarize(np.zeros((1, 6), np.float32), PAPER, quadrants, 20, 100)


@pytest.mark.parametrize(
    "m_max, max_pillars, name",
    [(0, 10, "max_points_per_pillar"), (5, 0, "max_pillars"), (2.5, 10, "max_points_per_pillar")],
)
def test_bad_caps_raise(m_max, max_pillars, name):
    with pytest.raises(ValueError, match=name):
        pillarize(np.zeros((1, 6), np.float32), PAPER, (0,), m_max, max_pillars)


def test_real_sweep_slices_match_reference():
    """Two 45-degree slices of the bundled nuScenes sweep, in the form the streaming reader produces."""
    root = importlib.resources.files("streamdet.data") / "nuscenes_sample"
    name = "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
    sweep = np.frombuffer((root / name).read_bytes(), np.float32).reshape(-1, 5)
    k_of_point = slice_index_of(sweep[:, 0], sweep[:, 1], 8)
    for k in (1, 6):
        part = sweep[k_of_point == k]
        points = np.zeros((len(part), 6), np.float32)
        points[:, :3] = part[:, :3]
        points[:, 3] = part[:, 3] / 255
        points[:, 5] = k
        quadrants = quadrants_of_sector(k, 8)
        out = pillarize(points, PAPER, quadrants, 20, 30000)
        assert out.num_pillars > 500 and out.num_outside_dropped > 0  # the sweep reaches past 51.2 m
        assert_matches_reference(out, points, PAPER, quadrants, 20, 30000)
