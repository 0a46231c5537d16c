"""One multi-modal sample (a LiDAR sweep, its camera images, calibration and ground truth) and its loaders.

Every reader (nuScenes tables, the bundled real sample, the synthetic world) returns a ``Sample``; what crosses
into the model is the sweep ``points`` (N, 5) float32 ``x, y, z, intensity (0..255), ring`` in the LiDAR frame of
the sample, the images named by ``image_paths`` in rig order, and boxes ``(M, 9)`` in the layout of
``streamdet.core.boxes`` (LiDAR frame).
"""

from __future__ import annotations

import importlib.resources
import logging
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from streamdet.calibration.camera import MAX_CALIBRATION_BYTES, Rig
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.constants import BUNDLED_SAMPLE_DIR
from streamdet.core.file_input import InputFileError, missing_reason, read_regular_file
from streamdet.core.image_header import MAX_IMAGE_FILE_BYTES, check_image_size, decoder_error_reason, read_image_header
from streamdet.core.json_input import is_finite_number, read_json, short_repr  # noqa: F401 (public here too)
from streamdet.core.points import MAX_SWEEP_POINTS, SWEEP_COLUMNS, check_sweep

log = logging.getLogger(__name__)

POINT_TIME_SUFFIX = ".time"  # optional float32 (N,) per-point times beside a .pcd.bin (synthetic data writes it)
MAX_BOXES_BYTES = 64 << 20  # boxes.json of one sample is ~100 kB; a larger file is refused before it is read
_INT64_MAX = (1 << 63) - 1


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
        """(J, H, W, 3) uint8 RGB in rig order; ``size`` = (width, height) resizes every image. Each file must have
        its camera's calibrated size (a different one would project with the wrong intrinsics: ValueError)."""
        return np.stack([load_image(self.image_paths[c.name], size, expected_size=(c.width, c.height))
                         for c in self.rig.cameras])  # fmt: skip  # (J, H, W, 3)


class ImageFileError(FileNotFoundError, ValueError):
    """An image file that cannot be read: missing, not a regular file, or not a decodable JPEG / PNG.

    A FileNotFoundError as ``load_image`` always raised for these, and a ValueError as every other bad input is.
    """


def load_image(path: str | Path, size: tuple[int, int] | None = None,
               expected_size: tuple[int, int] | None = None) -> np.ndarray:  # fmt: skip
    """(H, W, 3) uint8 RGB image; ``size`` = (width, height) resizes with area averaging.

    The file must be a regular file holding an 8-bit colour JPEG or PNG (an alpha channel is dropped) of at most
    ``core.image_header.MAX_IMAGE_FILE_BYTES``; its size is read from its header and refused (ValueError) over
    ``MAX_IMAGE_SIDE_PX`` a side or ``MAX_IMAGE_PIXELS`` in all before anything is decoded. Grey and 16-bit images
    are refused, not replicated or scaled: the detector was trained on colour images (as the ROS readers refuse
    them). ``expected_size`` = (width, height): the size the camera is calibrated for; another size is refused,
    since the camera's K would not fit the image. ``ImageFileError`` (a FileNotFoundError and a ValueError) for a
    file that is missing, not a regular file (a FIFO would block), or not decodable (e.g. a truncated JPEG, which
    ``cv2.imread`` would fill with grey); ValueError for the rest, always naming the file. An EXIF orientation
    tag is ignored: the pixels are returned as stored, the grid the camera was calibrated on.
    """
    path = Path(path)
    if size is not None:
        size = _check_size(size)
    if expected_size is not None:
        expected_size = _check_size(expected_size)
    data = read_image_bytes(path)
    try:
        header = read_image_header(data)
    except ValueError as e:  # not a JPEG or PNG, or its header cut short
        raise ImageFileError(f"cannot read image {path}: it {e}") from None
    check_image_size(header, f"image {path}")
    if not header.is_colour_8bit:
        raise ValueError(f"image {path} is a {header.describe()} image; streamdet takes 8-bit colour (RGB) images")
    if expected_size is not None and (header.width, header.height) != expected_size:
        raise ValueError(f"image {path} is {header.width}x{header.height} px but its camera is calibrated for "
                         f"{expected_size[0]}x{expected_size[1]}")  # fmt: skip
    try:
        # IGNORE_ORIENTATION: the camera's K is for the pixels as stored; an EXIF rotation would turn them
        image = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)  # (H, W, 3) BGR; None: corrupt
    except cv2.error as e:
        raise ValueError(f"image {path} ({header.width}x{header.height} {header.format}) could not be decoded: "
                         f"{decoder_error_reason(e)}") from None  # fmt: skip
    if (image is None or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8
            or image.shape[:2] != (header.height, header.width)):
        raise ImageFileError(f"cannot read image {path}: not a decodable image ({header.format} declaring "
                             f"{header.width}x{header.height} px; truncated or corrupt?)")  # fmt: skip
    try:
        if size is not None and (image.shape[1], image.shape[0]) != size:
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    except cv2.error as e:  # a failed allocation
        raise ValueError(f"image {path}: cannot resize or convert {image.shape[1]}x{image.shape[0]} px: "
                         f"{decoder_error_reason(e)}") from None  # fmt: skip


def read_image_bytes(path: str | Path) -> np.ndarray:
    """The bytes of an image file, bounded: a regular file (never a FIFO or device) of at most MAX_IMAGE_FILE_BYTES."""
    try:
        raw = read_regular_file(path, MAX_IMAGE_FILE_BYTES)
    except InputFileError as e:
        if e.too_large:
            raise ValueError(f"image {path} {e.reason}") from None
        raise ImageFileError(f"cannot read image {path}: {e.reason}") from None
    return np.frombuffer(raw, dtype=np.uint8)


def load_points(path: str | Path, allow_empty: bool = True) -> np.ndarray:
    """(N, 5) float32 sweep from a nuScenes ``.pcd.bin`` (x, y, z, intensity, ring).

    A file of more than ``core.points.MAX_SWEEP_POINTS`` points is refused (ValueError naming it) before it is read.
    An empty file is a sweep without returns (with a warning), or, with ``allow_empty`` False, a ValueError: a reader
    that needs the sweep refuses it without the warning that it was read.
    """
    path = Path(path)
    if not path.is_file():
        if path.exists():  # a FIFO would block np.fromfile; a folder is no sweep
            raise ValueError(f"LiDAR file {path} is not a regular file (a FIFO, a device or a folder?)")
        raise FileNotFoundError(f"LiDAR file not found: {path}")
    size = _check_float32_size(path, "LiDAR file")
    point_bytes = 4 * SWEEP_COLUMNS
    if size > MAX_SWEEP_POINTS * point_bytes:  # np.fromfile would allocate it whole: a wrong or corrupt file, unread
        raise ValueError(f"LiDAR file {path} is {size} bytes ({size // point_bytes} points), over the {MAX_SWEEP_POINTS} "
                         "points of any sweep (core.points.MAX_SWEEP_POINTS): not a sweep, or corrupt; refused before "
                         "reading")  # fmt: skip
    if size == 0 and not allow_empty:
        raise ValueError(f"LiDAR file {path} holds no points (0 bytes): a sample needs its sweep")
    raw = np.fromfile(path, dtype=np.float32, count=size // 4)  # count: a file grown since the check is read no further
    if raw.size % 5:
        raise ValueError(f"LiDAR file {path}: {raw.size} floats is not a multiple of 5 (x, y, z, intensity, ring)")
    if raw.size == 0:  # read as a sweep without returns (the devkit does too), but a copy cut short is likelier
        log.warning("LiDAR file %s holds no points (an empty or unfinished copy?): read as a sweep without returns", path)
    return raw.reshape(-1, 5)  # (N, 5)


def load_point_times(points_path: str | Path, num_points: int) -> np.ndarray | None:
    """(N,) float32 per-point times from the ``<file>.time`` beside a sweep, or None where there is none."""
    path = Path(points_path)
    path = path.with_name(path.name + POINT_TIME_SUFFIX)
    if not path.is_file():
        return None
    size = _check_float32_size(path, "point-time file")
    if size != 4 * num_points:
        raise ValueError(f"point-time file {path} is {size} bytes ({size // 4} values) for {num_points} points: "
                         f"expected {4 * num_points} (one float32 each)")  # fmt: skip
    return np.fromfile(path, dtype="<f4")


def _check_float32_size(path: Path, what: str) -> int:
    """The size of a raw float32 file, checked before reading: np.fromfile silently drops a partial last value."""
    size = path.stat().st_size
    if size % 4:
        raise ValueError(f"{what} {path}: {size} bytes is not a whole number of float32 values (truncated or corrupted?)")
    return size


def bundled_sample_dir() -> Path:
    """Folder of the real nuScenes sample that ships with the package."""
    return Path(str(importlib.resources.files("streamdet.data") / BUNDLED_SAMPLE_DIR))


# ---- fields of the JSON files a dataset is made of ---------------------------------------------------------------
# One vocabulary for every reader of dataset JSON (boxes.json here, the nuScenes tables in nuscenes.py): a field
# is checked against a FieldKind, and a bad one is a ValueError naming the file, the record and the field, never a
# TypeError / OverflowError / KeyError from deep inside numpy. The tests are plain Python on what json.loads gives
# (exact types, no numpy), cheap enough to run on every record a reader uses.


@dataclass(frozen=True)
class FieldKind:
    """What a JSON field must hold: ``test`` it, and ``what`` it must be, in words, for the error message."""

    test: Callable[[object], bool]
    what: str


def numbers(n: int, positive: bool = False) -> FieldKind:
    """Exactly ``n`` finite numbers (``positive``: each > 0), as a JSON list."""

    def test(v: object) -> bool:
        return type(v) is list and len(v) == n and all(is_finite_number(x) and (not positive or x > 0) for x in v)

    return FieldKind(test, f"{n} {'positive ' if positive else ''}finite numbers")


NUMBER = FieldKind(is_finite_number, "a finite number")
COUNT = FieldKind(lambda v: type(v) is int and 0 <= v <= _INT64_MAX, "an integer >= 0 (int64)")
TEXT = FieldKind(lambda v: type(v) is str, "a string")
NAME = FieldKind(lambda v: type(v) is str and v != "", "a non-empty string")
FLAG = FieldKind(lambda v: type(v) is bool, "true or false")
TEXTS = FieldKind(lambda v: type(v) is list and all(type(x) is str for x in v), "a list of strings")


def check_fields(record: object, kinds: Mapping[str, FieldKind], where: str | Callable[[], str],
                 optional: frozenset[str] | set[str] = frozenset()) -> None:  # fmt: skip
    """Check ``record`` (a JSON object) field by field; ``optional`` fields may be absent.

    ``where`` names the record in the error (file, table, row); a callable is called only on an error, for
    readers whose names cost a search (the nuScenes row number).
    """
    if type(record) is not dict:
        raise ValueError(f"{_where(where)}: must be a JSON object, got {short_repr(record)}")
    for name, kind in kinds.items():
        if name not in record:
            if name in optional:
                continue
            raise ValueError(f"{_where(where)}: field {name!r} is missing (fields: {sorted(record)[:20]})")
        if not kind.test(record[name]):
            raise ValueError(f"{_where(where)}: field {name!r} must be {kind.what}, got {short_repr(record[name])}")


def _where(where: str | Callable[[], str]) -> str:
    return where if isinstance(where, str) else where()


def dataset_file(root: str | Path, name: object, where: str | Callable[[], str]) -> Path:
    """``root / name`` for a file that a dataset's own metadata names (a table row, calibration.json), confined.

    ``name`` must be a non-empty relative path without ``..`` (nor a drive, a root or a NUL): a table or a
    calibration file cannot make a reader open a file outside the dataset. Symlinks in the dataset are followed
    wherever they lead: they are the file system's owner's, and nuScenes set-ups link ``samples/`` and ``sweeps/``
    to other disks. The file need not exist: readers check. ValueError naming ``where`` (as in ``check_fields``)
    otherwise.
    """
    if type(name) is not str or not name or "\x00" in name:
        raise ValueError(f"{_where(where)}: file must be a non-empty relative path, got {short_repr(name)}")
    rel = Path(name)
    if rel.is_absolute() or rel.drive or rel.root or ".." in rel.parts:
        raise ValueError(f"{_where(where)}: file {name!r} must be a relative path inside the dataset root {root}, without '..'")
    return Path(root) / rel


def _unknown(c: object) -> bool:
    return c is None or (type(c) is float and math.isnan(c))


# boxes.json records, as load_bundled_sample reads them
_BOX_FIELDS = {
    "center_xyz": numbers(3), "size_wlh": numbers(3, positive=True), "yaw": NUMBER,
    "label": FieldKind(lambda v: type(v) is int and -1 <= v < len(CLASS_NAMES),
                       f"an integer in -1..{len(CLASS_NAMES) - 1} (an index into CLASS_NAMES, -1: other)"),
    # null, or a null / NaN component, where the source had NaN; a bare number or one component would broadcast
    "velocity_xy": FieldKind(lambda v: v is None or (type(v) is list and len(v) == 2
                                                     and all(is_finite_number(c) or _unknown(c) for c in v)),
                             "null or 2 numbers (null or NaN where unknown)"),
    "num_lidar_pts": COUNT, "num_radar_pts": COUNT, "center_global": numbers(3),
}  # fmt: skip


def load_bundled_sample(root: str | Path | None = None) -> Sample:
    """The shipped real nuScenes sample (scene-0061, first key frame): calibration.json, boxes.json and files.

    ``extras["center_global"]`` holds the boxes' global centres as boxes.json gives them (the devkit's numbers).
    Another ``root`` is read as untrusted: every box field is checked, and the files calibration.json names must
    lie inside ``root`` (``dataset_file``); any defect is a ValueError naming the file, box and field.
    """
    what = "bundled sample" if root is None else "sample"  # a user's --sample folder is not the bundled one
    root = Path(root) if root is not None else bundled_sample_dir()
    calib_path = root / "calibration.json"
    boxes_path = root / "boxes.json"
    for p in (calib_path, boxes_path):
        _check_sample_file(p, what)
    calib = read_json(calib_path, "calibration file", MAX_CALIBRATION_BYTES)
    if type(calib) is not dict:  # Rig.from_calibration_json would take a JSON string for a path to open
        raise ValueError(f"calibration file {calib_path}: expected a JSON object at the top level, got {_json_type(calib)}")
    rig = Rig.from_calibration_json(calib, source=str(calib_path))  # CalibrationError (a ValueError) for a malformed rig
    check_fields(calib, {"sample_token": TEXT, "sample_timestamp_us": COUNT}, str(calib_path))
    check_fields(calib["lidar"], {"file": NAME}, f"{calib_path} lidar")  # Rig checked lidar and cameras are objects
    for i, cam in enumerate(calib["cameras"]):
        check_fields(cam, {"file": NAME}, f"{calib_path} cameras[{i}]")
    records = _box_records(read_json(boxes_path, "boxes file", MAX_BOXES_BYTES), boxes_path)
    boxes = np.zeros((len(records), BOX_DIM), dtype=np.float64)
    valid_v = np.ones(len(records), dtype=bool)
    for i, r in enumerate(records):
        check_fields(r, _BOX_FIELDS, f"{boxes_path} boxes[{i}]")
        boxes[i, 0:3] = r["center_xyz"]
        boxes[i, 3:6] = r["size_wlh"]
        boxes[i, 6] = r["yaw"]
        v = r["velocity_xy"]
        if v is None or not all(is_finite_number(c) for c in v):
            valid_v[i] = False
        else:
            boxes[i, 7:9] = v
    labels = np.array([r["label"] for r in records], dtype=np.int64)
    names = tuple(CLASS_NAMES[lab] if lab >= 0 else "other" for lab in labels)
    return Sample(
        token=calib["sample_token"],
        timestamp_us=calib["sample_timestamp_us"],
        points=_load_sample_points(dataset_file(root, calib["lidar"]["file"], f"{calib_path} lidar")),
        rig=rig,
        image_paths={
            c["name"]: dataset_file(root, c["file"], f"{calib_path} cameras[{i}]")
            for i, c in enumerate(calib["cameras"])
        },
        gt_boxes=boxes,
        gt_labels=labels,
        gt_names=names,
        num_lidar_pts=np.array([r["num_lidar_pts"] for r in records], dtype=np.int64),
        num_radar_pts=np.array([r["num_radar_pts"] for r in records], dtype=np.int64),
        velocity_valid=valid_v,
        scene_name=str(calib.get("scene", "")),
        extras={"center_global": np.array([r["center_global"] for r in records], dtype=np.float64).reshape(-1, 3)},  # (M, 3)
    )


def _check_sample_file(path: Path, what: str) -> None:
    """FileNotFoundError for a missing calibration.json / boxes.json of a sample folder, ValueError for one that is
    there but no regular file (a FIFO would block the reader; "not found" would send the user looking for it)."""
    if path.is_file():
        return
    if path.exists():
        raise ValueError(f"{what} file {path} is not a regular file (a FIFO, a device or a folder?)")
    if os.path.islink(path):
        raise FileNotFoundError(f"{what} file {path} is {missing_reason(path)}")
    raise FileNotFoundError(f"{what} file not found: {path} (a sample folder holds calibration.json and boxes.json)")


def _box_records(doc: object, boxes_path: Path) -> list:
    """The ``boxes`` list of a boxes.json document, ValueError naming the file and what its top level is."""
    if type(doc) is not dict:
        raise ValueError(f"{boxes_path}: 'boxes' must be a list in a top-level JSON object, but the top level is "
                         f"{_json_type(doc)}")  # fmt: skip
    if "boxes" not in doc:
        raise ValueError(f"{boxes_path}: 'boxes' must be a list, but the object has no 'boxes' (keys: {sorted(doc)[:20]})")
    if type(doc["boxes"]) is not list:
        raise ValueError(f"{boxes_path}: 'boxes' must be a list, got {_json_type(doc['boxes'])}")
    return doc["boxes"]


def _json_type(value: object) -> str:
    """What a parsed JSON value is, in JSON's words (an array, not a list; null, not NoneType), with the value."""
    if value is None:
        return "null"
    names = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", int: "a number", float: "a number"}
    return f"{names.get(type(value), type(value).__name__)} {short_repr(value)}"


def _load_sample_points(path: Path) -> np.ndarray:
    """The sample's key-frame sweep; an empty one is refused: a key frame without a single LiDAR point is a broken
    recording (a truncated copy, a failed export), and detecting on it would report "0 detections" as a result.
    (Past sweeps and the nuScenes reader keep load_points' leniency.)"""
    return load_points(path, allow_empty=False)


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"size must be positive (width, height) in pixels, got {size!r}")
    return width, height
