"""One multi-modal sample (a LiDAR sweep, its camera images, calibration and ground truth) and its loaders.

Every reader (nuScenes tables, the bundled real sample, the synthetic world) returns a ``Sample``; what crosses
into the model is the sweep ``points`` (N, 5) float32 ``x, y, z, intensity (0..255), ring`` in the LiDAR frame of
the sample, the images named by ``image_paths`` in rig order, and boxes ``(M, 9)`` in the layout of
``streamdet.core.boxes`` (LiDAR frame).
"""

from __future__ import annotations

import importlib.resources
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.constants import BUNDLED_SAMPLE_DIR
from streamdet.core.points import check_sweep

POINT_TIME_SUFFIX = ".time"  # optional float32 (N,) per-point times beside a .pcd.bin (synthetic data writes it)


@dataclass(frozen=True, eq=False)
class Sweep:
    """A past LiDAR sweep, moved into the LiDAR frame of the sample it accompanies."""

    token: str
    timestamp_us: int
    time_lag_s: float  # sample timestamp minus this sweep's, > 0
    points: np.ndarray  # (N, 5) float32 x, y, z (sample's LiDAR frame), intensity, ring


@dataclass(frozen=True, eq=False)
class Sample:
    """A key frame: LiDAR sweep, camera images, rig and ground truth (boxes in the LiDAR frame)."""

    token: str
    timestamp_us: int  # the LiDAR sweep's timestamp (nuScenes: the end of the sweep)
    points: np.ndarray  # (N, 5) float32 x, y, z (m), intensity (0..255), ring
    rig: Rig  # cameras in image order, lidar2ego, ego2global at the LiDAR timestamp
    image_paths: dict[str, Path]  # camera name -> image file, in rig order
    gt_boxes: np.ndarray  # (M, 9) float64 x, y, z, w, l, h, yaw, vx, vy (LiDAR frame)
    gt_labels: np.ndarray  # (M,) int64 index into CLASS_NAMES, -1 = category outside the 10 classes
    gt_names: tuple[str, ...]  # (M,) detection class name, or the raw category for label -1
    num_lidar_pts: np.ndarray  # (M,) int64
    num_radar_pts: np.ndarray  # (M,) int64
    velocity_valid: np.ndarray  # (M,) bool; False where the velocity was unknown (NaN) and is reported as 0
    instance_tokens: tuple[str, ...] = ()  # (M,) track ids; "" where unknown
    annotation_tokens: tuple[str, ...] = ()  # (M,) sample_annotation tokens; "" where unknown
    attribute_names: tuple[str, ...] = ()  # (M,) e.g. "vehicle.moving"; "" where none
    point_time_s: np.ndarray | None = None  # (N,) float32 time after the sweep start, where known (synthetic)
    sweeps: tuple[Sweep, ...] = ()  # past sweeps, newest first
    scene_name: str = ""
    extras: dict = field(default_factory=dict)  # reader-specific facts (e.g. the bundled sample's global centres)

    def __post_init__(self) -> None:
        pts = check_sweep(self.points, "Sample.points")
        boxes = np.asarray(self.gt_boxes)
        if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
            raise ValueError(f"Sample.gt_boxes must be (M, {BOX_DIM}), got shape {boxes.shape}")
        m = len(boxes)
        for name in ("gt_labels", "num_lidar_pts", "num_radar_pts", "velocity_valid"):
            if len(getattr(self, name)) != m:
                raise ValueError(f"Sample.{name} has {len(getattr(self, name))} entries for {m} boxes")
        for name in ("gt_names", "instance_tokens", "annotation_tokens", "attribute_names"):
            value = getattr(self, name)
            if name != "gt_names" and not value:
                object.__setattr__(self, name, ("",) * m)
            elif len(value) != m:
                raise ValueError(f"Sample.{name} has {len(value)} entries for {m} boxes")
        if self.point_time_s is not None and len(self.point_time_s) != len(pts):
            raise ValueError(f"Sample.point_time_s has {len(self.point_time_s)} entries for {len(pts)} points")
        missing = [n for n in self.rig.names if n not in self.image_paths]
        if missing:
            raise ValueError(f"Sample.image_paths lacks cameras {missing} of the rig {list(self.rig.names)}")

    @property
    def ego2global(self) -> np.ndarray:
        """(4, 4) ego pose at the LiDAR timestamp."""
        return self.rig.ego2global

    @property
    def lidar2ego(self) -> np.ndarray:
        return self.rig.lidar2ego

    @property
    def lidar2global(self) -> np.ndarray:
        return self.rig.ego2global @ self.rig.lidar2ego

    def load_images(self, size: tuple[int, int] | None = None) -> np.ndarray:
        """(J, H, W, 3) uint8 RGB in rig order; ``size`` = (width, height) resizes every image."""
        return np.stack([load_image(self.image_paths[name], size) for name in self.rig.names])  # (J, H, W, 3)


def load_image(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB image; ``size`` = (width, height) resizes with area averaging."""
    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"cannot read image {path}: missing or not an image file")
    if size is not None:
        width, height = _check_size(size)
        if (image.shape[1], image.shape[0]) != (width, height):
            image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def load_points(path: str | Path) -> np.ndarray:
    """(N, 5) float32 sweep from a nuScenes ``.pcd.bin`` (x, y, z, intensity, ring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LiDAR file not found: {path}")
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 5:
        raise ValueError(f"LiDAR file {path}: {raw.size} floats is not a multiple of 5 (x, y, z, intensity, ring)")
    return raw.reshape(-1, 5)  # (N, 5)


def load_point_times(points_path: str | Path, num_points: int) -> np.ndarray | None:
    """(N,) float32 per-point times from the ``<file>.time`` beside a sweep, or None where there is none."""
    path = Path(points_path)
    path = path.with_name(path.name + POINT_TIME_SUFFIX)
    if not path.is_file():
        return None
    times = np.fromfile(path, dtype="<f4")
    if times.shape != (num_points,):
        raise ValueError(f"point-time file {path} holds {times.size} values for {num_points} points")
    return times


def bundled_sample_dir() -> Path:
    """Folder of the real nuScenes sample that ships with the package."""
    return Path(str(importlib.resources.files("streamdet.data") / BUNDLED_SAMPLE_DIR))


def load_bundled_sample(root: str | Path | None = None) -> Sample:
    """The shipped real nuScenes sample (scene-0061, first key frame): calibration.json, boxes.json and files.

    ``extras["center_global"]`` holds the boxes' global centres as boxes.json gives them (the devkit's numbers).
    """
    root = Path(root) if root is not None else bundled_sample_dir()
    calib_path = root / "calibration.json"
    boxes_path = root / "boxes.json"
    for p in (calib_path, boxes_path):
        if not p.is_file():
            raise FileNotFoundError(f"bundled sample file not found: {p}")
    calib = json.loads(calib_path.read_text())
    rig = Rig.from_calibration_json(calib)
    doc = json.loads(boxes_path.read_text())
    records = doc.get("boxes")
    if not isinstance(records, list):
        raise ValueError(f"{boxes_path}: 'boxes' must be a list, got {type(records).__name__}")
    boxes = np.zeros((len(records), BOX_DIM), dtype=np.float64)
    valid_v = np.ones(len(records), dtype=bool)
    for i, r in enumerate(records):
        boxes[i, 0:3] = r["center_xyz"]
        boxes[i, 3:6] = r["size_wlh"]
        boxes[i, 6] = r["yaw"]
        v = r["velocity_xy"]  # null, or [null, null], where the source had NaN
        if v is None or any(c is None for c in v) or not np.all(np.isfinite(np.asarray(v, dtype=np.float64))):
            valid_v[i] = False
        else:
            boxes[i, 7:9] = v
    labels = np.array([r["label"] for r in records], dtype=np.int64)
    names = tuple(CLASS_NAMES[lab] if lab >= 0 else "other" for lab in labels)
    return Sample(
        token=calib["sample_token"],
        timestamp_us=int(calib["sample_timestamp_us"]),
        points=load_points(root / calib["lidar"]["file"]),
        rig=rig,
        image_paths={c["name"]: root / c["file"] for c in calib["cameras"]},
        gt_boxes=boxes,
        gt_labels=labels,
        gt_names=names,
        num_lidar_pts=np.array([r["num_lidar_pts"] for r in records], dtype=np.int64),
        num_radar_pts=np.array([r["num_radar_pts"] for r in records], dtype=np.int64),
        velocity_valid=valid_v,
        scene_name=str(calib.get("scene", "")),
        extras={"center_global": np.array([r["center_global"] for r in records], dtype=np.float64).reshape(-1, 3)},  # (M, 3)
    )


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"size must be positive (width, height) in pixels, got {size!r}")
    return width, height
