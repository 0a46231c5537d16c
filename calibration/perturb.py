"""Seeded camera-LiDAR miscalibration, as in the paper's robustness study (Sec. "On Calibration").

Per camera, three Euler angles and a translation are drawn uniformly within +-bounds and the resulting rigid
transform N = [R | t] is applied to the extrinsic in the camera frame: ``lidar2cam' = N @ lidar2cam``, the way a
mount that moved would: the camera turns about its own optical centre, and the points' camera coordinates shift by
t (its centre moves by -R^T t in its old axes: the same size, and as the draws are symmetric, the same spread).
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.calibration.camera import Camera, Rig


def euler_to_matrix(angles_rad: np.ndarray) -> np.ndarray:
    """(3, 3) rotation ``Rz(c) @ Ry(b) @ Rx(a)`` of angles (a, b, c) about the x, y, z axes (radians)."""
    a, b, c = (float(x) for x in np.asarray(angles_rad, dtype=np.float64).reshape(3))
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return rz @ ry @ rx


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) in radians with ``R = Rz(c) @ Ry(b) @ Rx(a)``, b in [-pi/2, pi/2] (inverse of euler_to_matrix)."""
    R = np.asarray(R, dtype=np.float64)
    b = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    a = math.atan2(R[2, 1], R[2, 2])
    c = math.atan2(R[1, 0], R[0, 0])
    return np.array([a, b, c])


def perturb_rig(rig: Rig, max_angle_deg: float, max_translation_m: float, seed: int) -> Rig:
    """The rig with every camera's extrinsic disturbed by seeded uniform noise.

    Per camera in rig order: angles about the camera's x, y, z axes each uniform in [-max_angle_deg,
    max_angle_deg], translation each axis uniform in [-max_translation_m, max_translation_m] (camera frame),
    from ``numpy.random.default_rng(seed)``. Zero bounds return an identical rig.
    """
    for name, value, limit in (("max_angle_deg", max_angle_deg, 180.0), ("max_translation_m", max_translation_m, math.inf)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0.0 <= value < limit) or math.isnan(value):
            raise ValueError(f"{name} must be a finite number in [0, {limit}), got {value!r}")
    if max_angle_deg == 0 and max_translation_m == 0:
        return rig
    rng = np.random.default_rng(seed)
    cameras = []
    for cam in rig.cameras:
        angles = np.radians(rng.uniform(-max_angle_deg, max_angle_deg, size=3))
        shift = rng.uniform(-max_translation_m, max_translation_m, size=3)
        noise = np.eye(4)
        noise[:3, :3] = euler_to_matrix(angles)
        noise[:3, 3] = shift
        cameras.append(Camera(cam.name, cam.K, noise @ cam.lidar2cam, cam.width, cam.height, cam.timestamp_us))
    return Rig(tuple(cameras), rig.lidar2ego, rig.ego2global)
