"""Pinhole projection of LiDAR points into an image (numpy only); the formula the LUT and the devkit share."""

from __future__ import annotations

import numpy as np


def project_points(points_lidar: np.ndarray, K: np.ndarray, lidar2cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) float64 and depths (N,) float64 of (N, 3+) points (extra columns, e.g. intensity, ignored).

    ``p = R x + t``, ``(u, v) = (K p)_{0,1} / p_z``, depth ``p_z``. Points at or behind the camera plane get
    meaningless (u, v) (inf or mirrored); callers mask them with ``depth > min_depth``.
    """
    pts = np.asarray(points_lidar)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points_lidar: expected shape (N, 3) or (N, 3+k), got {pts.shape}")
    xyz = pts[:, :3].astype(np.float64)  # (N, 3)
    cam = xyz @ lidar2cam[:3, :3].T + lidar2cam[:3, 3]  # (N, 3) camera frame
    hom = cam @ K.T  # (N, 3) = (u z, v z, z)
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = hom[:, :2] / hom[:, 2:3]  # (N, 2)
    return uv, depth


def visible_mask(uv: np.ndarray, depth: np.ndarray, width: int, height: int, min_depth_m: float = 0.0) -> np.ndarray:
    """(N,) bool: depth > min_depth_m and 0 <= u < width and 0 <= v < height (half-open pixel extent)."""
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        return (depth > min_depth_m) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
