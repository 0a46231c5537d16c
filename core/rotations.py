"""Rotations, defined once: quaternions, rotation matrices and yaw (numpy only).

Conventions (nuScenes and pyquaternion use the same):

- a quaternion is ``(w, x, y, z)``, scalar first, Hamilton product; it rotates a column vector ``v`` as
  ``R @ v`` with ``R = quaternion_to_matrix(q)``;
- a unit quaternion and its negation are the same rotation; ``matrix_to_quaternion`` returns the one with ``w >= 0``;
- yaw is the angle about +z in radians, counter-clockwise seen from above (x towards y), as in the box layout
  (``core/boxes.py``).

Every function takes stacks: ``(..., 4)`` quaternions, ``(..., 3, 3)`` matrices, ``(...)`` yaws. They check
nothing: the readers of calibration (``calibration/camera.py``) and of boxes check norms and orthonormality
where a value enters, and name the field.

Scoring keeps its own devkit-exact yaw (``evaluation/detection_eval.py``): the devkit's route through
pyquaternion, reproduced bit for bit, decides ties exactly as the devkit does.
"""

from __future__ import annotations

import numpy as np


def quaternion_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)  # (..., 3, 3)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Four algebraically equal forms (each 4 * q * its leading component); the one whose leading term is largest
    # never divides by a number near 0, at any angle.
    cand = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1),
            np.stack([r[..., 2, 1] - r[..., 1, 2], 1 + m00 - m11 - m22, r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),
            np.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 1 - m00 + m11 - m22, r[..., 1, 2] + r[..., 2, 1]], -1),
            np.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 forms, 4)
    best = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], -1), axis=-1)  # (...)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]  # (..., 4)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def yaw_to_quaternion(yaw: np.ndarray | float) -> np.ndarray:
    """(...) yaws -> (..., 4) quaternions of the rotation about +z, ``(cos(yaw / 2), 0, 0, sin(yaw / 2))``.

    The half angle is not wrapped: a yaw beyond pi gives w < 0, the same rotation (pyquaternion's axis-angle agrees).
    """
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zeros = np.zeros_like(half)
    return np.stack([np.cos(half), zeros, zeros, np.sin(half)], axis=-1)


def quaternion_to_yaw(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (...) yaw in [-pi, pi] (arctan2: a -0.0 numerator gives -pi): the heading of the rotated x axis in the x-y plane."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def matrix_to_yaw(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (...) yaw in [-pi, pi] (arctan2: a -0.0 numerator gives -pi): the heading of the rotated x axis."""
    r = np.asarray(r, dtype=np.float64)
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])
