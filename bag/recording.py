"""A drive as a car records it: every LiDAR sweep and camera image of one scene with its sensor mounting and
ego pose, read from a nuScenes-format dataset (the tables, e.g. ``streamdet-synth`` output) or from the bundled
real sample (``calibration.json`` layout, one key frame).

Poses are kept as nuScenes records ``{"rotation": [w, x, y, z], "translation": [x, y, z]}`` with the tables'
own numbers, so the bag carries them unchanged and a reader rebuilds the rig with the same arithmetic. The bundled
sample's come from its rig (``Rig.from_calibration_json``), so its bag gives back that rig, not a second reading of
calibration.json.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# transform_entry: how the Rig reads a calibration.json transform (matrix, or rotation_wxyz + translation)
from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.calibration.camera import (
    MAX_CALIBRATION_BYTES, Camera, CalibrationError, Rig, transform_entry, invert_transform, matrix_to_quaternion)
from streamdet.core.json_input import read_json
from streamdet.data.nuscenes import LIDAR_CHANNEL, NuScenesReader
from streamdet.data.sample import (
    COUNT, FieldKind, Sample, bundled_sample_dir, check_fields, load_bundled_sample, load_point_times, load_points)
from streamdet.runtime_ort.ros.header import INT32_MAX

Record = dict  # {"rotation": [w, x, y, z], "translation": [x, y, z]}


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """A key frame's annotated boxes in its LiDAR frame."""

    boxes: np.ndarray  # (M, 9) x, y, z, w, l, h, yaw, vx, vy
    labels: np.ndarray  # (M,) int64 index into CLASS_NAMES, -1 outside the detection classes
    names: tuple[str, ...]  # (M,) class name, or the raw category for label -1

    @classmethod
    def of(cls, sample: Sample) -> "GroundTruth":
        return cls(sample.gt_boxes, sample.gt_labels, tuple(sample.gt_names))


@dataclass(frozen=True, eq=False)
class LidarSweep:
    timestamp_us: int  # nuScenes: the end of the sweep
    ego_pose: Record  # ego -> global at timestamp_us
    sample_token: str | None  # the key frame's sample token; None for a sweep between key frames
    gt: GroundTruth | None  # the key frame's ground truth; None between key frames
    path: Path | None = None  # the .pcd.bin, read when the sweep is written: a scene never sits in memory
    points_in_memory: np.ndarray | None = None  # (N, 5) when there is no file to read (the bundled sample)

    def load(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(points (N, 5) float32 x, y, z, intensity, ring; per-point firing time after the sweep start (N,)
        float32, or None where the data has none)."""
        if self.path is None:
            return self.points_in_memory, None
        points = load_points(self.path)
        return points, load_point_times(self.path, len(points))


@dataclass(frozen=True, eq=False)
class CameraImage:
    name: str  # channel, e.g. "CAM_FRONT"
    timestamp_us: int
    path: Path  # the JPEG, written to the bag byte for byte
    K: np.ndarray  # (3, 3) intrinsics of the image as stored
    width: int
    height: int
    ego_pose: Record  # ego -> global at timestamp_us


@dataclass(frozen=True, eq=False)
class Recording:
    scene: str
    lidar_mount: Record  # LIDAR_TOP -> ego
    camera_mounts: dict[str, Record]  # camera -> ego, in the dataset's camera order
    sweeps: tuple[LidarSweep, ...]  # time order
    images: tuple[CameraImage, ...]  # time order


def read_recording(data_dir: str | Path | None, scene: str | None = None, version: str = DEFAULT_TABLE_VERSION) -> Recording:
    """The scene ``scene`` of the nuScenes-format dataset in ``data_dir``; a folder holding ``calibration.json``
    (or None: the bundled sample) is read as the bundled real sample's one key frame.

    Both are read by the toolkit's own readers, as untrusted input: the tables through ``NuScenesReader`` (a malformed
    row is a ValueError naming table, row and field; a file a row names must lie inside the dataset root), the sample
    through ``load_bundled_sample`` and ``Rig.from_calibration_json``. A bag export then fails where eval and replay
    fail, with their words, and carries the rig they use."""
    if data_dir is None or (Path(data_dir) / "calibration.json").is_file():
        return _bundled(data_dir, scene)
    return _tables(Path(data_dir), scene, version)


# Every message of a bag is stamped in ROS 2 time (builtin_interfaces/Time: int32 seconds) and logged in MCAP's
# uint64 nanoseconds: a timestamp outside both cannot be written, and is refused where it is read, by field,
# rather than as a struct.error (a negative one) or an unnamed stamp (a huge one) half-way through the bag.
MAX_STAMP_US = INT32_MAX * 1_000_000 + 999_999
STAMP_US = FieldKind(lambda v: COUNT.test(v) and v <= MAX_STAMP_US,
                     f"an integer of microseconds in 0..{MAX_STAMP_US} (a ROS 2 stamp holds int32 seconds)")  # fmt: skip


# How far the bundled sample's lidar2cam may come back off through the bag's TF chain (metres, and rotation matrix
# entries): the rotations the rig takes may be off orthonormal by ORTHONORMAL_TOL (1e-5), and the chain inverts them
# by transposing (the shipped sample: 6e-8 off); a millimetre more means numbers float64 cannot carry (poses 1e308 m
# from the map origin, which the rig's finite-number checks pass).
MAX_CHAIN_ERROR = 1e-3


def _tables(root: Path, scene: str | None, version: str) -> Recording:
    reader = NuScenesReader(root, version)  # every table loaded and indexed by token; a row's fields checked on use
    table_dir = root / version
    scenes = {s["name"]: s for s in (reader.row("scene", r) for r in reader.rows("scene"))}
    if scene is None:
        if len(scenes) != 1:
            raise ValueError(f"{root} holds {len(scenes)} scenes; name one with --scene: {sorted(scenes)}")
        scene = next(iter(scenes))
    if scene not in scenes:
        raise ValueError(f"scene {scene!r} not found in {table_dir}; it has {sorted(scenes)}")
    scene_token = scenes[scene]["token"]
    # every sample's scene followed, as eval does: one naming no scene is an error, not a key frame left out
    samples = {s["token"] for s in (reader.row("sample", r) for r in reader.rows("sample"))
               if reader.ref("sample", s, "scene_token", "scene")["token"] == scene_token}  # fmt: skip
    # the scene's rows are checked before they are read; so is a row whose sample_token is no string (it cannot be
    # told to be another scene's, and skipping it would drop data silently); other scenes' rows are not read
    rows = [reader.row("sample_data", r) for r in reader.rows("sample_data")
            if type(r.get("sample_token")) is not str or r["sample_token"] in samples]  # fmt: skip
    mounts: dict[str, Record] = {}
    sweeps, images = [], []
    for sd in sorted(rows, key=lambda r: r["timestamp"]):
        channel = reader.channel(sd)
        if channel != LIDAR_CHANNEL and not channel.startswith("CAM_"):
            continue  # radar and the like: not in the bag
        cs = reader.ref("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
        pose = _record(reader.ref("sample_data", sd, "ego_pose_token", "ego_pose"))
        mount = _record(cs)
        if mounts.setdefault(channel, mount) != mount:
            raise ValueError(f"{channel} changes its calibrated_sensor within scene {scene!r}; a bag holds one mounting")
        # the reader's own naming of a row (table, file, row number, token), as its checks word it
        check_fields(sd, {"timestamp": STAMP_US}, lambda: reader.row_name("sample_data", sd))
        path = reader.file(sd)  # inside the dataset root, a regular file
        if channel == LIDAR_CHANNEL:
            key = sd["is_key_frame"]
            token = sd["sample_token"] if key else None
            gt = GroundTruth.of(reader.get(token)) if key else None
            sweeps.append(LidarSweep(sd["timestamp"], pose, token, gt, path=path))
        else:
            camera = _camera(channel, cs.get("camera_intrinsic", []), sd["width"], sd["height"],
                             lambda: f"{reader.row_name('sample_data', sd)} and its calibrated_sensor")  # fmt: skip
            images.append(CameraImage(channel, sd["timestamp"], path, camera.K, camera.width, camera.height, pose))
    if LIDAR_CHANNEL not in mounts:
        raise ValueError(f"scene {scene!r} of {table_dir} has no {LIDAR_CHANNEL} data")
    cameras = {name: mounts[name] for name in mounts if name.startswith("CAM_")}
    return Recording(scene, mounts[LIDAR_CHANNEL], cameras, tuple(sweeps), tuple(images))


def _camera(name: str, K: object, width: object, height: object, where: Callable[[], str]) -> Camera:
    """The pinhole camera an image is taken with, checked as a rig's cameras are (``Camera``: a 3x3 upper-triangular
    K with positive focal lengths, a plausible field of view, 1..MAX_IMAGE_PX a side). Key frames' cameras go through
    the rig of ``NuScenesReader.get`` too; the images between key frames (12 Hz in nuScenes) only through this."""
    try:
        return Camera(name, K, np.eye(4), width, height)  # no extrinsic: the bag carries the mounting and poses
    except CalibrationError as e:
        raise ValueError(f"{where()}: not a camera the toolkit takes: {e}") from None


def _bundled(root: str | Path | None, scene: str | None) -> Recording:
    """The sample's one key frame. Its transforms are the rig's (``Rig.from_calibration_json``, which takes a
    transform as ``matrix`` or as ``rotation_wxyz`` + ``translation``, and each camera's ``lidar2cam`` as stored):
    the LiDAR mounting and pose as the rig holds them, each camera's mounting chosen so that the bag's TF chain
    (``inv(cam2ego) @ inv(ego2global(t_cam)) @ ego2global(t_lidar) @ lidar2ego``) gives back the rig's lidar2cam."""
    sample = load_bundled_sample(root)  # calibration.json through the Rig, boxes.json and the files checked
    folder = bundled_sample_dir() if root is None else Path(root)
    calib_path = folder / "calibration.json"
    calib = read_json(calib_path, "calibration file", MAX_CALIBRATION_BYTES)
    rig = Rig.from_calibration_json(calib, source=str(calib_path))  # this very document's rig (the sample's, checked)
    if scene is not None and scene != sample.scene_name:
        raise ValueError(f"the sample in {folder} is of scene {sample.scene_name!r}, not {scene!r}")
    check_fields(calib, {"sample_timestamp_us": STAMP_US}, str(calib_path))
    lidar2global = rig.ego2global @ rig.lidar2ego
    images, cameras = [], {}
    for i, (entry, cam) in enumerate(zip(calib["cameras"], rig.cameras)):
        at = f"cameras[{i}]"
        check_fields(entry, {"timestamp_us": STAMP_US}, f"{calib_path} {at}")  # the rig takes null; a bag stamps the image
        # the ego pose at the camera's time where the file gives one, else the LiDAR's (no motion known: the rig's
        # lidar2cam holds whatever there was, and the mounting below takes it up)
        pose = rig.ego2global if "ego2global" not in entry else transform_entry(entry["ego2global"], str(calib_path), f"{at}.ego2global")
        cam2ego = invert_transform(pose) @ lidar2global @ invert_transform(cam.lidar2cam)
        # the chain a reader of the bag composes must give back the rig's lidar2cam: poses far past any map cancel to
        # nothing in float64, and the bag would carry another rig
        error = float(np.abs(invert_transform(cam2ego) @ invert_transform(pose) @ lidar2global - cam.lidar2cam).max())
        if not error <= MAX_CHAIN_ERROR:
            raise ValueError(f"{calib_path} {at}: its lidar2cam cannot be carried as a mounting beside lidar.sensor2ego, "
                             f"lidar.ego2global and {at}.ego2global: the bag's TF chain gives it back {error:.3g} off, "
                             f"over {MAX_CHAIN_ERROR:g} (translations too large for float64?)")  # fmt: skip
        cameras[cam.name] = _matrix_record(cam2ego, f"{calib_path} {at}: the mounting its lidar2cam implies")
        images.append(CameraImage(cam.name, entry["timestamp_us"], sample.image_paths[cam.name], cam.K, cam.width, cam.height,
                                  _matrix_record(pose, f"{calib_path} {at}.ego2global")))  # fmt: skip
    sweep = LidarSweep(sample.timestamp_us, _matrix_record(rig.ego2global, f"{calib_path} lidar.ego2global"), sample.token,
                       GroundTruth.of(sample), points_in_memory=sample.points)  # fmt: skip
    lidar_mount = _matrix_record(rig.lidar2ego, f"{calib_path} lidar.sensor2ego")
    return Recording(sample.scene_name, lidar_mount, cameras, (sweep,), tuple(sorted(images, key=lambda c: c.timestamp_us)))


def _record(row: dict) -> Record:
    """A checked nuScenes calibrated_sensor / ego_pose row as a Record, its numbers as the table gives them."""
    return {"rotation": [float(v) for v in row["rotation"]], "translation": [float(v) for v in row["translation"]]}


def _matrix_record(T: np.ndarray, where: str) -> Record:
    """A rigid (4, 4) transform of the rig as a Record (unit quaternion w >= 0, translation). The rotation goes to
    the nearest one first: the rig takes rotations within ORTHONORMAL_TOL of one, and a camera's mounting is the product
    of three such, up to three times as far off; a quaternion holds the nearest rotation anyway."""
    try:
        u, _, vt = np.linalg.svd(T[:3, :3])
        q = matrix_to_quaternion(u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt)
    except (CalibrationError, np.linalg.LinAlgError) as e:  # a product of checked rotations: not expected
        raise ValueError(f"{where}: not a rotation: {e}") from None
    return {"rotation": [float(v) for v in q], "translation": [float(v) for v in T[:3, 3]]}
