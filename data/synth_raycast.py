"""Vectorised ray casting against the ground plane and oriented boxes (the geometry of the synthetic sensors).

Both the LiDAR and the cameras use these two functions, so a point and a pixel see the same surface.
Rays are ``origin + t * direction`` with unit directions, so ``t`` is a distance in metres.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def ray_box_entry(
    origins_local: np.ndarray, dirs_local: np.ndarray, half_extent: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slab test of rays against axis-aligned boxes centred at the origin of their local frame.

    origins_local, dirs_local: (P, 3) in the box frame; half_extent: (P, 3) or (3,) half sizes along x, y, z.
    Returns ``hit`` (P,) bool, ``t`` (P,) entry distance (inf where no hit), ``axis`` (P,) int64 of the entered
    face (0: +-x, 1: +-y, 2: +-z) and ``sign`` (P,) float64 (+1 / -1: which of the two faces, its outward
    normal is ``sign * e_axis``). A ray starting inside a box does not hit it (the sensor is never inside one).
    """
    o = np.asarray(origins_local)
    d = np.asarray(dirs_local)
    half = np.asarray(half_extent)
    d_safe = np.where(np.abs(d) < _EPS, _EPS, d)
    inv = 1.0 / d_safe
    t1 = (-half - o) * inv  # (P, 3)
    t2 = (half - o) * inv
    t_near = np.minimum(t1, t2)
    t_far = np.maximum(t1, t2, out=t1).min(axis=1)
    axis = np.argmax(t_near, axis=1)  # the last slab entered is the face the ray crosses
    t_near = t_near.max(axis=1)
    hit = (t_near <= t_far) & (t_near > 0.0)
    sign = -np.sign(d_safe[np.arange(len(axis)), axis])
    return hit, np.where(hit, t_near, np.inf), axis, sign


def ray_ground(origins: np.ndarray, dirs: np.ndarray, ground_z_m: float = 0.0) -> np.ndarray:
    """(P,) distance to the plane z = ground_z along each ray (inf for rays that never reach it)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    dz = d[..., 2]
    down = dz < -1e-9
    t = np.where(down, (ground_z_m - o[..., 2]) / np.where(down, dz, -1.0), np.inf)
    return np.where(t > 0, t, np.inf)


def world_to_local(points: np.ndarray, centers: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """(P, 3) points (or directions, with centers 0) in the frames of boxes rotated by yaw about z."""
    rel = np.asarray(points, dtype=np.float64) - centers
    c, s = np.cos(yaws), np.sin(yaws)
    return np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], axis=-1)


def local_normals(axis: np.ndarray, sign: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """(P, 3) outward face normals in the world frame from ``ray_box_entry``'s axis / sign and the box yaw."""
    n_local = np.zeros(axis.shape + (3,))
    np.put_along_axis(n_local, axis[..., None], sign[..., None], axis=-1)
    c, s = np.cos(yaws), np.sin(yaws)
    return np.stack([c * n_local[..., 0] - s * n_local[..., 1], s * n_local[..., 0] + c * n_local[..., 1], n_local[..., 2]], axis=-1)
