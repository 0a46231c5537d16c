"""core/rotations.py against naive references: Rodrigues' formula, the Hamilton product, explicit Rz(yaw)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from streamdet.core.rotations import (
    matrix_to_quaternion,
    matrix_to_yaw,
    quaternion_to_matrix,
    quaternion_to_yaw,
    yaw_to_quaternion,
)
from streamdet.evaluation.detection_eval import quaternion_yaw as devkit_quaternion_yaw


def _rodrigues(q: np.ndarray) -> np.ndarray:
    """The rotation of a unit quaternion as an axis-angle turn (naive, one quaternion at a time)."""
    w, v = q[0], q[1:]
    s = np.linalg.norm(v)
    if s == 0.0:
        return np.eye(3)
    angle = 2.0 * np.arctan2(s, w)
    k = v / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])  # fmt: skip


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def _unit_quaternions(seed: int, n: int = 256) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    # Each Shepperd branch at its extreme: identity and the three 180-degree turns (w = 0), and turns near them.
    q[:4] = np.eye(4)
    q[4:8] = np.eye(4) + 1e-9 * rng.normal(size=(4, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", range(4))
def test_quaternion_to_matrix_is_rodrigues(seed):
    q = _unit_quaternions(seed)
    r = quaternion_to_matrix(q)
    assert r.shape == (len(q), 3, 3) and r.dtype == np.float64
    for qi, ri in zip(q, r):
        np.testing.assert_allclose(ri, _rodrigues(qi), atol=1e-12)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_matrices_compose_as_the_hamilton_product(seed):
    q = _unit_quaternions(seed, 64)
    a, b = q[:32], q[32:]
    ab = np.stack([_hamilton(x, y) for x, y in zip(a, b)])
    np.testing.assert_allclose(quaternion_to_matrix(ab), quaternion_to_matrix(a) @ quaternion_to_matrix(b), atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_matrix_to_quaternion_round_trip_with_w_non_negative(seed):
    q = _unit_quaternions(seed)
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    # q and -q are one rotation; with w = 0 the sign is free.
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(back), quaternion_to_matrix(q), atol=1e-12)


def test_quaternion_to_matrix_normalises():
    q = np.array([2.0, 0.0, 0.0, 2.0])  # 90 degrees about z, norm 2.83
    np.testing.assert_allclose(quaternion_to_matrix(q), _rz(np.pi / 2), atol=1e-15)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_stacks_and_dtypes(dtype):
    q = _unit_quaternions(0, 24).reshape(2, 3, 4, 4).astype(dtype)
    r = quaternion_to_matrix(q)
    assert r.shape == (2, 3, 4, 3, 3) and r.dtype == np.float64
    assert matrix_to_quaternion(r).shape == (2, 3, 4, 4)
    assert quaternion_to_yaw(q).shape == matrix_to_yaw(r).shape == (2, 3, 4)
    yaws = np.zeros((2, 5), dtype=dtype)
    assert yaw_to_quaternion(yaws).shape == (2, 5, 4) and yaw_to_quaternion(yaws).dtype == np.float64


def test_empty_stacks():
    assert quaternion_to_matrix(np.zeros((0, 4))).shape == (0, 3, 3)
    assert matrix_to_quaternion(np.zeros((0, 3, 3))).shape == (0, 4)
    assert yaw_to_quaternion(np.zeros(0)).shape == (0, 4)
    assert quaternion_to_yaw(np.zeros((0, 4))).shape == (0,)
    assert matrix_to_yaw(np.zeros((0, 3, 3))).shape == (0,)


def test_scalar_yaw():
    q = yaw_to_quaternion(0.5)
    assert q.shape == (4,)
    np.testing.assert_array_equal(q, [np.cos(0.25), 0.0, 0.0, np.sin(0.25)])


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=-20.0, max_value=20.0, allow_nan=False))
def test_yaw_round_trips(yaw):
    q = yaw_to_quaternion(yaw)
    np.testing.assert_allclose(quaternion_to_matrix(q), _rz(yaw), atol=1e-12)
    # Compare on the circle: a yaw of pi may come back as -pi.
    assert abs(_wrap(quaternion_to_yaw(q) - yaw)) < 1e-12
    assert abs(_wrap(matrix_to_yaw(_rz(yaw)) - yaw)) < 1e-12


@pytest.mark.parametrize("seed", range(3))
def test_yaw_agrees_with_the_devkit_route(seed):
    """The closed form and the matrix's yaw are the devkit's quaternion_yaw (which scoring keeps bit-exact)."""
    q = _unit_quaternions(seed)
    want = devkit_quaternion_yaw(q)
    np.testing.assert_allclose(_wrap(quaternion_to_yaw(q) - want), 0.0, atol=1e-12)
    np.testing.assert_allclose(_wrap(matrix_to_yaw(quaternion_to_matrix(q)) - want), 0.0, atol=1e-12)
