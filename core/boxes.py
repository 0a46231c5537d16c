"""The box layout, defined once, and pairwise box operations as free functions.

Every package reads boxes in this layout (the export's ``det_boxes`` after the runtime's uncrop, ground truth,
evaluation, previews). A box set is an ``(N, 9)`` float array, one row per box::

    x, y, z      centre in metres, LiDAR frame of the sweep, geometric (not bottom) centre
    w, l, h      size in metres, nuScenes order; l lies along the heading
    yaw          rotation about +z in radians, 0 = heading along +x, counter-clockwise
    vx, vy       velocity in m/s, LiDAR frame

with scores ``(N,)`` float32 and labels ``(N,)`` int64 indexing ``CLASS_NAMES`` (``streamdet.core.classes``).
The column indices ``X .. VY`` name the columns.
"""

from __future__ import annotations

import numpy as np

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


_INSIDE_TOLERANCE_M = 1e-9  # corner-in-box slack for rounding; far below any physical size


def _to_frame(corners: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BEV points (P, V, 2) in the frame of paired boxes (P, 9): origin at the centre, x along the heading."""
    cos = np.cos(boxes[:, YAW])[:, None]
    sin = np.sin(boxes[:, YAW])[:, None]
    dx = corners[..., 0] - boxes[:, X, None]
    dy = corners[..., 1] - boxes[:, Y, None]
    return cos * dx + sin * dy, -sin * dx + cos * dy  # (P, V) each


def _intersection_area(
    a: np.ndarray, b: np.ndarray, corners_a: np.ndarray | None = None, corners_b: np.ndarray | None = None
) -> np.ndarray:
    """BEV intersection area (P,) of paired boxes (P, 9) with positive sizes, computed exactly in a's frame.

    The intersection is convex; its vertices are among the corners of each box inside the other and the
    crossings of b's edges with a's four sides, which are axis-aligned in a's frame. Sorting those 24
    candidates by angle around their mean orders them along the boundary, and the shoelace formula gives
    the area. Shapes stay fixed: invalid candidates sort last and are replaced by the first vertex, which
    only adds zero-length edges.
    """
    num_pairs = a.shape[0]
    half_l, half_w = a[:, L, None] / 2, a[:, W, None] / 2  # (P, 1)
    # callers pairing rows of one box set pass its corners, gathered, instead of recomputing them per pair
    corners_a = box_corners_bev(a) if corners_a is None else corners_a  # (P, 4, 2)
    corners_b = box_corners_bev(b) if corners_b is None else corners_b
    ax = np.concatenate([half_l, half_l, -half_l, -half_l], axis=1)  # (P, 4), box_corners_bev order
    ay = np.concatenate([-half_w, half_w, half_w, -half_w], axis=1)
    bx, by = _to_frame(corners_b, a)  # (P, 4)
    a_in_bx, a_in_by = _to_frame(corners_a, b)
    # A corner shared by both boxes (duplicates, collinear edges) lands a rounding error outside the other
    # box; the tolerance keeps it. Admitting points that close to the boundary moves the area by ~1e-9 m^2.
    tol = _INSIDE_TOLERANCE_M
    a_inside_b = (np.abs(a_in_bx) <= b[:, L, None] / 2 + tol) & (np.abs(a_in_by) <= b[:, W, None] / 2 + tol)
    b_inside_a = (np.abs(bx) <= half_l + tol) & (np.abs(by) <= half_w + tol)

    # b's edges (P, 4) against a's sides x = -hl, +hl and y = -hw, +hw: (P, 4, 2) each.
    ex, ey = np.roll(bx, -1, axis=1) - bx, np.roll(by, -1, axis=1) - by
    side = np.array([-1.0, 1.0])
    # Edges parallel to a side: inf / nan, rejected below. The products too: a parallel edge's t is inf times its
    # zero run (nan), and a positive but denormal side's edge divides into inf the same way.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_x = (side * half_l[:, :, None] - bx[..., None]) / ex[..., None]  # hits x = +-hl
        t_y = (side * half_w[:, :, None] - by[..., None]) / ey[..., None]  # hits y = +-hw
        hit_x_y = by[..., None] + t_x * ey[..., None]
        hit_y_x = bx[..., None] + t_y * ex[..., None]
    ok_x = (t_x >= 0) & (t_x <= 1) & (np.abs(hit_x_y) <= half_w[:, :, None] + tol)
    ok_y = (t_y >= 0) & (t_y <= 1) & (np.abs(hit_y_x) <= half_l[:, :, None] + tol)
    hit_x_x = np.broadcast_to(side * half_l[:, :, None], t_x.shape)  # (P, 4, 2), the sides' own coordinate
    hit_y_y = np.broadcast_to(side * half_w[:, :, None], t_y.shape)
    xs = np.concatenate([ax, bx, hit_x_x.reshape(num_pairs, 8), hit_y_x.reshape(num_pairs, 8)], axis=1)  # (P, 24)
    ys = np.concatenate([ay, by, hit_x_y.reshape(num_pairs, 8), hit_y_y.reshape(num_pairs, 8)], axis=1)
    valid = np.concatenate([a_inside_b, b_inside_a, ok_x.reshape(num_pairs, 8), ok_y.reshape(num_pairs, 8)], axis=1)
    xs = np.where(valid, xs, 0.0)  # also clears the nan of rejected parallel hits
    ys = np.where(valid, ys, 0.0)

    count = valid.sum(axis=1)
    cx = xs.sum(axis=1, keepdims=True) / np.maximum(count, 1)[:, None]  # (P, 1)
    cy = ys.sum(axis=1, keepdims=True) / np.maximum(count, 1)[:, None]
    # A pseudo-angle in (-2, 2], monotonic in atan2(dy, dx), is enough to sort and much cheaper.
    dx, dy = xs - cx, ys - cy
    ratio = dx / np.maximum(np.abs(dx) + np.abs(dy), np.finfo(np.float64).tiny)
    angle = np.where(valid, np.copysign(1.0 - ratio, dy), np.inf)
    order = np.argsort(angle, axis=1)  # (P, 24): valid candidates first, counter-clockwise
    keep = np.take_along_axis(valid, order, axis=1)
    xs = np.take_along_axis(xs, order, axis=1)
    ys = np.take_along_axis(ys, order, axis=1)
    xs = np.where(keep, xs, xs[:, :1])
    ys = np.where(keep, ys, ys[:, :1])
    area = 0.5 * (xs * np.roll(ys, -1, axis=1) - np.roll(xs, -1, axis=1) * ys).sum(axis=1)
    return np.where(count >= 3, np.maximum(area, 0.0), 0.0)


def paired_bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU of row i of `boxes_a` with row i of `boxes_b`: (P, 9), (P, 9) -> (P,) float64.

    Exact polygon intersection; boxes with a non-positive w or l have IoU 0 with everything.
    """
    a = _check_boxes(boxes_a, "boxes_a").astype(np.float64)
    b = _check_boxes(boxes_b, "boxes_b").astype(np.float64)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"paired boxes must have the same count, got boxes_a {a.shape} and boxes_b {b.shape}")
    proper = (a[:, W] > 0) & (a[:, L] > 0) & (b[:, W] > 0) & (b[:, L] > 0)
    iou = np.zeros(a.shape[0])
    if not proper.any():
        return iou
    a, b = a[proper], b[proper]
    inter = _intersection_area(a, b)
    union = a[:, W] * a[:, L] + b[:, W] * b[:, L] - inter
    iou[proper] = _iou(inter, union)
    return iou


def indexed_bev_iou(boxes: np.ndarray, corners: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU of pairs (boxes[i], boxes[j]) of one float64 (N, 9) box set with positive sizes, whose
    ``box_corners_bev`` the caller computed once: the hot loop of crowded rotated NMS. (P,) float64."""
    a, b = boxes[i], boxes[j]
    inter = _intersection_area(a, b, corners[i], corners[j])
    union = a[:, W] * a[:, L] + b[:, W] * b[:, L] - inter
    return _iou(inter, union)


def _iou(inter: np.ndarray, union: np.ndarray) -> np.ndarray:
    """inter / union clipped to [0, 1], and 0 where the union has no area: sides so small (denormal) that w * l
    underflows to 0 give a box without area, which overlaps nothing (the division gave 1 or nan, with a warning)."""
    return np.clip(np.divide(inter, union, out=np.zeros_like(inter), where=union > 0), 0.0, 1.0)


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


def pair_boxes(
    boxes_a: np.ndarray, keys_a: np.ndarray, boxes_b: np.ndarray, keys_b: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedy nearest-centre pairing of two box sets: boxes with equal keys, BEV centres within ``radius_m``.

    ``keys_a`` (Na,) or (Na, k) and ``keys_b`` (Nb,) or (Nb, k): what must agree for a pair (the label, or the
    label and the quadrant). The nearest pair is taken first, then the nearest among the boxes left, and so on.
    Returns (index into a, index into b, centre distance in metres) of each pair, nearest pairs first.
    """
    boxes_a = _check_boxes(boxes_a, "boxes_a")
    boxes_b = _check_boxes(boxes_b, "boxes_b")
    ka = _key_columns(keys_a, len(boxes_a), "keys_a")  # (Na, k)
    kb = _key_columns(keys_b, len(boxes_b), "keys_b")  # (Nb, k)
    d = np.linalg.norm(boxes_a[:, None, :2].astype(np.float64) - boxes_b[None, :, :2], axis=-1)  # (Na, Nb)
    d[np.any(ka[:, None, :] != kb[None, :, :], axis=-1)] = np.inf
    used_a = np.zeros(len(boxes_a), dtype=bool)
    used_b = np.zeros(len(boxes_b), dtype=bool)
    ia, ib, dist = [], [], []
    for flat in np.argsort(d, axis=None, kind="stable"):
        i, j = divmod(int(flat), len(boxes_b))
        if not d[i, j] <= radius_m:
            break
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            ia.append(i)
            ib.append(j)
            dist.append(d[i, j])
    return np.asarray(ia, dtype=np.int64), np.asarray(ib, dtype=np.int64), np.asarray(dist, dtype=np.float64)


def _key_columns(keys: np.ndarray, n: int, name: str) -> np.ndarray:
    keys = np.asarray(keys)
    keys = keys[:, None] if keys.ndim == 1 else keys
    if keys.ndim != 2 or keys.shape[0] != n:
        raise ValueError(f"{name} must be ({n},) or ({n}, k), one row per box, got shape {keys.shape}")
    return keys
