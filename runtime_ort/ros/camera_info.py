"""``sensor_msgs/CameraInfo`` + TF -> the ``Rig`` (calibration.json types) the projection LUT is built from.

The rig's ``lidar2cam`` holds the ego motion between the LiDAR and the camera times, as nuScenes does:
``inv(cam2ego) @ inv(ego2global(t_cam)) @ ego2global(t_lidar) @ lidar2ego``. The TF tree gives each factor
(``ego_frame -> sensor frame`` mountings from ``/tf_static``, ``global_frame -> ego_frame`` from ``/tf`` at the two
stamps), and the composition is ``Rig.from_nuscenes_records``, the very code that reads the nuScenes tables, so a
bag written from the tables gives back the identical rig and LUT. Without a global frame (a stack without
localisation) the ego motion is left out.

The camera model is the rig's: pinhole, no distortion. A CameraInfo with non-zero distortion is refused unless
the images are the rectified ones and ``intrinsics="p"`` takes the projection matrix's left 3x3 as their K.

A rectified image is not taken in the camera's TF frame: CameraInfo defines ``x_rect = R x_cam`` (R rotates the
optical frame onto the rectified image plane) and ``pixels ~ P [x_rect; 1]``. With ``intrinsics="p"``, ``rig_from_ros``
folds R into the camera's mounting (the rectified camera is the optical frame turned by R about its own centre, so
its pose is ``cam2ego @ R^T``), which is exact. P's 4th column is refused when non-zero: it is a stereo pair's second
camera (``Tx = -fx' * baseline``), whose P projects points given in the first camera's rectified frame, and whether
the TF frame of its CameraInfo is that frame or its own cannot be told from the message, so the baseline would be
applied twice or not at all.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from streamdet.calibration.camera import ORTHONORMAL_TOL, Rig, matrix_to_quaternion, quaternion_to_matrix
from streamdet.runtime_ort.ros.header import RosMessageError, header_frame_id, header_msg, header_stamp_ns, int_field, shown
from streamdet.runtime_ort.ros.tf import TfBuffer

IDENTITY_RECORD = {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]}
MSG = "sensor_msgs/CameraInfo"


def camera_info_intrinsics(msg: Any, intrinsics: str = "k") -> dict:
    """``{"camera_intrinsic": 3x3, "width", "height"}`` of a CameraInfo; refuses what the pinhole rig cannot hold.

    ``intrinsics="p"``: the rectified image's K, P's left 3x3. Its camera is the TF frame turned by R
    (``camera_info_rectification``), which ``rig_from_ros`` folds into the mounting; a caller building its own rig
    from this K must do the same."""
    _check_intrinsics_kind(intrinsics)
    frame = header_frame_id(msg, MSG)
    where = f"{MSG} of {frame!r}"
    d = _numbers(msg.d, where, "d")
    if intrinsics == "k" and d.size and np.any(d != 0):
        if not np.isfinite(d).all():
            raise RosMessageError(f"{where}: d={d.tolist()} holds non-finite distortion coefficients")
        raise RosMessageError(
            f"{where} has distortion ({msg.distortion_model}, d={d.tolist()}): streamdet's camera model has none; "
            "feed the rectified images and read their CameraInfo with intrinsics='p'"
        )
    # uint32 fields: int() would turn -1 into a binning that passes, and None or NaN into TypeError / its own message
    binning = (int_field(msg.binning_x, f"{where}: binning_x"), int_field(msg.binning_y, f"{where}: binning_y"))
    if any(b > 1 for b in binning):
        raise RosMessageError(f"{where} has binning {binning}; streamdet takes full-resolution images (binning 0 or 1)")
    roi = {f: int_field(getattr(msg.roi, f), f"{where}: roi.{f}") for f in ("x_offset", "y_offset", "height", "width")}
    if any(roi.values()):
        raise RosMessageError(f"{where} has a region of interest ({roi['width']}x{roi['height']}); streamdet takes full images")
    if intrinsics == "k":
        K = _numbers(msg.k, where, "k")
        if K.size != 9:
            raise RosMessageError(f"{where}: k must hold 9 values, got {K.size}")
        values, K = K, K.reshape(3, 3)
    else:
        values = _numbers(msg.p, where, "p")
        if values.size != 12:
            raise RosMessageError(f"{where}: p must hold 12 values, got {values.size}")
        K = values.reshape(3, 4)[:, :3]
        shift = values.reshape(3, 4)[:, 3]
        if np.isfinite(shift).all() and np.any(shift != 0):
            raise RosMessageError(
                f"{where}: p's 4th column [Tx, Ty, Tz] = {shift.tolist()} is not zero: a stereo pair's second camera "
                "(Tx = -fx' * baseline), whose P projects points of the first camera's rectified frame, while streamdet "
                f"places each camera at its own TF frame ({frame!r}) and cannot tell which one that is; use the first "
                "camera of the pair, or publish this one as a monocular camera (P[:, 3] = 0) with its own optical frame"
            )
    # refused here by field: the Rig would refuse a NaN or zero K later, without saying it came from this message
    if not np.isfinite(values).all():
        raise RosMessageError(f"{where}: {intrinsics} holds non-finite values {values.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise RosMessageError(f"{where}: {intrinsics} focal lengths fx={K[0, 0]}, fy={K[1, 1]} must be > 0")
    width, height = int_field(msg.width, f"{where}: width"), int_field(msg.height, f"{where}: height")
    if width <= 0 or height <= 0:
        raise RosMessageError(f"{where}: image size {width}x{height} must be positive")
    return {"camera_intrinsic": K.tolist(), "width": width, "height": height}


def camera_info_rectification(msg: Any, intrinsics: str = "k") -> np.ndarray:
    """(3, 3) rotation from a CameraInfo's optical frame (its TF frame) to the frame its images are taken in:
    R (``x_rect = R x_cam``) for ``intrinsics="p"`` (rectified images), the identity for "k" (raw images, which R does
    not concern). R must be a rotation (orthonormal within calibration's ORTHONORMAL_TOL, det +1): a zero R (an
    uncalibrated driver) or a reflection is refused by name rather than taken as the identity."""
    _check_intrinsics_kind(intrinsics)
    if intrinsics == "k":
        return np.eye(3)
    where = f"{MSG} of {header_frame_id(msg, MSG)!r}"
    R = _numbers(msg.r, where, "r")
    if R.size != 9:
        raise RosMessageError(f"{where}: r must hold 9 values, got {R.size}")
    R = R.reshape(3, 3)
    error = float(np.abs(R @ R.T - np.eye(3)).max()) if np.isfinite(R).all() else np.inf
    if not (error <= ORTHONORMAL_TOL and np.linalg.det(R) > 0):
        raise RosMessageError(f"{where}: r = {R.reshape(-1).tolist()} is not a rotation (max |R R^T - I| = {error:.3g}, "
                              f"tolerance {ORTHONORMAL_TOL}; det must be +1): the rectified frame is unknown")  # fmt: skip
    if np.array_equal(R, np.eye(3)):
        return np.eye(3)
    u, _, vt = np.linalg.svd(R)  # the nearest exact rotation: R's rounding (6-8 digits in calibration files) stays out
    return u @ vt


def _check_intrinsics_kind(intrinsics: str) -> None:
    if intrinsics not in ("k", "p"):
        raise ValueError(f"intrinsics must be 'k' or 'p' (the rectified projection), got {intrinsics!r}")


def _rectified_mount(mount: dict, R: np.ndarray) -> dict:
    """The mounting record of the rectified camera: the optical frame turned by R about its centre. x_cam = R^T x_rect,
    so rect2ego = cam2ego @ [R^T | 0]; the translation (the optical centre) is the same point."""
    if np.array_equal(R, np.eye(3)):
        return mount  # untouched: the common case keeps TF's own numbers, bit for bit
    rotation = quaternion_to_matrix(mount["rotation"]) @ R.T
    return {"rotation": matrix_to_quaternion(rotation).tolist(), "translation": list(mount["translation"])}


def _numbers(values: Any, where: str, name: str) -> np.ndarray:
    """A ``float64[]`` field as a flat float64 array. None, strings and nested or mixed lists are refused by name:
    np.asarray(None, dtype=float) is [nan] (read as distortion), and numpy's own message names no field."""
    try:
        raw = np.asarray(values)
    except ValueError:  # ragged
        raw = None
    if raw is None or raw.dtype.kind not in "iuf":
        raise RosMessageError(f"{where}: {name} must be a list of numbers, got {shown(values)}")
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

    ``camera_stamps_ns`` are the stamps of the images used (default: each CameraInfo's own stamp). With
    ``intrinsics="p"`` each camera's R is folded into its mounting (``camera_info_rectification``).
    """
    names = list(order) if order is not None else list(camera_infos)
    missing = [n for n in names if n not in camera_infos]
    if missing:
        raise RosMessageError(f"no CameraInfo for cameras {missing}; have {sorted(camera_infos)}")
    stamps = dict(camera_stamps_ns or {})

    def pose(stamp: int) -> dict:
        return tf.lookup(global_frame, ego_frame, stamp) if global_frame else IDENTITY_RECORD

    lidar_sensor = tf.lookup(ego_frame, lidar_frame, lidar_stamp_ns)
    cameras = []
    for name in names:
        info = camera_infos[name]
        stamp = int(stamps.get(name, header_stamp_ns(info, MSG)))
        K = camera_info_intrinsics(info, intrinsics)["camera_intrinsic"]  # first: it names a malformed message best
        mount = tf.lookup(ego_frame, header_frame_id(info, MSG), stamp)
        sensor = {**_rectified_mount(mount, camera_info_rectification(info, intrinsics)), "camera_intrinsic": K}
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

