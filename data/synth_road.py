"""The street layout of the synthetic world (lateral offsets from a road's centre line) and the ground's height.

A scene has a main road (the ego drives along it) and, in most scenes, a cross street meeting it at an
intersection. Offsets are metres to the left of the road direction. The ground is not a plane: a gentle
undulation of a few centimetres (drainage slopes, patches) that the LiDAR sees; the cameras draw the ground as the
plane z = 0 (the undulation is below a pixel at the rendered resolutions) and objects stand on the true ground.
"""

from __future__ import annotations

import math

import numpy as np

LANE_WIDTH_M = 3.5
LANE_OFFSETS_M = (-1.5 * LANE_WIDTH_M, -0.5 * LANE_WIDTH_M, 0.5 * LANE_WIDTH_M, 1.5 * LANE_WIDTH_M)
EGO_LANE_M = LANE_OFFSETS_M[1]  # the inner lane along +u
PARKING_OFFSET_M = 7.6
ROAD_HALF_WIDTH_M = 8.5
SIDEWALK_OUTER_M = 13.5
BUILDING_LINE_M = 14.0
CROSS_HALF_WIDTH_M = 7.0  # the cross street: two lanes each way, no parking
GROUND_AMPLITUDE_M = 0.05  # peak height of the ground's undulation


def ground_height(x: np.ndarray, y: np.ndarray, phase: float = 0.0) -> np.ndarray:
    """Height (m) of the ground at world (x, y): a sum of long waves, at most GROUND_AMPLITUDE_M."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    h = np.sin(x * (2 * math.pi / 23.0) + phase) * np.sin(y * (2 * math.pi / 31.0) + 0.7 * phase)
    h = h + 0.6 * np.sin((x + 0.6 * y) * (2 * math.pi / 11.0) + 1.3 * phase)
    return (GROUND_AMPLITUDE_M / 1.6) * h


def ray_ground_height(origins: np.ndarray, dirs: np.ndarray, phase: float = 0.0, iterations: int = 3) -> np.ndarray:
    """(P,) distance along unit rays to the undulating ground (inf for rays that never reach it).

    Fixed-point iteration from the plane z = 0, ``iterations`` steps: each step puts the point at the height the
    ground has under the previous one. A step shrinks the range error by the ground's slope along the ray over the
    ray's own slope, so steep rays (the near ground) converge within a few steps, while rays that graze the ground
    far away converge slowly or not at all and keep a range error many times the undulation (along the ray). The
    point found still lies within the undulation's band (|z| <= GROUND_AMPLITUDE_M), so its height above the true
    ground under it is at most twice that amplitude. ``test_ray_ground_height_accuracy`` (tests/test_data_synth_world.py)
    measures both against many more steps.
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    dz = d[..., 2]
    down = dz < -1e-9
    safe = np.where(down, dz, -1.0)
    t = np.where(down, -o[..., 2] / safe, np.inf)
    for _ in range(iterations):
        tt = np.where(np.isfinite(t), t, 0.0)
        h = ground_height(o[..., 0] + tt * d[..., 0], o[..., 1] + tt * d[..., 1], phase)
        t = np.where(down, (h - o[..., 2]) / safe, np.inf)
    return np.where(t > 0, t, np.inf)
