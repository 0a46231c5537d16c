"""``sensor_msgs/CameraInfo`` + TF -> the ``Rig`` (calibration.json types) the projection LUT is built from.

The rig's ``lidar2cam`` holds the ego motion between the LiDAR and the camera times, as nuScenes does:
``inv(cam2ego) @ inv(ego2global(t_cam)) @ ego2global(t_lidar) @ lidar2ego``. The TF tree gives each factor
(``ego_frame -> sensor frame`` mountings from ``/tf_static``, ``global_frame -> ego_frame`` from ``/tf`` at the two
stamps), and the composition is ``Rig.from_nuscenes_records``, the very code that reads the nuScenes tables, so a
bag written from the tables gives back the identical rig and LUT. Without a global frame (a stack without
localisation) the ego motion is left out.

The camera model is the rig's: pinhole, no distortion. A CameraInfo with non-zero distortion is refused unless
the images are the rectified ones and ``intrinsics="p"`` takes the projection matrix's left 3x3 as their K.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.runtime_ort.ros.header import header_msg, header_stamp_ns, int_field, shown
from streamdet.runtime_ort.ros.tf import TfBuffer

IDENTITY_RECORD = {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]}
MSG = "sensor_msgs/CameraInfo"


def camera_info_intrinsics(msg: Any, intrinsics: str = "k") -> dict:
    """``{"camera_intrinsic": 3x3, "width", "height"}`` of a CameraInfo; refuses what the pinhole rig cannot hold."""
    if intrinsics not in ("k", "p"):
        raise ValueError(f"intrinsics must be 'k' or 'p' (the rectified projection), got {intrinsics!r}")
    frame = str(msg.header.frame_id)
    where = f"{MSG} of {frame!r}"
    d = _numbers(msg.d, where, "d")
    if intrinsics == "k" and d.size and np.any(d != 0):
        if not np.isfinite(d).all():
            raise ValueError(f"{where}: d={d.tolist()} holds non-finite distortion coefficients")
        raise ValueError(
            f"{where} has distortion ({msg.distortion_model}, d={d.tolist()}): streamdet's camera model has none; "
            "feed the rectified images and read their CameraInfo with intrinsics='p'"
        )
    # uint32 fields: int() would turn -1 into a binning that passes, and None or NaN into TypeError / its own message
    binning = (int_field(msg.binning_x, f"{where}: binning_x"), int_field(msg.binning_y, f"{where}: binning_y"))
    if any(b > 1 for b in binning):
        raise ValueError(f"{where} has binning {binning}; streamdet takes full-resolution images (binning 0 or 1)")
    roi = {f: int_field(getattr(msg.roi, f), f"{where}: roi.{f}") for f in ("x_offset", "y_offset", "height", "width")}
    if any(roi.values()):
        raise ValueError(f"{where} has a region of interest ({roi['width']}x{roi['height']}); streamdet takes full images")
    if intrinsics == "k":
        K = _numbers(msg.k, where, "k")
        if K.size != 9:
            raise ValueError(f"{where}: k must hold 9 values, got {K.size}")
        values, K = K, K.reshape(3, 3)
    else:
        values = _numbers(msg.p, where, "p")
        if values.size != 12:
            raise ValueError(f"{where}: p must hold 12 values, got {values.size}")
        K = values.reshape(3, 4)[:, :3]
    # refused here by field: the Rig would refuse a NaN or zero K later, without saying it came from this message
    if not np.isfinite(values).all():
        raise ValueError(f"{where}: {intrinsics} holds non-finite values {values.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{where}: {intrinsics} focal lengths fx={K[0, 0]}, fy={K[1, 1]} must be > 0")
    width, height = int_field(msg.width, f"{where}: width"), int_field(msg.height, f"{where}: height")
    if width <= 0 or height <= 0:
        raise ValueError(f"{where}: image size {width}x{height} must be positive")
    return {"camera_intrinsic": K.tolist(), "width": width, "height": height}


def _numbers(values: Any, where: str, name: str) -> np.ndarray:
    """A ``float64[]`` field as a flat float64 array. None, strings and nested or mixed lists are refused by name:
    np.asarray(None, dtype=float) is [nan] (read as distortion), and numpy's own message names no field."""
    try:
        raw = np.asarray(values)
    except ValueError:  # ragged
        raw = None
    if raw is None or raw.dtype.kind not in "iuf":
        raise ValueError(f"{where}: {name} must be a list of numbers, got {shown(values)}")
    return raw.astype(np.float64).reshape(-1)


def rig_from_ros(
    camera_infos: Mapping[str, Any],
    tf: TfBuffer,
    lidar_frame: str,
    lidar_stamp_ns: int,
    camera_stamps_ns: Mapping[str, int] | None = None,
    ego_frame: str = "base_link",
    global_frame: str | None = "map",
    order: Sequence[str] | None = None,
    intrinsics: str = "k",
) -> Rig:
    """The rig of one image set: cameras (named by the keys of ``camera_infos``, in ``order``) with their
    CameraInfo, the TF mountings and the ego poses at the LiDAR stamp and at each camera's stamp.

    ``camera_stamps_ns`` are the stamps of the images used (default: each CameraInfo's own stamp).
    """
    names = list(order) if order is not None else list(camera_infos)
    missing = [n for n in names if n not in camera_infos]
    if missing:
        raise ValueError(f"no CameraInfo for cameras {missing}; have {sorted(camera_infos)}")
    stamps = dict(camera_stamps_ns or {})

    def pose(stamp: int) -> dict:
        return tf.lookup(global_frame, ego_frame, stamp) if global_frame else IDENTITY_RECORD

    lidar_sensor = tf.lookup(ego_frame, lidar_frame, lidar_stamp_ns)
    cameras = []
    for name in names:
        info = camera_infos[name]
        stamp = int(stamps.get(name, header_stamp_ns(info, MSG)))
        mount = tf.lookup(ego_frame, str(info.header.frame_id), stamp)
        sensor = {**mount, "camera_intrinsic": camera_info_intrinsics(info, intrinsics)["camera_intrinsic"]}
        cameras.append({
            "name": name,
            "calibrated_sensor": sensor,
            "ego_pose": pose(stamp),
            "width": int(info.width),
            "height": int(info.height),
            "timestamp_us": stamp // 1000,
        })  # fmt: skip
    return Rig.from_nuscenes_records(lidar_sensor, pose(int(lidar_stamp_ns)), cameras)


def camera_info_message(K: np.ndarray, width: int, height: int, stamp_ns: int, frame_id: str) -> dict:
    """A ``sensor_msgs/CameraInfo`` dict of a distortion-free pinhole camera (rectified: R = I, P = [K | 0])."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "header": header_msg(stamp_ns, frame_id),
        "height": int(height),
        "width": int(width),
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": K.reshape(-1).tolist(),
        "r": np.eye(3).reshape(-1).tolist(),
        "p": P.reshape(-1).tolist(),
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }

