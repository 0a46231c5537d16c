"""Pictures to look at: a bird's-eye view of points and boxes coloured by slice, and 3D boxes on camera images.

All drawing returns BGR uint8 images (OpenCV's order, ready for ``cv2.imwrite``). The BEV is drawn in the
LiDAR frame seen from above: x to the right, y (nuScenes LIDAR_TOP: forward) up, the sensor in the centre.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from streamdet.calibration.camera import Camera
from streamdet.core.boxes import BOX_DIM, box_corners_3d, box_corners_bev
from streamdet.core.classes import CLASS_COLORS_RGB, CLASS_NAMES, OTHER_COLOR_RGB
from streamdet.core.sectors import check_num_slices, sector_bounds_deg, slice_index_of
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import Sample, load_image

# core.classes' class colours, in OpenCV's channel order
CLASS_COLORS_BGR: tuple[tuple[int, int, int], ...] = tuple(c[::-1] for c in CLASS_COLORS_RGB)
OTHER_COLOR_BGR = OTHER_COLOR_RGB[::-1]
# Box edges in box_corners_3d order: bottom face, top face, verticals.
BOX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
NEAR_M = 0.1


def slice_colors_bgr(n: int) -> np.ndarray:
    """(n, 3) uint8 distinct, bright BGR colours, one per slice, around the hue circle in scan order."""
    hue = (np.arange(n) * 180 // max(n, 1)).astype(np.uint8)  # OpenCV hue is 0..179
    hsv = np.stack([hue, np.full(n, 220, np.uint8), np.full(n, 255, np.uint8)], axis=-1)[None]  # (1, n, 3)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]


def draw_bev(
    points: np.ndarray,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    slice_of_point: np.ndarray | None = None,
    n_slices: int = 8,
    range_m: float = 51.2,
    det_boxes: np.ndarray | None = None,
    det_scores: np.ndarray | None = None,
    *,
    start_deg: float = 0.0,
    size_px: int = 900,
    score_threshold: float = 0.0,
) -> np.ndarray:
    """Bird's-eye view (size_px, size_px, 3) BGR of points and boxes.

    points: (N, >=2) LiDAR frame. slice_of_point: (N,) slice index per point (e.g. column 5 of slice points);
    None colours the points by height. Ground-truth ``boxes`` (M, 9) are drawn in the colour of the slice of their
    centre, with a heading tick and a class initial from ``labels``; ``det_boxes`` (D, 9) in white, with
    ``det_scores`` printed and those below ``score_threshold`` skipped. Sector boundaries of the n slices are
    drawn from ``start_deg``.
    """
    check_num_slices(n_slices, start_deg)
    if not (np.isfinite(range_m) and range_m > 0):
        raise ValueError(f"range_m must be a positive number of metres, got {range_m!r}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 2:
        raise ValueError(f"points must be (N, >=2), got shape {points.shape}")
    scale = size_px / (2.0 * range_m)
    image = np.full((size_px, size_px, 3), 18, dtype=np.uint8)
    centre = (size_px // 2, size_px // 2)
    for r in np.arange(10.0, range_m * 1.5, 10.0):
        cv2.circle(image, centre, int(round(r * scale)), (48, 48, 48), 1, cv2.LINE_AA)
    colors = slice_colors_bgr(n_slices)
    for k in range(n_slices):
        lo, _ = sector_bounds_deg(k, n_slices, start_deg)
        end = (centre[0] + int(2 * size_px * np.cos(np.radians(lo))), centre[1] - int(2 * size_px * np.sin(np.radians(lo))))
        cv2.line(image, centre, end, (70, 70, 70), 1, cv2.LINE_AA)

    if boxes is not None and len(boxes):
        boxes = _check_boxes(boxes, "boxes")
        labels = np.full(len(boxes), -1) if labels is None else np.asarray(labels)
        box_slice = slice_index_of(boxes[:, 0], boxes[:, 1], n_slices, start_deg)
        for box, corners, k, label in zip(boxes, box_corners_bev(boxes), box_slice, labels):
            color = tuple(int(c) for c in colors[k])
            _draw_bev_box(image, box, corners, color, scale, size_px, 1)
            if 0 <= label < len(CLASS_NAMES):
                x, y = _to_px(box[None, :2], scale, size_px)[0]
                cv2.putText(image, CLASS_NAMES[label][:2], (int(x) + 4, int(y) - 4), cv2.FONT_HERSHEY_PLAIN, 0.8, color, 1, cv2.LINE_AA)
    # Points after the ground truth: an object's points lie on its outline and would be hidden under it.
    uv = _to_px(points[:, :2], scale, size_px)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < size_px) & (uv[:, 1] >= 0) & (uv[:, 1] < size_px)
    if slice_of_point is not None:
        slice_of_point = np.asarray(slice_of_point).astype(np.int64)
        if slice_of_point.shape != (len(points),):
            raise ValueError(f"slice_of_point must be ({len(points)},), got shape {slice_of_point.shape}")
        if len(slice_of_point) and (slice_of_point.min() < 0 or slice_of_point.max() >= n_slices):
            raise ValueError(f"slice_of_point values must be in [0, {n_slices}), got {slice_of_point.min()}..{slice_of_point.max()}")
        point_colors = colors[slice_of_point]
    else:
        z = points[:, 2] if points.shape[1] > 2 else np.zeros(len(points))
        level = np.clip((z + 2.5) / 5.0 * 255, 0, 255).astype(np.uint8)
        turbo = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0]  # (256, 3)
        point_colors = turbo[level]
    image[uv[inside, 1], uv[inside, 0]] = point_colors[inside]

    if det_boxes is not None and len(det_boxes):
        det_boxes = _check_boxes(det_boxes, "det_boxes")
        scores = np.ones(len(det_boxes)) if det_scores is None else np.asarray(det_scores)
        if scores.shape != (len(det_boxes),):
            raise ValueError(f"det_scores must be ({len(det_boxes)},), got shape {scores.shape}")
        for box, corners, score in zip(det_boxes, box_corners_bev(det_boxes), scores):
            if score < score_threshold:
                continue
            _draw_bev_box(image, box, corners, (255, 255, 255), scale, size_px, 1)
            if det_scores is not None:
                x, y = _to_px(box[None, :2], scale, size_px)[0]
                cv2.putText(image, f"{score:.2f}", (int(x) + 4, int(y) + 10), cv2.FONT_HERSHEY_PLAIN, 0.7, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.drawMarker(image, centre, (255, 255, 255), cv2.MARKER_TRIANGLE_UP, 10, 1)
    return image


def draw_camera_boxes(
    image_rgb: np.ndarray,
    camera: Camera,
    boxes: np.ndarray,
    labels: np.ndarray | None = None,
    thickness: int = 2,
    colors_bgr: np.ndarray | None = None,
) -> np.ndarray:
    """The image (BGR) with LiDAR-frame ``boxes`` (M, 9) drawn as 3D wireframes, cut at the camera's near plane.

    The box's front face (corners 0, 1, 4, 5 of ``box_corners_3d``, +x of the box) gets a cross.
    """
    image_rgb = np.asarray(image_rgb)
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got shape {image_rgb.shape}")
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"image is {image_rgb.shape[1]}x{image_rgb.shape[0]} but camera {camera.name} is {camera.width}x{camera.height}"
        )
    image = cv2.cvtColor(np.ascontiguousarray(image_rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    if boxes is None or not len(boxes):
        return image
    boxes = _check_boxes(boxes, "boxes")
    labels = np.full(len(boxes), -1) if labels is None else np.asarray(labels)
    corners = box_corners_3d(boxes)  # (M, 8, 3)
    cam = corners @ camera.lidar2cam[:3, :3].T + camera.lidar2cam[:3, 3]  # (M, 8, 3) camera frame
    edges = BOX_EDGES + ((0, 5), (1, 4))  # the cross on the front face
    for m in range(len(boxes)):
        if cam[m, :, 2].max() <= NEAR_M:
            continue
        if colors_bgr is not None:
            color = tuple(int(c) for c in colors_bgr[m])
        else:
            color = CLASS_COLORS_BGR[labels[m]] if 0 <= labels[m] < len(CLASS_COLORS_BGR) else OTHER_COLOR_BGR
        for i, j in edges:
            seg = _clip_segment(cam[m, i], cam[m, j])
            if seg is None:
                continue
            uv = seg @ camera.K.T
            uv = uv[:, :2] / uv[:, 2:3]
            if not np.all(np.abs(uv) < 1e5):
                continue
            p0, p1 = (tuple(int(round(v)) for v in p) for p in uv)
            cv2.line(image, p0, p1, color, thickness, cv2.LINE_AA)
    return image


def camera_mosaic(tiles: dict[str, np.ndarray], order: tuple[tuple[str, ...], ...] | None = None) -> np.ndarray:
    """Camera images (BGR, same size) arranged in rows; default: front row left-to-right, back row below."""
    order = order or (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))
    any_tile = next(iter(tiles.values()))
    blank = np.zeros_like(any_tile)
    rows = [np.concatenate([tiles.get(name, blank) for name in row], axis=1) for row in order]
    return np.concatenate(rows, axis=0)


def write_previews(sample: Sample, out_dir: str | Path, n_slices: int = 8, start_deg: float = 0.0, max_width_px: int = 2400) -> list[Path]:
    """Write ``<scene>_<token>_cameras.png`` (six images with ground truth) and ``..._bev.png`` (slices)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{sample.scene_name}_{sample.token[:8]}" if sample.scene_name else sample.token[:8]
    tiles = {}
    for cam in sample.rig.cameras:
        tiles[cam.name] = draw_camera_boxes(load_image(sample.image_paths[cam.name]), cam, sample.gt_boxes, sample.gt_labels)
    mosaic = camera_mosaic(tiles)
    if mosaic.shape[1] > max_width_px:
        f = max_width_px / mosaic.shape[1]
        mosaic = cv2.resize(mosaic, (max_width_px, int(round(mosaic.shape[0] * f))), interpolation=cv2.INTER_AREA)
    slices = split_sweep(sample.points, n_slices, start_deg)
    pts = np.concatenate(slices, axis=0)  # (N, 6)
    index = np.repeat(np.arange(n_slices), [len(s) for s in slices])  # (N,) each point's slice (its feature may differ)
    bev = draw_bev(pts, sample.gt_boxes, sample.gt_labels, index, n_slices, start_deg=start_deg)
    paths = [out_dir / f"{stem}_cameras.png", out_dir / f"{stem}_bev.png"]
    for path, image in zip(paths, (mosaic, bev)):
        if not cv2.imwrite(str(path), image):
            raise OSError(f"cannot write {path}")
    return paths


def _to_px(xy: np.ndarray, scale: float, size_px: int) -> np.ndarray:
    """(N, 2) int64 pixel (col, row) of LiDAR (x, y): x to the right, y up."""
    col = np.floor(xy[:, 0] * scale + size_px / 2).astype(np.int64)
    row = np.floor(size_px / 2 - xy[:, 1] * scale).astype(np.int64)
    return np.stack([col, row], axis=1)


def _draw_bev_box(image, box, corners, color, scale, size_px, thickness) -> None:
    px = _to_px(corners, scale, size_px).astype(np.int32)
    cv2.polylines(image, [px], True, color, thickness, cv2.LINE_AA)
    front = _to_px(((corners[0] + corners[1]) / 2)[None], scale, size_px)[0]
    c = _to_px(box[None, :2], scale, size_px)[0]
    cv2.line(image, (int(c[0]), int(c[1])), (int(front[0]), int(front[1])), color, thickness, cv2.LINE_AA)


def _clip_segment(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """The part of segment a-b (camera frame) in front of the near plane, (2, 3), or None."""
    if a[2] < NEAR_M and b[2] < NEAR_M:
        return None
    if a[2] < NEAR_M:
        a = a + (NEAR_M - a[2]) / (b[2] - a[2]) * (b - a)
    elif b[2] < NEAR_M:
        b = b + (NEAR_M - b[2]) / (a[2] - b[2]) * (a - b)
    return np.stack([a, b])


def _check_boxes(boxes: np.ndarray, name: str) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"{name} must be (M, {BOX_DIM}), got shape {boxes.shape}")
    return boxes
