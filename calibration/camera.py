"""Pinhole cameras and the camera rig, loaded from calibration.json or nuScenes records (numpy only).

Conventions (the same as data/nuscenes_sample/README.md):

- ``A2B`` maps coordinates from frame A to frame B: ``p_B = R p_A + t``, stored as ``[[R, t], [0, 0, 0, 1]]``.
- Quaternions are ``(w, x, y, z)`` as nuScenes / pyquaternion write them.
- Camera frame is OpenCV (x right, y down, z forward); ``u = (K p)_0 / p_z``, ``v = (K p)_1 / p_z`` with the
  pixel origin at the top-left corner of the image; no distortion.
- ``lidar2cam`` maps the LiDAR frame at the LiDAR timestamp into the camera at the camera timestamp, so it
  already holds the ego motion between the two (the devkit's lidar -> ego -> global -> ego -> cam chain).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import threading
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from streamdet.calibration.projection import project_points, visible_mask
from streamdet.core import rotations
from streamdet.core.file_input import InputFileError, missing_reason, read_regular_file
from streamdet.core.json_input import short_repr
from streamdet.core.sectors import angle_diff_deg

log = logging.getLogger(__name__)

# A rotation read from a float32 source deviates from orthonormal by ~1e-7; a hand-edited or corrupted
# one by far more. Anything between is refused rather than silently re-orthonormalised.
ORTHONORMAL_TOL = 1e-5
QUATERNION_NORM_TOL = 1e-5
# The largest image side, in pixels, of any camera (the manifest schema's image.width/height maximum, the same
# number): past it a calibration is corrupt, and its sizes would overflow float ratios or scale K to nothing.
MAX_IMAGE_PX = 65536
# Past these a camera is corrupt, not unusual: a focal length of 1000 image sides is a field of view under 0.06
# degrees, a principal point 100 sides off the image looks at nothing in it, and a camera 1 km from the LiDAR (ego
# motion between their timestamps included) is not on the vehicle. Such numbers only made a LUT that sees nothing.
MAX_FOCAL_PER_SIDE = 1000.0
MAX_PRINCIPAL_POINT_PER_SIDE = 100.0
MAX_CAMERA_OFFSET_M = 1000.0
# The other end: a focal length under a thousandth of the image side is a field of view over 179.77 degrees across
# it (2 atan(500)), which no distortion-free pinhole has; it maps the whole grid onto a few pixels and makes a LUT
# that is wrong but not blind, so no BlindCameraWarning would say so.
MIN_FOCAL_PER_SIDE = 1e-3
# Skew K[0, 1] = fx cot(theta), theta the angle between the pixel axes. Real sensors have square pixels (the devkit's
# and OpenCV's K have zero skew); a tenth of fx is an axis angle 5.7 degrees off square, far past any calibration
# error, and a huge one shears the image into garbage that is, again, not blind.
MAX_SKEW_PER_FOCAL = 0.1
# A calibration.json transform given both as "matrix" and as "rotation_wxyz" + "translation": written from one float32
# source, the two forms agree to ~1e-7 in the rotation's entries and to float32's rounding of the translation (6e-8 of
# it: 0.06 m of a 1e6 m map coordinate). Past TRANSFORM_FORMS_ATOL (rotation entries; metres) plus TRANSFORM_FORMS_RTOL
# of the entry they say two things, an edit made to one of them alone: refused, since which one was meant is unknown.
TRANSFORM_FORMS_ATOL = 1e-4
TRANSFORM_FORMS_RTOL = 1e-6
# A camera's lidar2img is [K 0; 0 1] @ lidar2cam, written for other tools and never read here. Rounding moves it by
# ~1e-7 of its largest entry (float32 sources); past this fraction of that entry it is another projection.
LIDAR2IMG_RTOL = 1e-5


class CalibrationError(ValueError):
    """A calibration input (file, record, matrix, LUT) is malformed; the message names the field."""


# ---- validation helpers (shared by Camera, Rig and the loaders) -----------------------------------

def _as_array(value: Any, shape: tuple[int, ...], field: str) -> np.ndarray:
    """float64 copy of ``value`` with exactly ``shape`` and only finite entries, else CalibrationError."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:  # OverflowError: a JSON integer past float range (1e400)
        raise CalibrationError(f"{field}: expected a numeric array of shape {shape}, got {short_repr(value)} ({e})") from None
    if arr.shape != shape:
        raise CalibrationError(f"{field}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{field}: contains NaN or infinite values: {short_repr(arr.tolist())}")
    return arr


def _check_rotation(R: np.ndarray, field: str) -> None:
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ORTHONORMAL_TOL:
        raise CalibrationError(f"{field}: rotation is not orthonormal (max |R R^T - I| = {err:.3g} > {ORTHONORMAL_TOL})")
    det = float(np.linalg.det(R))
    if det < 0:
        raise CalibrationError(f"{field}: rotation is a reflection (det = {det:.6f})")


def _as_transform(value: Any, field: str) -> np.ndarray:
    """A rigid 4x4 transform: finite, bottom row (0, 0, 0, 1), orthonormal right-handed rotation."""
    T = _as_array(value, (4, 4), field)
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise CalibrationError(f"{field}: bottom row must be [0, 0, 0, 1], got {T[3].tolist()}")
    _check_rotation(T[:3, :3], field)
    return T


def _as_intrinsics(value: Any, field: str) -> np.ndarray:
    K = _as_array(value, (3, 3), field)
    if np.abs(K[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-9 or K[1, 0] != 0.0:
        raise CalibrationError(f"{field}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"{field}: focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def as_image_px(value: Any, field: str) -> int:
    """An image side in pixels: a positive integer up to MAX_IMAGE_PX, else CalibrationError naming ``field``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 < value <= MAX_IMAGE_PX:
        raise CalibrationError(f"{field}: expected a positive integer pixel count up to {MAX_IMAGE_PX}, got {short_repr(value)}")
    return int(value)


def check_camera_name(name: Any, field: str) -> str:
    """``name`` if it is a non-empty printable string (``str.isprintable``), else CalibrationError quoting its repr:
    names go into log lines, warnings and CLI output, where a newline or a terminal escape would forge or hide text."""
    if not isinstance(name, str) or not name or not name.isprintable():
        raise CalibrationError(f"{field}: expected a non-empty printable string, got {short_repr(name)}")
    return name


def _check_plausible(K: np.ndarray, lidar2cam: np.ndarray, width: int, height: int, where: str) -> None:
    """Refuse intrinsics and offsets no camera on a vehicle has (MAX_FOCAL_PER_SIDE and the constants after it)."""
    side = max(width, height)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    if max(fx, fy) > MAX_FOCAL_PER_SIDE * side:
        raise CalibrationError(f"{where}.K: focal length fx={fx:.6g}, fy={fy:.6g} px is over {MAX_FOCAL_PER_SIDE:g} "
                               f"times the image's {side} px side (a field of view under 0.06 degrees)")
    if min(fx, fy) < MIN_FOCAL_PER_SIDE * side:
        raise CalibrationError(f"{where}.K: focal length fx={fx:.6g}, fy={fy:.6g} px is under {MIN_FOCAL_PER_SIDE:g} "
                               f"times the image's {side} px side (a field of view of almost 180 degrees: no pinhole's)")
    if abs(skew) > MAX_SKEW_PER_FOCAL * fx:
        raise CalibrationError(f"{where}.K: skew K[0][1]={skew:.6g} is over {MAX_SKEW_PER_FOCAL:g} times fx={fx:.6g} "
                               f"(pixel axes {math.degrees(math.atan2(fx, abs(skew))):.3g} degrees apart, not about 90)")
    if max(abs(cx) / width, abs(cy) / height) > MAX_PRINCIPAL_POINT_PER_SIDE:
        raise CalibrationError(f"{where}.K: principal point ({cx:.6g}, {cy:.6g}) px is over "
                               f"{MAX_PRINCIPAL_POINT_PER_SIDE:g} image sides from a {width}x{height} image")
    centre = -lidar2cam[:3, :3].T @ lidar2cam[:3, 3]  # (3,) the camera's centre in the LiDAR frame
    offset_m = float(np.hypot(np.hypot(centre[0], centre[1]), centre[2]))  # hypot: no overflow at 1e308
    if offset_m > MAX_CAMERA_OFFSET_M:
        raise CalibrationError(f"{where}.lidar2cam: the camera is {offset_m:.6g} m from the LiDAR, over "
                               f"{MAX_CAMERA_OFFSET_M:g} m (not a camera on the vehicle)")


# A rig of six cameras is a few kB of JSON; far more than that is not a calibration file (and is not read whole).
MAX_CALIBRATION_BYTES = 4 * 1024 * 1024


def _read_calibration_file(path: str | os.PathLike) -> tuple[Any, str]:
    """(parsed JSON, name for errors) of a calibration file; CalibrationError naming the path as the caller gave it
    (a basename alone does not tell ``cal/a.json`` from ``b/a.json``, and is nothing for ``""``)."""
    src = os.fsdecode(os.fspath(path))
    if not src:
        raise CalibrationError("calibration path is empty ('')")
    try:  # a regular file, bounded: a FIFO (it would block) or a device or a huge file is refused unread
        raw = read_regular_file(src, MAX_CALIBRATION_BYTES)
    except InputFileError as e:
        if e.too_large:
            raise CalibrationError(f"{src}: larger than {MAX_CALIBRATION_BYTES} bytes, too large to be a calibration file") from None
        raise CalibrationError(f"{src}: cannot read: {_unreadable_reason(src, e.reason)}") from None
    return _parse_calibration(lambda: raw.decode("utf-8"), src), src


def _read_calibration_resource(resource: Any) -> tuple[Any, str]:
    """(parsed JSON, name for errors) of an importlib.resources file."""
    src = getattr(resource, "name", "calibration.json")
    return _parse_calibration(lambda: resource.read_text(encoding="utf-8"), src), src


def _parse_calibration(text: Callable[[], str], src: str) -> Any:
    """json.loads of ``text()``, every failure a one-line CalibrationError naming ``src``."""
    try:
        return json.loads(text())
    except UnicodeDecodeError as e:  # a ValueError too: caught before the JSON one below
        raise CalibrationError(f"{src}: not UTF-8 text (a binary file?): {e.reason} at byte {e.start}") from None
    except ValueError as e:  # JSONDecodeError, or an integer literal past Python's 4300-digit limit
        raise CalibrationError(f"{src}: not valid JSON: {e}") from None
    except RecursionError:
        raise CalibrationError(f"{src}: nests too deeply to be a calibration file") from None


def _unreadable_reason(src: str, reason: str) -> str:
    """``reason`` from read_regular_file, told apart where it says "missing" of a path that is a symlink."""
    return missing_reason(src) if reason == "missing" else reason


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)  # own copy: the caller may keep mutating theirs
    a.setflags(write=False)
    return a


# ---- rotations -------------------------------------------------------------------------------------

def quaternion_to_matrix(wxyz: Any, field: str = "quaternion") -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z); norms off by more than 1e-5 are refused (the maths:
    ``core/rotations.py``)."""
    q = _as_array(wxyz, (4,), field)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise CalibrationError(f"{field}: quaternion must have unit norm, got norm {norm:.6g} for {q.tolist()}")
    return rotations.quaternion_to_matrix(q)


def matrix_to_quaternion(R: Any) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a checked (3, 3) rotation (Shepperd's method, stable for all angles;
    ``core/rotations.py``)."""
    R = _as_array(R, (3, 3), "R")
    _check_rotation(R, "R")
    return rotations.matrix_to_quaternion(R)


def make_transform(R: Any, t: Any) -> np.ndarray:
    """(4, 4) ``[[R, t], [0, 0, 0, 1]]`` from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = _as_array(R, (3, 3), "R")
    T[:3, 3] = _as_array(t, (3,), "t")
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, exact in the rotation (R^T) rather than a general inverse."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


# ---- camera ---------------------------------------------------------------------------------------


def optical_axis_azimuth_deg(cam2lidar_rotation: np.ndarray) -> float:
    """Azimuth in [0, 360) of a camera's optical axis (its z) in the LiDAR frame, given the camera -> LiDAR rotation."""
    axis = np.asarray(cam2lidar_rotation, dtype=np.float64) @ np.array([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(axis[1], axis[0])) % 360.0

@dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole camera: intrinsics, LiDAR-to-camera extrinsic and image size."""

    name: str  # e.g. "CAM_FRONT"
    K: np.ndarray  # (3, 3) float64 intrinsics, u = (K p)_0 / p_z (OpenCV camera frame)
    lidar2cam: np.ndarray  # (4, 4) float64, p_cam = R p_lidar + t, ego motion lidar time -> camera time included
    width: int  # image size in pixels
    height: int
    timestamp_us: int | None = None  # capture time; informative only, no geometry depends on it

    def __post_init__(self) -> None:
        check_camera_name(self.name, "Camera.name")
        where = f"Camera {self.name!r}"
        object.__setattr__(self, "K", _readonly(_as_intrinsics(self.K, f"{where}.K")))
        object.__setattr__(self, "lidar2cam", _readonly(_as_transform(self.lidar2cam, f"{where}.lidar2cam")))
        object.__setattr__(self, "width", as_image_px(self.width, f"{where}.width"))
        object.__setattr__(self, "height", as_image_px(self.height, f"{where}.height"))
        _check_plausible(self.K, self.lidar2cam, self.width, self.height, where)
        if self.timestamp_us is not None:
            if isinstance(self.timestamp_us, bool) or not isinstance(self.timestamp_us, (int, np.integer)):
                raise CalibrationError(f"{where}.timestamp_us: expected an integer or None, got {self.timestamp_us!r}")
            object.__setattr__(self, "timestamp_us", int(self.timestamp_us))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.name == other.name
            and (self.width, self.height, self.timestamp_us) == (other.width, other.height, other.timestamp_us)
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.lidar2cam, other.lidar2cam)
        )

    def __hash__(self) -> int:
        return hash((self.name, self.width, self.height, self.K.tobytes(), self.lidar2cam.tobytes()))

    @property
    def projection_matrix(self) -> np.ndarray:
        """(3, 4) ``K [R | t]``: homogeneous LiDAR point -> (u z, v z, z)."""
        return self.K @ self.lidar2cam[:3]

    @property
    def center_lidar(self) -> np.ndarray:
        """(3,) optical centre in the LiDAR frame."""
        R, t = self.lidar2cam[:3, :3], self.lidar2cam[:3, 3]
        return -R.T @ t

    def project(self, points_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (N, 2) float64 and depth (N,) float64 of (N, 3+) LiDAR points; depth <= 0 means behind."""
        return project_points(points_lidar, self.K, self.lidar2cam)

    def visible(self, points_lidar: np.ndarray, min_depth_m: float = 0.0) -> np.ndarray:
        """(N,) bool: depth > min_depth_m and 0 <= u < width and 0 <= v < height."""
        uv, depth = self.project(points_lidar)
        return visible_mask(uv, depth, self.width, self.height, min_depth_m)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for the image resized to (width, height): pixel corners scale, so K rows scale."""
        width = as_image_px(width, "width")
        height = as_image_px(height, "height")
        scale = np.diag([width / self.width, height / self.height, 1.0])
        return Camera(self.name, scale @ self.K, self.lidar2cam, width, height, self.timestamp_us)

    def border_rays_lidar(self, samples_per_edge: int = 33) -> np.ndarray:
        """(4 * samples_per_edge, 3) unit directions, LiDAR frame, of rays through the image border."""
        s = np.linspace(0.0, 1.0, samples_per_edge)
        w, h = float(self.width), float(self.height)
        u = np.concatenate([s * w, s * w, np.zeros_like(s), np.full_like(s, w)])
        v = np.concatenate([np.zeros_like(s), np.full_like(s, h), s * h, s * h])
        pix = np.stack([u, v, np.ones_like(u)], axis=0)  # (3, B)
        rays_cam = np.linalg.solve(self.K, pix)  # (3, B)
        rays = self.lidar2cam[:3, :3].T @ rays_cam  # (3, B) camera -> LiDAR axes
        return (rays / np.linalg.norm(rays, axis=0)).T  # (B, 3)

    @property
    def axis_azimuth_deg(self) -> float:
        """Azimuth in [0, 360) of the optical axis (camera z) in the LiDAR frame."""
        return optical_axis_azimuth_deg(self.lidar2cam[:3, :3].T)

    @property
    def fov_azimuth_deg(self) -> tuple[float, float]:
        """Horizontal field of view as an azimuth interval (lo, hi) in degrees, LiDAR frame, of ray directions.

        lo is in [0, 360) and hi > lo may exceed 360. Directions, not points: the ~1 m offset between the camera
        and the LiDAR is ignored, which is exact far away (see ``sectors.py`` for the near-range test).
        """
        rays = self.border_rays_lidar()
        centre = self.axis_azimuth_deg
        rel = angle_diff_deg(np.degrees(np.arctan2(rays[:, 1], rays[:, 0])), centre)
        lo = (centre + float(rel.min())) % 360.0
        return lo, lo + float(rel.max() - rel.min())


# ---- rig --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Rig:
    """The cameras of one sample in a fixed order (the J axis everywhere) plus the LiDAR's poses."""

    cameras: tuple[Camera, ...]  # order = order of images / feature maps / LUT camera index j
    lidar2ego: np.ndarray  # (4, 4) LiDAR -> ego frame
    ego2global: np.ndarray  # (4, 4) ego pose at the LiDAR timestamp (identity if unknown)

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if not cams:
            raise CalibrationError("Rig.cameras: a rig needs at least one camera")
        for i, cam in enumerate(cams):
            if not isinstance(cam, Camera):
                raise CalibrationError(f"Rig.cameras[{i}]: expected a Camera, got {type(cam).__name__}")
        names = [c.name for c in cams]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CalibrationError(f"Rig.cameras: duplicate camera names {dupes}")
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "lidar2ego", _readonly(_as_transform(self.lidar2ego, "Rig.lidar2ego")))
        object.__setattr__(self, "ego2global", _readonly(_as_transform(self.ego2global, "Rig.ego2global")))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Rig):
            return NotImplemented
        return (
            self.cameras == other.cameras
            and np.array_equal(self.lidar2ego, other.lidar2ego)
            and np.array_equal(self.ego2global, other.ego2global)
        )

    def __hash__(self) -> int:
        return hash((self.cameras, self.lidar2ego.tobytes(), self.ego2global.tobytes()))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    def camera(self, name: str) -> Camera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r}; the rig has {list(self.names)}")

    def resized(self, width: int, height: int) -> "Rig":
        return Rig(tuple(c.resized(width, height) for c in self.cameras), self.lidar2ego, self.ego2global)

    def without(self, names: str | Iterable[str]) -> "Rig":
        """The rig minus the named cameras (robustness studies); unknown names raise KeyError."""
        drop = {names} if isinstance(names, str) else set(names)
        unknown = sorted(drop - set(self.names))
        if unknown:
            raise KeyError(f"cannot drop unknown cameras {unknown}; the rig has {list(self.names)}")
        kept = tuple(c for c in self.cameras if c.name not in drop)
        if not kept:
            raise CalibrationError(f"Rig.without({sorted(drop)}): would drop every camera")
        return Rig(kept, self.lidar2ego, self.ego2global)

    # ---- serialisation ----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """A calibration.json-compatible dict (the subset ``from_calibration_json`` reads)."""
        return {
            "lidar": {
                "sensor2ego": {"matrix": self.lidar2ego.tolist()},
                "ego2global": {"matrix": self.ego2global.tolist()},
            },
            "cameras": [
                {
                    "name": c.name,
                    "width": c.width,
                    "height": c.height,
                    "timestamp_us": c.timestamp_us,
                    "K": c.K.tolist(),
                    "lidar2cam": {"matrix": c.lidar2cam.tolist()},
                }
                for c in self.cameras
            ],
        }

    def sha256(self) -> str:
        """Canonical hash of the projection geometry: camera names and order, sizes, K, lidar2cam, lidar2ego.

        The ego pose and timestamps are left out on purpose: they change every frame without changing where a
        voxel projects, and a LUT must stay valid across frames of a static rig.
        """
        h = hashlib.sha256()
        h.update(b"streamdet-rig-v1")
        for c in self.cameras:
            h.update(json.dumps([c.name, c.width, c.height]).encode())
            h.update(np.ascontiguousarray(c.K, dtype="<f8").tobytes())
            h.update(np.ascontiguousarray(c.lidar2cam, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.lidar2ego, dtype="<f8").tobytes())
        return h.hexdigest()

    # ---- loaders ----------------------------------------------------------------------------------
    @classmethod
    def from_calibration_json(cls, path_or_dict: str | os.PathLike | Mapping, source: str | None = None) -> "Rig":
        """Rig from the calibration.json format of data/nuscenes_sample: a path, an importlib.resources file, or the
        parsed dict (``to_dict()`` output included).

        Errors name the path as given; for a parsed dict they name ``source`` (the file it was read from, where the
        caller knows it), else "calibration". Any other argument (a list, None, bytes) is a CalibrationError: a JSON
        document that is not an object must not be taken for a path and opened.

        Read: ``lidar.sensor2ego``, ``lidar.ego2global`` (optional: identity) and each camera's ``name``, ``K``,
        ``width``, ``height``, ``lidar2cam`` and ``timestamp_us`` (optional). A transform is its ``matrix``, else its
        ``rotation_wxyz`` + ``translation``; given both ways they must agree (TRANSFORM_FORMS_ATOL). Each camera's
        ``lidar2cam`` is used as stored: it must hold the ego motion between the LiDAR's timestamp and the camera's.
        Not read: a camera's ``sensor2ego`` and ``ego2global``, ``note`` and the file's other fields; a camera's
        ``lidar2img`` is only compared with ``K @ lidar2cam`` (a warning where it differs: ``check_lidar2img``).
        docs/architecture.md, "calibration.json".
        """
        if isinstance(path_or_dict, Mapping):
            doc, src = path_or_dict, source or "calibration"
        elif isinstance(path_or_dict, (str, os.PathLike)):
            doc, src = _read_calibration_file(path_or_dict)
        elif hasattr(path_or_dict, "read_text"):
            # an importlib.resources Traversable (the bundled sample inside a zipped install)
            doc, src = _read_calibration_resource(path_or_dict)
        else:
            raise CalibrationError(f"{source or 'calibration'}: expected a path to a calibration.json or its parsed "
                                   f"JSON object, got {type(path_or_dict).__name__} {short_repr(path_or_dict)}")
        if not isinstance(doc, Mapping):
            raise CalibrationError(f"{src}: expected a JSON object at the top level, got {type(doc).__name__}")

        lidar = _field(doc, "lidar", src, "")
        lidar2ego = transform_entry(_field(lidar, "sensor2ego", src, "lidar."), src, "lidar.sensor2ego")
        pose = lidar.get("ego2global") if isinstance(lidar, Mapping) else None
        ego2global = np.eye(4) if pose is None else transform_entry(pose, src, "lidar.ego2global")

        cams_doc = _field(doc, "cameras", src, "")
        if not isinstance(cams_doc, list) or not cams_doc:
            raise CalibrationError(f"{src}: cameras: expected a non-empty list, got {short_repr(cams_doc)}")
        cameras = []
        for i, c in enumerate(cams_doc):
            at = f"cameras[{i}]"
            if not isinstance(c, Mapping):
                raise CalibrationError(f"{src}: {at}: expected an object, got {short_repr(c)}")
            name = _wrap(check_camera_name, _field(c, "name", src, f"{at}."), src, f"{at}.name")
            K = _wrap(_as_intrinsics, _field(c, "K", src, f"{at}."), src, f"{at}.K")
            lidar2cam = transform_entry(_field(c, "lidar2cam", src, f"{at}."), src, f"{at}.lidar2cam")
            width = _wrap(as_image_px, _field(c, "width", src, f"{at}."), src, f"{at}.width")
            height = _wrap(as_image_px, _field(c, "height", src, f"{at}."), src, f"{at}.height")
            ts = c.get("timestamp_us")
            if ts is not None and (isinstance(ts, bool) or not isinstance(ts, int)):
                raise CalibrationError(f"{src}: {at}.timestamp_us: expected an integer or null, got {ts!r}")
            try:  # what only the whole camera can tell (_check_plausible)
                cameras.append(Camera(name, K, lidar2cam, width, height, ts))
            except CalibrationError as e:
                raise CalibrationError(f"{src}: {at}: {e}") from None
            if "lidar2img" in c:
                check_lidar2img(c["lidar2img"], cameras[-1], src, at)
        try:
            return cls(tuple(cameras), lidar2ego, ego2global)
        except CalibrationError as e:
            raise CalibrationError(f"{src}: {e}") from None

    @classmethod
    def from_nuscenes_records(
        cls, lidar_sensor: Mapping, lidar_pose: Mapping, cameras: list[Mapping]
    ) -> "Rig":
        """Rig from nuScenes ``calibrated_sensor`` and ``ego_pose`` records, chained like the devkit.

        lidar2cam = inv(cam2ego) @ inv(ego2global(t_cam)) @ ego2global(t_lidar) @ lidar2ego, i.e. the LiDAR
        frame at the LiDAR time is carried through the global frame into the camera at its own time.
        Each camera dict: {"name", "calibrated_sensor", "ego_pose", "width", "height", "timestamp_us"}.
        """
        src = "nuscenes records"
        lidar2ego = _record_transform(lidar_sensor, src, "lidar_sensor")
        ego2global = _record_transform(lidar_pose, src, "lidar_pose")
        lidar2global = ego2global @ lidar2ego
        if not isinstance(cameras, (list, tuple)) or not cameras:
            raise CalibrationError(f"{src}: cameras: expected a non-empty list, got {short_repr(cameras)}")
        out = []
        for i, c in enumerate(cameras):
            at = f"cameras[{i}]"
            if not isinstance(c, Mapping):
                raise CalibrationError(f"{src}: {at}: expected an object, got {short_repr(c)}")
            name = _field(c, "name", src, f"{at}.")
            sensor = _field(c, "calibrated_sensor", src, f"{at}.")
            cam2ego = _record_transform(sensor, src, f"{at}.calibrated_sensor")
            cam_pose = _record_transform(_field(c, "ego_pose", src, f"{at}."), src, f"{at}.ego_pose")
            K = _wrap(_as_intrinsics, _field(sensor, "camera_intrinsic", src, f"{at}.calibrated_sensor."),
                      src, f"{at}.calibrated_sensor.camera_intrinsic")
            lidar2cam = invert_transform(cam2ego) @ invert_transform(cam_pose) @ lidar2global
            width = _wrap(as_image_px, _field(c, "width", src, f"{at}."), src, f"{at}.width")
            height = _wrap(as_image_px, _field(c, "height", src, f"{at}."), src, f"{at}.height")
            try:
                out.append(Camera(name, K, lidar2cam, width, height, c.get("timestamp_us")))
            except CalibrationError as e:
                raise CalibrationError(f"{src}: {at}: {e}") from None
        try:
            return cls(tuple(out), lidar2ego, ego2global)
        except CalibrationError as e:
            raise CalibrationError(f"{src}: {e}") from None


def _field(obj: Any, key: str, src: str, at: str) -> Any:
    if not isinstance(obj, Mapping):
        raise CalibrationError(f"{src}: {at.rstrip('.') or 'top level'}: expected an object, got {short_repr(obj)}")
    if key not in obj:
        raise CalibrationError(f"{src}: {at}{key}: missing field")
    return obj[key]


def _wrap(check, value: Any, src: str, field: str):
    """Run a ``_as_*`` check whose messages name ``field``, prefixed with the source."""
    try:
        return check(value, field)
    except CalibrationError as e:
        raise CalibrationError(f"{src}: {e}") from None


def transform_entry(entry: Any, src: str, at: str) -> np.ndarray:
    """A calibration.json transform: {"matrix": 4x4} or {"rotation_wxyz", "translation"}; a rotation or translation
    given beside the matrix must agree with it (TRANSFORM_FORMS_ATOL), else CalibrationError naming the entry."""
    if not isinstance(entry, Mapping):
        raise CalibrationError(f"{src}: {at}: expected an object with 'matrix', got {short_repr(entry)}")
    m = _wrap(_as_transform, entry["matrix"], src, f"{at}.matrix") if "matrix" in entry else None
    R = t = None
    if "rotation_wxyz" in entry:
        R = _wrap(quaternion_to_matrix, entry["rotation_wxyz"], src, f"{at}.rotation_wxyz")
    if "translation" in entry:
        t = _wrap(lambda v, f: _as_array(v, (3,), f), entry["translation"], src, f"{at}.translation")
    if m is not None:
        # the matrix is what is read: a rotation or translation beside it must say the same (TRANSFORM_FORMS_ATOL)
        for name, alt, got in (("rotation_wxyz", R, m[:3, :3]), ("translation", t, m[:3, 3])):
            if alt is None:
                continue
            diff = np.abs(got - alt)
            if np.any(diff > TRANSFORM_FORMS_ATOL + TRANSFORM_FORMS_RTOL * np.abs(alt)):
                raise CalibrationError(
                    f"{src}: {at}: matrix and {name} disagree (max |diff| {float(diff.max()):.3g}, over "
                    f"{TRANSFORM_FORMS_ATOL:g} + {TRANSFORM_FORMS_RTOL:g} of the entry): keep the one meant, drop the other"
                )
        return m
    if R is not None and t is not None:
        return make_transform(R, t)
    raise CalibrationError(f"{src}: {at}.matrix: missing field (nor rotation_wxyz + translation)")


_lidar2img_lock = threading.Lock()
_lidar2img_warned: set[tuple[str, bytes]] = set()  # (camera, its lidar2img's bytes) said once, not per republish


def check_lidar2img(value: Any, camera: "Camera", src: str, at: str) -> None:
    """Log a warning, once per camera and value, where a camera entry's ``lidar2img`` (its ``matrix``, 3x4 or 4x4)
    is not ``K @ lidar2cam[:3]`` beyond rounding (LIDAR2IMG_RTOL), naming the camera and the difference.

    Warned, not refused: the projection is K and lidar2cam, and lidar2img is never read. Other tools write it for
    their own image size or crop, so a refusal would reject a calibration whose read fields are right; an engineer
    who edited lidar2img instead of lidar2cam still learns that the edit did nothing. One that cannot be read as a
    matrix is informational all the same: not compared, and not an error."""
    matrix = value.get("matrix") if isinstance(value, Mapping) else value
    try:
        given = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return
    if given.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(given)):
        return
    want = camera.projection_matrix  # (3, 4)
    diff = float(np.abs(given[:3] - want).max())
    if diff <= LIDAR2IMG_RTOL * float(np.abs(want).max()):
        return
    key = (camera.name, given.tobytes())
    with _lidar2img_lock:
        if key in _lidar2img_warned:
            return
        if len(_lidar2img_warned) >= 256:  # a caller editing it over and over: bounded, it may warn again
            _lidar2img_warned.clear()
        _lidar2img_warned.add(key)
    log.warning("%s: %s.lidar2img of camera %s differs from K @ lidar2cam by up to %.6g: lidar2img is not read (the "
                "projection is K and lidar2cam); edit those to change where this camera looks", src, at, camera.name, diff)


def _record_transform(record: Any, src: str, at: str) -> np.ndarray:
    """A nuScenes calibrated_sensor / ego_pose record {"rotation": [w, x, y, z], "translation": [3]}."""
    R = _wrap(quaternion_to_matrix, _field(record, "rotation", src, f"{at}."), src, f"{at}.rotation")
    t = _wrap(lambda v, f: _as_array(v, (3,), f), _field(record, "translation", src, f"{at}."), src, f"{at}.translation")
    return make_transform(R, t)
