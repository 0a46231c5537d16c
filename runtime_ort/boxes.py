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


def _check_boxes(boxes: np.ndarray, name: str = "boxes") -> np.ndarray:
    boxes = np.asarray(boxes)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"{name} must be (N, {BOX_DIM}) (x, y, z, w, l, h, yaw, vx, vy), got shape {boxes.shape}")
    return boxes


def box_corners_bev(boxes: np.ndarray) -> np.ndarray:
    """BEV corners (M, 4, 2) of (M, 9) boxes, counter-clockwise from front-right: l along the heading, w across.

    Front-right means (+l/2, -w/2) in the box frame; the order is front-right, front-left, rear-left, rear-right.
    """
    boxes = _check_boxes(boxes)
    half_l = boxes[:, L] / 2
    half_w = boxes[:, W] / 2
    # Box-frame corners, counter-clockwise seen from above (+z).
    local_x = np.stack([half_l, half_l, -half_l, -half_l], axis=1)  # (M, 4)
    local_y = np.stack([-half_w, half_w, half_w, -half_w], axis=1)  # (M, 4)
    cos = np.cos(boxes[:, YAW])[:, None]
    sin = np.sin(boxes[:, YAW])[:, None]
    x = boxes[:, X, None] + cos * local_x - sin * local_y
    y = boxes[:, Y, None] + sin * local_x + cos * local_y
    return np.stack([x, y], axis=-1)  # (M, 4, 2)


def box_corners_3d(boxes: np.ndarray) -> np.ndarray:
    """3D corners (M, 8, 3): the 4 bottom corners, then the 4 top ones, each in `box_corners_bev` order."""
    boxes = _check_boxes(boxes)
    bev = box_corners_bev(boxes)  # (M, 4, 2)
    bottom = boxes[:, Z] - boxes[:, H] / 2
    top = boxes[:, Z] + boxes[:, H] / 2
    z = np.repeat(np.stack([bottom, top], axis=1), 4, axis=1)  # (M, 8): 4 bottom, then 4 top
    return np.concatenate([np.tile(bev, (1, 2, 1)), z[..., None]], axis=-1)  # (M, 8, 3)
