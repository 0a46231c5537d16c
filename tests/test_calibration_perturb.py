"""Seeded extrinsic perturbation (calibration/perturb.py)."""

from __future__ import annotations

from importlib.resources import files

import numpy as np
import pytest

from streamdet.calibration import GridSpec, Rig, build_lut, euler_to_matrix, matrix_to_euler, perturb_rig

SAMPLE = files("streamdet.data") / "nuscenes_sample"


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(SAMPLE / "calibration.json")


def _naive_euler_matrix(a: float, b: float, c: float) -> np.ndarray:
    """Rotate about x by a, then about the fixed y by b, then the fixed z by c, applied to each basis vector."""
    def rot(axis: int, angle: float, p: np.ndarray) -> np.ndarray:
        i, j = [k for k in range(3) if k != axis]
        out = p.copy()
        sign = -1.0 if axis == 1 else 1.0  # right-handed about y: z -> x
        out[i] = np.cos(angle) * p[i] - sign * np.sin(angle) * p[j]
        out[j] = sign * np.sin(angle) * p[i] + np.cos(angle) * p[j]
        return out

    cols = [rot(2, c, rot(1, b, rot(0, a, e))) for e in np.eye(3)]
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("seed", range(4))
def test_euler_round_trip_and_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-1.2, 1.2, size=3)
    R = euler_to_matrix(angles)
    np.testing.assert_allclose(R, _naive_euler_matrix(*angles), atol=1e-12)
    np.testing.assert_allclose(matrix_to_euler(R), angles, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_seeded_determinism(rig: Rig, seed: int) -> None:
    a = perturb_rig(rig, 1.0, 0.1, seed)
    b = perturb_rig(rig, 1.0, 0.1, seed)
    assert a == b and a.sha256() == b.sha256()
    assert perturb_rig(rig, 1.0, 0.1, seed + 100) != a
    assert a.names == rig.names
    for new, old in zip(a.cameras, rig.cameras):
        np.testing.assert_array_equal(new.K, old.K)
        assert (new.width, new.height, new.timestamp_us) == (old.width, old.height, old.timestamp_us)
    np.testing.assert_array_equal(a.lidar2ego, rig.lidar2ego)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("max_angle_deg, max_translation_m", [(1.0, 0.1), (5.0, 0.5), (0.0, 0.3), (2.0, 0.0)])
def test_bounds_respected(rig: Rig, seed: int, max_angle_deg: float, max_translation_m: float) -> None:
    noisy = perturb_rig(rig, max_angle_deg, max_translation_m, seed)
    for new, old in zip(noisy.cameras, rig.cameras):
        noise = new.lidar2cam @ np.linalg.inv(old.lidar2cam)  # N in lidar2cam' = N @ lidar2cam
        angles = np.degrees(matrix_to_euler(noise[:3, :3]))
        assert np.all(np.abs(angles) <= max_angle_deg + 1e-9), angles
        assert np.all(np.abs(noise[:3, 3]) <= max_translation_m + 1e-9), noise[:3, 3]
        if max_angle_deg:
            assert np.abs(angles).max() > 0
        np.testing.assert_allclose(noise[3], [0, 0, 0, 1], atol=1e-12)


def test_angles_fill_the_range(rig: Rig) -> None:
    """Over many seeds the draws cover [-a, a] roughly uniformly, not a narrower band."""
    draws = []
    for seed in range(40):
        noisy = perturb_rig(rig, 3.0, 0.2, seed)
        for new, old in zip(noisy.cameras, rig.cameras):
            draws.append(np.degrees(matrix_to_euler((new.lidar2cam @ np.linalg.inv(old.lidar2cam))[:3, :3])))
    draws = np.array(draws)  # (240, 3)
    assert draws.min() < -2.7 and draws.max() > 2.7
    assert np.abs(draws.mean(axis=0)).max() < 0.5


def test_zero_bounds_are_identity(rig: Rig) -> None:
    same = perturb_rig(rig, 0.0, 0.0, seed=7)
    assert same == rig and same.sha256() == rig.sha256()


def test_one_degree_changes_the_lut(rig: Rig) -> None:
    grid = GridSpec(voxel_xy_m=1.6)  # 64 x 64 x 16: enough to see the shift, fast
    clean = build_lut(rig, grid)
    noisy = build_lut(perturb_rig(rig, 1.0, 0.0, seed=0), grid)
    assert noisy.calibration_sha256 != clean.calibration_sha256
    changed = (noisy.index != clean.index).mean()
    assert 0.05 < changed < 0.9, changed  # ~20 px at 1 deg moves many voxels by a stride-4 cell, not all


@pytest.mark.parametrize(
    "angle, shift, pattern",
    [(-1.0, 0.1, "max_angle_deg"), (float("nan"), 0.1, "max_angle_deg"), (180.0, 0.1, "max_angle_deg"),
     (1.0, -0.1, "max_translation_m"), (1.0, float("inf"), "max_translation_m"), (True, 0.1, "max_angle_deg")],
)
def test_bad_bounds(rig: Rig, angle, shift, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        perturb_rig(rig, angle, shift, seed=0)
