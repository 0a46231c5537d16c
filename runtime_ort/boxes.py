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


def box_corners_bev(boxes: np.ndarray) -> np.ndarray:
    """Rotated bird's-eye-view corners, ``(M, 4, 2)``, counter-clockwise from front-left.

    Corner order in the box frame (x along the heading, y to its left):
    ``(+l/2, +w/2), (-l/2, +w/2), (-l/2, -w/2), (+l/2, -w/2)``; corners 0 and 3 span the front face.
    """
    boxes = _check_boxes(boxes, "boxes")
    half_l = 0.5 * boxes[:, L]
    half_w = 0.5 * boxes[:, W]
    local = np.stack(
        [
            np.stack([half_l, half_w], axis=-1),
            np.stack([-half_l, half_w], axis=-1),
            np.stack([-half_l, -half_w], axis=-1),
            np.stack([half_l, -half_w], axis=-1),
        ],
        axis=1,
    )  # (M, 4, 2)
    cos, sin = np.cos(boxes[:, YAW]), np.sin(boxes[:, YAW])
    rot = np.stack([np.stack([cos, -sin], axis=-1), np.stack([sin, cos], axis=-1)], axis=1)  # (M, 2, 2)
    return np.einsum("mij,mkj->mki", rot, local) + boxes[:, None, X : Y + 1]


def box_corners_3d(boxes: np.ndarray) -> np.ndarray:
    """3D corners, ``(M, 8, 3)``: the bottom face (z - h/2) then the top face, each in ``box_corners_bev`` order.

    Edges: ``(i, (i + 1) % 4)`` on each face and ``(i, i + 4)`` verticals; the front face is corners 0, 3, 7, 4.
    """
    boxes = _check_boxes(boxes, "boxes")
    bev = box_corners_bev(boxes)  # (M, 4, 2)
    bottom = (boxes[:, Z] - 0.5 * boxes[:, H])[:, None, None]
    top = (boxes[:, Z] + 0.5 * boxes[:, H])[:, None, None]
    z = np.concatenate([np.broadcast_to(bottom, bev.shape[:2] + (1,)), np.broadcast_to(top, bev.shape[:2] + (1,))], axis=1)
    return np.concatenate([np.concatenate([bev, bev], axis=1), z], axis=-1)  # (M, 8, 3)


def _check_boxes(boxes: np.ndarray, name: str) -> np.ndarray:
    boxes = np.asarray(boxes)
    if boxes.ndim != 2 or boxes.shape[1] < YAW + 1:
        raise ValueError(f"{name} must be (M, {BOX_DIM}) (at least x, y, z, w, l, h, yaw), got shape {boxes.shape}")
    return boxes
