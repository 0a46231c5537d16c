"""Which cameras overlap which slice (calibration/sectors.py), against brute-force sampling."""

from __future__ import annotations

from importlib.resources import files

import numpy as np
import pytest

from streamdet.calibration import (
    Camera,
    Rig,
    camera_sees_sector,
    cameras_overlapping_sector,
    intervals_overlap_deg,
    make_transform,
    sector_bounds_deg,
    sector_camera_table,
)

SAMPLE = files("streamdet.data") / "nuscenes_sample"


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(SAMPLE / "calibration.json")


def _naive_sees(cam: Camera, k: int, n: int, start_deg: float) -> bool:
    """Scan the sector's directions (0.05 deg, elevations +-30 deg) for one that lands in the image at infinity."""
    lo, hi = sector_bounds_deg(k, n, start_deg)
    az = np.radians(np.arange(lo + 0.025, hi, 0.05))
    el = np.radians(np.linspace(-30, 30, 31))
    aa, ee = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], -1).reshape(-1, 3)
    pc = d @ cam.lidar2cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (pc @ cam.K.T)[:, 0] / pc[:, 2]
        v = (pc @ cam.K.T)[:, 1] / pc[:, 2]
    return bool(np.any((pc[:, 2] > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)))


@pytest.mark.parametrize("n", [1, 2, 4, 8, 16])
def test_matches_brute_force(rig: Rig, n: int) -> None:
    for k in range(n):
        expected = tuple(c.name for c in rig.cameras if _naive_sees(c, k, n, 0.0))
        assert cameras_overlapping_sector(rig, k, n) == expected, (k, n)


def test_eight_slices_on_the_real_rig(rig: Rig) -> None:
    table = sector_camera_table(rig, 8)
    assert all(1 <= len(names) <= 3 for names in table), table
    assert set().union(*table) == set(rig.names)
    for names in table:  # rig order is kept
        assert list(names) == [n for n in rig.names if n in names]
    assert cameras_overlapping_sector(rig, 0, 1) == rig.names
    # the front camera looks along lidar +y (azimuth 90): slices [45, 90) and [90, 135)
    assert [k for k, names in enumerate(table) if "CAM_FRONT" in names] == [1, 2]


def test_start_angle_rotates_the_table(rig: Rig) -> None:
    base = sector_camera_table(rig, 8)
    shifted = sector_camera_table(rig, 8, start_deg=90.0)
    assert shifted == base[2:] + base[:2]


def test_bad_slice_arguments(rig: Rig) -> None:
    with pytest.raises(ValueError, match="slice index"):
        cameras_overlapping_sector(rig, 8, 8)
    with pytest.raises(ValueError, match="multiple of 4"):
        cameras_overlapping_sector(rig, 0, 6)
    with pytest.raises(ValueError, match="max_range_m"):
        cameras_overlapping_sector(rig, 0, 8, max_range_m=-1.0)


def _naive_overlap(a, b) -> bool:
    """Integer-degree intervals: compare the sets of whole degrees [d, d + 1) they cover on the circle."""
    def cells(lo, hi):
        return {int(x) % 360 for x in np.arange(lo, hi)}
    return bool(cells(*a) & cells(*b))


@pytest.mark.parametrize("seed", range(5))
def test_interval_overlap_matches_naive(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(300):
        a_lo, b_lo = rng.integers(-400, 800, size=2)
        a_w, b_w = rng.integers(1, 400, size=2)
        a, b = (float(a_lo), float(a_lo + a_w)), (float(b_lo), float(b_lo + b_w))
        assert intervals_overlap_deg(a, b) == _naive_overlap(a, b), (a, b)
        assert intervals_overlap_deg(b, a) == intervals_overlap_deg(a, b)


def test_touching_intervals_do_not_overlap() -> None:
    assert not intervals_overlap_deg((0.0, 45.0), (45.0, 90.0))
    assert not intervals_overlap_deg((315.0, 360.0), (0.0, 10.0))
    assert intervals_overlap_deg((315.0, 360.5), (0.0, 10.0))


def _offset_camera() -> Camera:
    """A camera 10 m to the right of the LiDAR (x = 10), looking along +y with a +-10 deg horizontal FoV."""
    fx = 500.0 / np.tan(np.radians(10.0))  # half the 1000 px width spans 10 deg
    K = np.array([[fx, 0, 500.0], [0, 500.0, 250.0], [0, 0, 1]])
    # camera axes in the lidar frame: x_cam = +x, y_cam = -z (down), z_cam = +y (forward)
    cam2lidar = make_transform(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), [10.0, 0.0, 0.0])
    lidar2cam = np.linalg.inv(cam2lidar)
    return Camera("OFFSET", K, lidar2cam, 1000, 500)


def _naive_sees_within_range(cam: Camera, k: int, n: int, max_range_m: float) -> bool:
    lo, hi = sector_bounds_deg(k, n)
    az = np.radians(np.arange(lo + 0.05, hi, 0.1))
    r = np.linspace(0.1, max_range_m, 400)
    rr, aa = np.meshgrid(r, az, indexing="ij")
    pts = np.stack([rr * np.cos(aa), rr * np.sin(aa), np.full_like(rr, cam.center_lidar[2])], -1).reshape(-1, 3)
    return bool(cam.visible(pts).any())


def test_finite_range_uses_the_camera_position() -> None:
    cam = _offset_camera()
    lo, hi = cam.fov_azimuth_deg
    np.testing.assert_allclose([lo, hi], [80.0, 100.0], atol=1e-9)
    rig = Rig((cam,), np.eye(4), np.eye(4))
    # directions only: the wedge [80, 100) touches slices 1 and 2 of 8
    assert [k for k in range(8) if camera_sees_sector(cam, k, 8)] == [1, 2]
    # within 30 m, seen from the LiDAR the wedge lies at x in [5, 15], azimuths up to ~80 deg: slices 0 and 1
    near = [k for k in range(8) if cameras_overlapping_sector(rig, k, 8, max_range_m=30.0)]
    assert near == [k for k in range(8) if _naive_sees_within_range(cam, k, 8, 30.0)] == [0, 1]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_angle_diff_deg_against_a_naive_reference(seed, dtype):
    from streamdet.core.sectors import angle_diff_deg

    rng = np.random.default_rng(seed)
    a = rng.uniform(-1000, 1000, 200).astype(dtype)
    b = rng.uniform(-1000, 1000, 200).astype(dtype)
    got = angle_diff_deg(a, b)
    for x, y, d in zip(a.astype(float), b.astype(float), got.astype(float)):
        naive = x - y
        while naive >= 180.0:
            naive -= 360.0
        while naive < -180.0:
            naive += 360.0
        assert -180.0 <= d < 180.0 + 1e-3
        assert min(abs(d - naive), 360.0 - abs(d - naive)) < (1e-9 if dtype is np.float64 else 1e-3)
    assert angle_diff_deg(10.0, 350.0) == 20.0 and angle_diff_deg(350.0, 10.0) == -20.0 and angle_diff_deg(180.0, 0.0) == -180.0
    assert angle_diff_deg(np.zeros(0), 5.0).shape == (0,)
