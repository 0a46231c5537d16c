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


def _convex_intersection_area(poly_a: np.ndarray, poly_b: np.ndarray) -> np.ndarray:
    """Area of the intersection of paired counter-clockwise quadrilaterals (P, 4, 2) -> (P,).

    Sutherland-Hodgman, vectorised over pairs: a is clipped by the four half-planes left of b's edges.
    Clipping a convex polygon by one half-plane adds at most one vertex, so 8 slots always suffice.
    """
    num_pairs = poly_a.shape[0]
    capacity = 8
    slots = np.arange(capacity)
    verts = np.zeros((num_pairs, capacity, 2))  # (P, 8, 2), the first `count` slots are the polygon
    verts[:, :4] = poly_a
    count = np.full(num_pairs, 4)
    for e in range(4):
        start = poly_b[:, e, None, :]  # (P, 1, 2)
        edge = poly_b[:, (e + 1) % 4, None, :] - start  # (P, 1, 2)
        valid = slots < count[:, None]  # (P, 8)
        following = np.where(slots + 1 < count[:, None], slots + 1, 0)  # (P, 8), wraps to slot 0
        nxt = np.take_along_axis(verts, following[..., None], axis=1)  # (P, 8, 2)
        # Signed distance (times |edge|) from the clipping line; >= 0 is inside (left of a CCW edge).
        side_cur = edge[..., 0] * (verts[..., 1] - start[..., 1]) - edge[..., 1] * (verts[..., 0] - start[..., 0])
        side_nxt = edge[..., 0] * (nxt[..., 1] - start[..., 1]) - edge[..., 1] * (nxt[..., 0] - start[..., 0])
        inside_cur = side_cur >= 0
        crosses = valid & (inside_cur != (side_nxt >= 0))
        # The denominator is non-zero wherever `crosses` holds: the two sides have different signs there.
        t = np.where(crosses, side_cur / np.where(crosses, side_cur - side_nxt, 1.0), 0.0)
        crossing = verts + t[..., None] * (nxt - verts)  # (P, 8, 2)
        candidates = np.stack([verts, crossing], axis=2).reshape(num_pairs, 2 * capacity, 2)  # (P, 16, 2)
        emitted = np.stack([valid & inside_cur, crosses], axis=2).reshape(num_pairs, 2 * capacity)  # (P, 16)
        # Move the emitted vertices to the front, keeping their order around the polygon.
        order = np.argsort(~emitted, axis=1, kind="stable")[:, :capacity]  # (P, 8)
        verts = np.take_along_axis(candidates, order[..., None], axis=1)
        count = np.minimum(emitted.sum(axis=1), capacity)
    valid = slots < count[:, None]
    following = np.where(slots + 1 < count[:, None], slots + 1, 0)
    nxt = np.take_along_axis(verts, following[..., None], axis=1)
    cross = verts[..., 0] * nxt[..., 1] - verts[..., 1] * nxt[..., 0]  # shoelace terms, (P, 8)
    return np.maximum(0.5 * np.where(valid, cross, 0.0).sum(axis=1), 0.0)


def paired_bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU of row i of `boxes_a` with row i of `boxes_b`: (P, 9), (P, 9) -> (P,) float64.

    Exact polygon intersection; boxes with a non-positive w or l have IoU 0 with everything.
    """
    a = _check_boxes(boxes_a, "boxes_a").astype(np.float64)
    b = _check_boxes(boxes_b, "boxes_b").astype(np.float64)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"paired boxes must have the same count, got boxes_a {a.shape} and boxes_b {b.shape}")
    area_a = a[:, W] * a[:, L]
    area_b = b[:, W] * b[:, L]
    proper = (a[:, W] > 0) & (a[:, L] > 0) & (b[:, W] > 0) & (b[:, L] > 0)
    iou = np.zeros(a.shape[0])
    if not proper.any():
        return iou
    # Centre each pair on box a: intersection is translation-invariant and small coordinates lose less.
    shift = a[proper, None, :2]  # (P', 1, 2)
    corners_a = box_corners_bev(a[proper]) - shift
    corners_b = box_corners_bev(b[proper]) - shift
    inter = _convex_intersection_area(corners_a, corners_b)
    union = area_a[proper] + area_b[proper] - inter
    iou[proper] = np.clip(inter / union, 0.0, 1.0)
    return iou


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU of every box of `boxes_a` with every box of `boxes_b`: (A, 9), (B, 9) -> (A, B) float64.

    Exact polygon intersection, computed only for pairs whose axis-aligned BEV extents overlap.
    """
    a = _check_boxes(boxes_a, "boxes_a").astype(np.float64)
    b = _check_boxes(boxes_b, "boxes_b").astype(np.float64)
    iou = np.zeros((a.shape[0], b.shape[0]))
    if iou.size == 0:
        return iou
    lo_a, hi_a = bev_extent(a)
    lo_b, hi_b = bev_extent(b)
    touching = np.all((lo_a[:, None] < hi_b[None]) & (lo_b[None] < hi_a[:, None]), axis=-1)  # (A, B)
    ia, ib = np.nonzero(touching)
    iou[ia, ib] = paired_bev_iou(a[ia], b[ib])
    return iou


def bev_extent(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned BEV bounds of rotated boxes: (lo (N, 2), hi (N, 2)) in metres."""
    boxes = _check_boxes(boxes)
    cos = np.abs(np.cos(boxes[:, YAW]))
    sin = np.abs(np.sin(boxes[:, YAW]))
    half_l = np.abs(boxes[:, L]) / 2
    half_w = np.abs(boxes[:, W]) / 2
    half = np.stack([cos * half_l + sin * half_w, sin * half_l + cos * half_w], axis=1)  # (N, 2)
    return boxes[:, :2] - half, boxes[:, :2] + half
