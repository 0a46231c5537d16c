"""A drive as a car records it: every LiDAR sweep and camera image of one scene with its sensor mounting and
ego pose, read from a nuScenes-format dataset (the tables, e.g. ``streamdet-synth`` output) or from the bundled
real sample (``calibration.json`` layout, one key frame).

Poses are kept as nuScenes records ``{"rotation": [w, x, y, z], "translation": [x, y, z]}`` with the tables'
own numbers, so the bag carries them unchanged and a reader rebuilds the rig with the same arithmetic.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.data.nuscenes import LIDAR_CHANNEL, NuScenesReader
from streamdet.data.sample import Sample, load_bundled_sample, load_point_times, load_points

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


def read_recording(data_dir: str | Path | None, scene: str | None = None, version: str = "v1.0-synth") -> Recording:
    """The scene ``scene`` of the nuScenes-format dataset in ``data_dir``; a folder holding ``calibration.json``
    (or None: the bundled sample) is read as the bundled real sample's one key frame."""
    if data_dir is None or (Path(data_dir) / "calibration.json").is_file():
        return _bundled(data_dir, scene)
    return _tables(Path(data_dir), scene, version)


def _tables(root: Path, scene: str | None, version: str) -> Recording:
    reader = NuScenesReader(root, version)
    table_dir = root / version
    rows = {name: json.loads((table_dir / f"{name}.json").read_text()) for name in
            ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor")}  # fmt: skip
    scenes = {s["name"]: s for s in rows["scene"]}
    if scene is None:
        if len(scenes) != 1:
            raise ValueError(f"{root} holds {len(scenes)} scenes; name one with --scene: {sorted(scenes)}")
        scene = next(iter(scenes))
    if scene not in scenes:
        raise ValueError(f"scene {scene!r} not found in {table_dir}; it has {sorted(scenes)}")
    scene_token = scenes[scene]["token"]
    samples = {s["token"] for s in rows["sample"] if s["scene_token"] == scene_token}
    by_token = {name: {r["token"]: r for r in rows[name]} for name in ("calibrated_sensor", "ego_pose", "sensor")}
    sensors = by_token["sensor"]
    channel_of_cs = {t: sensors[cs["sensor_token"]]["channel"] for t, cs in by_token["calibrated_sensor"].items()}
    mounts: dict[str, Record] = {}
    sweeps, images = [], []
    for sd in sorted((r for r in rows["sample_data"] if r["sample_token"] in samples), key=lambda r: r["timestamp"]):
        channel = channel_of_cs[sd["calibrated_sensor_token"]]
        cs = by_token["calibrated_sensor"][sd["calibrated_sensor_token"]]
        pose = _record(by_token["ego_pose"][sd["ego_pose_token"]])
        mount = _record(cs)
        if mounts.setdefault(channel, mount) != mount:
            raise ValueError(f"{channel} changes its calibrated_sensor within scene {scene!r}; a bag holds one mounting")
        path = root / sd["filename"]
        if channel == LIDAR_CHANNEL:
            if not path.is_file():
                raise FileNotFoundError(f"LiDAR file of sample_data {sd['token']} not found: {path}")
            key = bool(sd["is_key_frame"])
            token = sd["sample_token"] if key else None
            gt = GroundTruth.of(reader.get(token)) if key else None
            sweeps.append(LidarSweep(int(sd["timestamp"]), pose, token, gt, path=path))
        elif channel.startswith("CAM_"):
            if not path.is_file():
                raise FileNotFoundError(f"image of sample_data {sd['token']} not found: {path}")
            images.append(CameraImage(channel, int(sd["timestamp"]), path, np.asarray(cs["camera_intrinsic"], np.float64),
                                      int(sd["width"]), int(sd["height"]), pose))  # fmt: skip
    if LIDAR_CHANNEL not in mounts:
        raise ValueError(f"scene {scene!r} of {table_dir} has no {LIDAR_CHANNEL} data")
    cameras = {name: mounts[name] for name in mounts if name.startswith("CAM_")}
    return Recording(scene, mounts[LIDAR_CHANNEL], cameras, tuple(sweeps), tuple(images))


def _bundled(root: str | Path | None, scene: str | None) -> Recording:
    sample = load_bundled_sample(root)
    folder = sample.image_paths[sample.rig.names[0]].parent
    calib = json.loads((folder / "calibration.json").read_text())
    if scene is not None and scene != sample.scene_name:
        raise ValueError(f"the sample in {folder} is of scene {sample.scene_name!r}, not {scene!r}")
    lidar = calib["lidar"]
    images = tuple(
        CameraImage(c["name"], int(c["timestamp_us"]), folder / c["file"], np.asarray(c["K"], np.float64),
                    int(c["width"]), int(c["height"]), _calib_record(c["ego2global"]))  # fmt: skip
        for c in sorted(calib["cameras"], key=lambda c: c["timestamp_us"])
    )
    sweep = LidarSweep(sample.timestamp_us, _calib_record(lidar["ego2global"]), sample.token, GroundTruth.of(sample),
                       points_in_memory=sample.points)  # fmt: skip
    cameras = {c["name"]: _calib_record(c["sensor2ego"]) for c in calib["cameras"]}
    return Recording(sample.scene_name, _calib_record(lidar["sensor2ego"]), cameras, (sweep,), images)


def _record(row: dict) -> Record:
    return {"rotation": [float(v) for v in row["rotation"]], "translation": [float(v) for v in row["translation"]]}


def _calib_record(entry: dict) -> Record:
    return _record({"rotation": entry["rotation_wxyz"], "translation": entry["translation"]})
