"""Streaming slices (data/slicing.py) against naive per-point / per-box references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.core.points import SWEEP_DURATION_S
from streamdet.core.sectors import sector_bounds_deg
from streamdet.core.slicing import boxes_in_sector, relative_time_s, split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.data.slicing import slice_sample


def _random_sweep(seed: int, n: int = 3000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 5), dtype=np.float32)
    pts[:, :2] = rng.uniform(-60, 60, size=(n, 2))
    pts[:, 2] = rng.uniform(-3, 3, size=n)
    pts[:, 3] = rng.integers(0, 256, size=n)
    pts[:, 4] = rng.integers(0, 32, size=n)
    return pts


def _naive_slices(points, n, start_deg, duration, lag=0.0, clockwise=False):
    """Membership in the scan layout's order (clockwise: slice k is the counter-clockwise sector n - 1 - k); the time
    and index features counted counter-clockwise from +x whatever the layout."""
    out = [[] for _ in range(n)]
    for p in points:
        az = math.degrees(math.atan2(float(p[1]), float(p[0]))) % 360.0
        off = (az - start_deg) % 360.0
        j = min(int(off // (360.0 / n)), n - 1)
        k = n - 1 - j if clockwise else j
        feature = min(int(az // (360.0 / n)), n - 1)
        out[k].append([p[0], p[1], p[2], p[3] / 255.0, az / 360.0 * duration + lag, feature])
    return [np.array(s, dtype=np.float64).reshape(-1, 6) for s in out]


def _naive_corners(box):
    x, y, _, w, l, _, yaw = box[:7]
    out = []
    for lx, ly in ((l / 2, w / 2), (-l / 2, w / 2), (-l / 2, -w / 2), (l / 2, -w / 2)):
        out.append((x + math.cos(yaw) * lx - math.sin(yaw) * ly, y + math.sin(yaw) * lx + math.cos(yaw) * ly))
    return out


def _in_sector(x, y, k, n, start_deg):
    lo, _ = sector_bounds_deg(k, n, start_deg)
    off = (math.degrees(math.atan2(y, x)) - lo) % 360.0
    return off < 360.0 / n


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("clockwise", [False, True])
@pytest.mark.parametrize("n,start_deg", [(1, 0.0), (2, 0.0), (2, 90.0), (4, 90.0), (8, 0.0), (16, 270.0), (12, 180.0)])
def test_split_sweep_matches_naive(seed, n, start_deg, clockwise):
    pts = _random_sweep(seed, 800)
    got = split_sweep(pts, n, start_deg, clockwise=clockwise)
    ref = _naive_slices(pts, n, start_deg, SWEEP_DURATION_S, clockwise=clockwise)
    assert len(got) == n
    for k in range(n):
        assert got[k].dtype == np.float32 and got[k].shape[1] == 6
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_slices_partition_the_sweep_and_lie_in_their_sector(seed):
    pts = _random_sweep(seed)
    slices = split_sweep(pts, 8)
    assert sum(len(s) for s in slices) == len(pts)
    for k, s in enumerate(slices):
        lo, hi = sector_bounds_deg(k, 8)
        az = np.degrees(np.arctan2(s[:, 1], s[:, 0])) % 360.0
        assert np.all((az >= lo - 1e-4) & (az < hi + 1e-4)), k
        assert np.all(s[:, 5] == k)
        # relative time lies in the slice's share of the sweep
        assert np.all(s[:, 4] >= k * SWEEP_DURATION_S / 8 - 1e-6) and np.all(s[:, 4] <= (k + 1) * SWEEP_DURATION_S / 8 + 1e-6)
    # input order is kept inside a slice
    first = split_sweep(pts, 8)[3]
    rows = [np.flatnonzero(np.all(pts[:, :3] == r[:3], axis=1))[0] for r in first[:50]]
    assert rows == sorted(rows)


def test_relative_time_rises_with_azimuth():
    az = np.linspace(0.0, 359.9, 500)
    pts = np.stack([np.cos(np.radians(az)) * 10, np.sin(np.radians(az)) * 10], axis=1)
    t = relative_time_s(pts, start_deg=0.0)
    assert np.all(np.diff(t) > 0)
    t90 = relative_time_s(pts, start_deg=90.0)
    assert t90.argmin() == np.searchsorted(az, 90.0)


def test_time_lag_is_added_for_past_sweeps():
    pts = _random_sweep(3, 200)
    now = np.concatenate(split_sweep(pts, 4))
    past = np.concatenate(split_sweep(pts, 4, time_lag_s=0.25))
    np.testing.assert_allclose(past[:, 4] - now[:, 4], 0.25, atol=1e-6)
    lag = np.linspace(0, 0.4, len(pts))
    per_point = split_sweep(pts, 1, time_lag_s=lag)[0]
    np.testing.assert_allclose(per_point[:, 4] - relative_time_s(pts), lag, atol=1e-6)  # n = 1 keeps the input order
    with pytest.raises(ValueError, match="time_lag_s"):
        split_sweep(pts, 4, time_lag_s=np.zeros(3))


def test_split_sweep_empty_and_malformed():
    empty = split_sweep(np.zeros((0, 5), dtype=np.float32), 8)
    assert len(empty) == 8 and all(s.shape == (0, 6) for s in empty)
    with pytest.raises(ValueError, match="slices"):
        split_sweep(_random_sweep(0, 10), 3)
    with pytest.raises(ValueError, match="multiple of 90"):
        split_sweep(_random_sweep(0, 10), 8, start_deg=30.0)
    with pytest.raises(ValueError, match=r"\(N, 5\)"):
        split_sweep(np.zeros((10, 3), dtype=np.float32), 8)
    with pytest.raises(ValueError, match="float"):
        split_sweep(np.zeros((10, 5), dtype=np.int32), 8)
    with pytest.raises(ValueError, match="sweep_duration_s"):
        split_sweep(_random_sweep(0, 10), 8, sweep_duration_s=0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n,start_deg", [(4, 0.0), (8, 0.0), (8, 180.0), (32, 0.0), (2, 90.0)])
def test_boxes_in_sector_matches_naive(seed, n, start_deg):
    rng = np.random.default_rng(seed)
    m = 150
    boxes = np.zeros((m, 9))
    boxes[:, :2] = rng.uniform(-30, 30, size=(m, 2))
    boxes[:, 3:6] = rng.uniform(0.3, 8.0, size=(m, 3))
    boxes[:, 6] = rng.uniform(-math.pi, math.pi, size=m)
    for k in range(n):
        got = boxes_in_sector(boxes, k, n, start_deg)
        ref = [
            any(_in_sector(x, y, k, n, start_deg) for x, y in _naive_corners(b) + [(b[0], b[1])]) for b in boxes
        ]
        np.testing.assert_array_equal(got, ref)


def test_box_across_a_boundary_belongs_to_both_slices():
    box = np.array([[10.0, 0.0, 0.0, 2.0, 4.0, 1.5, math.pi / 2, 0.0, 0.0]])  # straddles azimuth 0
    assert boxes_in_sector(box, 0, 8)[0] and boxes_in_sector(box, 7, 8)[0]
    assert not boxes_in_sector(box, 3, 8)[0]
    assert boxes_in_sector(np.zeros((0, 9)), 0, 8).shape == (0,)
    with pytest.raises(ValueError, match=r"\(M, 9\)"):
        boxes_in_sector(np.zeros((3, 7)), 0, 8)
    with pytest.raises(ValueError, match="slice index"):
        boxes_in_sector(box, 8, 8)
    with pytest.raises(ValueError, match="slices"):
        boxes_in_sector(box, 0, 3)


def test_slice_sample_on_the_real_sample():
    sample = load_bundled_sample()
    slices = slice_sample(sample, 8)
    assert [s.index for s in slices] == list(range(8))
    assert sum(len(s.points) for s in slices) == len(sample.points)
    covered = np.zeros(len(sample.gt_boxes), dtype=bool)
    for s in slices:
        assert s.quadrants == (s.index // 2,)
        assert 1 <= len(s.camera_names) <= 3 and set(s.camera_names) <= set(sample.rig.names)
        np.testing.assert_array_equal(s.gt_boxes, sample.gt_boxes[s.gt_indices])
        np.testing.assert_array_equal(s.gt_labels, sample.gt_labels[s.gt_indices])
        covered[s.gt_indices] = True
        # every box whose centre is in the sector is in the slice
        lo, _ = s.sector_deg
        az = (np.degrees(np.arctan2(sample.gt_boxes[:, 1], sample.gt_boxes[:, 0])) - lo) % 360.0
        assert set(np.flatnonzero(az < 45.0)) <= set(s.gt_indices.tolist())
    assert covered.all()
    # the front camera (lidar +y) sees the slices around azimuth 90 deg
    assert "CAM_FRONT" in slices[2].camera_names and "CAM_BACK" in slices[6].camera_names


@pytest.mark.parametrize("n", [1, 2, 8, 32])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_point_without_azimuth_is_in_no_slice_on_every_platform(n, seed):
    """x or y NaN: the slice index was a float-to-int cast of NaN (INT64_MIN on x86, 0 on ARM, with a warning);
    now -1, and split_sweep leaves the point out as eval always did on x86. Other non-finite values keep their slice."""
    import warnings

    from streamdet.core.sectors import slice_index_of

    rng = np.random.default_rng(seed)
    pts = np.zeros((40, 5), np.float32)
    pts[:, :3] = rng.uniform(-30, 30, (40, 3))
    pts[:, 3] = rng.uniform(0, 255, 40)
    pts[3, 0] = np.nan
    pts[7, 1] = np.nan
    pts[11, 2] = np.nan  # z only: it has an azimuth
    pts[13, 0] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "invalid value encountered in cast"
        k = slice_index_of(pts[:, 0], pts[:, 1], n)
        slices = split_sweep(pts, n)
    assert k[3] == k[7] == -1 and ((k >= 0) & (k < n)).sum() == 38
    naive = [[i for i in range(40) if k[i] == j] for j in range(n)]  # the reference: by index, input order
    for j, s in enumerate(slices):
        np.testing.assert_array_equal(s[:, :3], pts[naive[j], :3])
    assert sum(len(s) for s in slices) == 38
