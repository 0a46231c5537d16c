"""Projection against the official nuScenes devkit output bundled with the sample (CAM_FRONT)."""

from __future__ import annotations

from importlib.resources import files

import numpy as np
import pytest

from streamdet.calibration import Rig, project_points, visible_mask

SAMPLE = files("streamdet.data") / "nuscenes_sample"


@pytest.fixture(scope="module")
def sweep() -> np.ndarray:
    (path,) = [p for p in SAMPLE.iterdir() if "LIDAR_TOP" in p.name and p.name.endswith(".pcd.bin")]
    return np.frombuffer(path.read_bytes(), dtype=np.float32).reshape(-1, 5)  # (N, 5) x, y, z, intensity, ring


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(SAMPLE / "calibration.json")


def test_reproduces_devkit_cam_front(sweep: np.ndarray, rig: Rig) -> None:
    ref = np.load(SAMPLE / "cam_front_projection_devkit.npz")
    cam = rig.camera("CAM_FRONT")
    uv, depth = cam.project(sweep)
    # map_pointcloud_to_image keeps depth > 1 m and a strict 1 px margin inside the image
    u, v = uv[:, 0], uv[:, 1]
    kept = (depth > 1.0) & (u > 1) & (u < cam.width - 1) & (v > 1) & (v < cam.height - 1)
    np.testing.assert_array_equal(np.flatnonzero(kept), ref["point_index"])
    idx = ref["point_index"]
    assert np.abs(u[idx] - ref["u"]).max() < 0.05
    assert np.abs(v[idx] - ref["v"]).max() < 0.05
    assert np.abs(depth[idx] - ref["depth"]).max() < 1e-3
    # without the devkit's margin and 1 m cut, the README counts 3,067 points in the image
    assert int(cam.visible(sweep).sum()) == 3067


def test_visible_counts_of_all_cameras(sweep: np.ndarray, rig: Rig) -> None:
    """README: points landing inside each 1600x900 image with depth > 0."""
    expected = {"CAM_FRONT": 3067, "CAM_FRONT_RIGHT": 3079, "CAM_FRONT_LEFT": 3704,
                "CAM_BACK": 4826, "CAM_BACK_LEFT": 4097, "CAM_BACK_RIGHT": 3379}
    for cam in rig.cameras:
        assert abs(int(cam.visible(sweep).sum()) - expected[cam.name]) <= 2, cam.name


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_project_points_matches_homogeneous_matrix(rig: Rig, seed: int, dtype) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-50, 50, size=(500, 3)).astype(dtype)
    for cam in rig.cameras:
        uv, depth = project_points(pts, cam.K, cam.lidar2cam)
        hom = np.c_[pts.astype(np.float64), np.ones(len(pts))] @ cam.projection_matrix.T  # (N, 3)
        front = hom[:, 2] > 1e-3
        np.testing.assert_allclose(uv[front], hom[front, :2] / hom[front, 2:], rtol=1e-9, atol=1e-7)
        np.testing.assert_allclose(depth, hom[:, 2], atol=1e-9)


def test_visible_mask_edges() -> None:
    uv = np.array([[0.0, 0.0], [1599.999, 899.999], [1600.0, 10.0], [10.0, 900.0], [-1e-9, 5.0], [5.0, 5.0], [np.nan, 5.0]])
    depth = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0])
    np.testing.assert_array_equal(visible_mask(uv, depth, 1600, 900), [True, True, False, False, False, False, False])
