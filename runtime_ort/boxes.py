"""The box layout, defined once, and pairwise box operations as free functions.

A box set is an ``(N, 9)`` float array, one row per box::

    x, y, z      centre in metres, LiDAR frame of the sweep, geometric (not bottom) centre
    w, l, h      size in metres, nuScenes order; l lies along the heading
    yaw          rotation about +z in radians, 0 = heading along +x, counter-clockwise
    vx, vy       velocity in m/s, LiDAR frame

with scores ``(N,)`` float32 and labels ``(N,)`` int64 indexing ``CLASS_NAMES``.
"""

from __future__ import annotations

import numpy as np

# The 10 nuScenes detection classes, in mmdetection3d's order (the `label` of the bundled sample).
CLASS_NAMES: tuple[str, ...] = (
    "car",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
)

BOX_DIM = 9
X, Y, Z, W, L, H, YAW, VX, VY = range(BOX_DIM)
