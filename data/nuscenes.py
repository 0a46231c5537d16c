"""A reader of the official nuScenes JSON tables and file layout, without the nuscenes-devkit package.

``DATAROOT/<version>/*.json`` holds the tables (v1.0-mini, v1.0-trainval, or the synthetic v1.0-synth written
by ``streamdet-synth``); ``DATAROOT/samples/...`` and ``DATAROOT/sweeps/...`` the files, named by
``sample_data.filename``. The geometry follows the devkit:

- boxes go global -> ego (at the LiDAR timestamp) -> LiDAR, quaternions composed the same way; yaw is the
  rotation about z of the box in the LiDAR frame, ``atan2(R[1, 0], R[0, 0])`` (pyquaternion's yaw);
- velocity is ``NuScenes.box_velocity`` (centred difference of the neighbouring annotations' global centres,
  one-sided at a track's ends, NaN for a lone annotation or a gap over 1.5 s, 3 s when centred), rotated into
  the LiDAR frame with its z set to 0 first as mmdetection3d does; NaN becomes 0 with ``velocity_valid`` False;
- ``Sample.point_time_s`` comes from the optional ``<file>.time`` beside a LiDAR file (synthetic data), else None;
- past sweeps follow the LiDAR ``sample_data.prev`` chain and are moved into the key frame's LiDAR frame via the
  global frame, with their time lag (key frame minus sweep timestamp), as nuScenes multi-sweep detectors do.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from streamdet.calibration.camera import Rig, invert_transform, make_transform, quaternion_to_matrix
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.data.sample import Sample, Sweep, load_point_times, load_points

LIDAR_CHANNEL = "LIDAR_TOP"
# mmdetection3d / the devkit's camera order; the J axis of every image tensor.
CAMERA_CHANNELS: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
# The devkit's category -> detection class mapping (nuscenes/eval/detection/utils.py).
CATEGORY_TO_CLASS: dict[str, str] = {
    "movable_object.barrier": "barrier",
    "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.car": "car",
    "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle",
    "human.pedestrian.adult": "pedestrian",
    "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "human.pedestrian.police_officer": "pedestrian",
    "movable_object.trafficcone": "traffic_cone",
    "vehicle.trailer": "trailer",
    "vehicle.truck": "truck",
}
REQUIRED_TABLES = (
    "category",
    "attribute",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
)
MAX_VELOCITY_TIME_DIFF_S = 1.5  # the devkit's box_velocity default


class NuScenesReader:
    """Samples (key frames) of a nuScenes-format dataset, in the order of the ``sample`` table."""

    def __init__(self, root: str | Path, version: str = "v1.0-mini") -> None:
        self.root = Path(root)
        self.version = version
        table_dir = self.root / version
        if not table_dir.is_dir():
            raise FileNotFoundError(f"nuScenes table folder not found: {table_dir} (version {version!r} under {self.root})")
        tables = {name: _load_table(table_dir, name) for name in REQUIRED_TABLES}
        self._by_token = {name: {r["token"]: r for r in rows} for name, rows in tables.items()}
        self._samples = tables["sample"]
        channel_of_cs = {
            cs["token"]: self._get("sensor", cs["sensor_token"])["channel"] for cs in tables["calibrated_sensor"]
        }
        self._channel_of_sd = {sd["token"]: channel_of_cs[sd["calibrated_sensor_token"]] for sd in tables["sample_data"]}
        self._key_data: dict[str, dict[str, str]] = {s["token"]: {} for s in self._samples}
        for sd in tables["sample_data"]:
            if sd["is_key_frame"]:
                self._key_data[sd["sample_token"]][self._channel_of_sd[sd["token"]]] = sd["token"]
        self._anns: dict[str, list[str]] = {s["token"]: [] for s in self._samples}
        for ann in tables["sample_annotation"]:
            self._anns[ann["sample_token"]].append(ann["token"])
        self._category_of_instance = {
            inst["token"]: self._get("category", inst["category_token"])["name"] for inst in tables["instance"]
        }

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def sample_tokens(self) -> list[str]:
        return [s["token"] for s in self._samples]

    def scene_name(self, sample_token: str) -> str:
        return self._get("scene", self._get("sample", sample_token)["scene_token"])["name"]

    def get(self, token_or_index: str | int, num_past_sweeps: int = 0) -> Sample:
        """The sample with its LiDAR sweep, up to ``num_past_sweeps`` earlier sweeps, images, rig and boxes."""
        if isinstance(token_or_index, (int, np.integer)) and not isinstance(token_or_index, bool):
            if not -len(self) <= token_or_index < len(self):
                raise IndexError(f"sample index {token_or_index} out of range for {len(self)} samples")
            record = self._samples[token_or_index]
        else:
            record = self._get("sample", token_or_index)
        if not isinstance(num_past_sweeps, (int, np.integer)) or num_past_sweeps < 0:
            raise ValueError(f"num_past_sweeps must be a non-negative integer, got {num_past_sweeps!r}")
        data = self._key_data[record["token"]]
        if LIDAR_CHANNEL not in data:
            raise KeyError(f"sample {record['token']} has no key-frame {LIDAR_CHANNEL} sample_data")
        lidar_sd = self._get("sample_data", data[LIDAR_CHANNEL])
        lidar_cs = self._get("calibrated_sensor", lidar_sd["calibrated_sensor_token"])
        lidar_pose = self._get("ego_pose", lidar_sd["ego_pose_token"])
        cams = []
        image_paths = {}
        for channel in [c for c in CAMERA_CHANNELS if c in data] + sorted(
            c for c in data if c.startswith("CAM_") and c not in CAMERA_CHANNELS
        ):
            sd = self._get("sample_data", data[channel])
            cams.append(
                {
                    "name": channel,
                    "calibrated_sensor": self._get("calibrated_sensor", sd["calibrated_sensor_token"]),
                    "ego_pose": self._get("ego_pose", sd["ego_pose_token"]),
                    "width": int(sd["width"]),
                    "height": int(sd["height"]),
                    "timestamp_us": int(sd["timestamp"]),
                }
            )
            image_paths[channel] = self._file(sd)
        if not cams:
            raise KeyError(f"sample {record['token']} has no key-frame camera sample_data")
        rig = Rig.from_nuscenes_records(lidar_cs, lidar_pose, cams)
        lidar2global = rig.ego2global @ rig.lidar2ego
        boxes = self._boxes(record["token"], rig)
        lidar_path = self._file(lidar_sd)
        points = load_points(lidar_path)
        return Sample(
            token=record["token"],
            timestamp_us=int(lidar_sd["timestamp"]),
            points=points,
            point_time_s=load_point_times(lidar_path, len(points)),
            rig=rig,
            image_paths=image_paths,
            sweeps=self._past_sweeps(lidar_sd, lidar2global, int(num_past_sweeps)),
            scene_name=self.scene_name(record["token"]),
            **boxes,
        )

    # ---- internals --------------------------------------------------------------------------------
    def _get(self, table: str, token: str) -> dict:
        try:
            return self._by_token[table][token]
        except KeyError:
            raise KeyError(f"token {token!r} not found in table {table!r} of {self.root / self.version}") from None

    def _file(self, sd: dict) -> Path:
        path = self.root / sd["filename"]
        if not path.is_file():
            raise FileNotFoundError(f"file of sample_data {sd['token']} not found: {path}")
        return path

    def _boxes(self, sample_token: str, rig: Rig) -> dict:
        anns = [self._get("sample_annotation", t) for t in self._anns[sample_token]]
        m = len(anns)
        global2lidar = invert_transform(rig.ego2global @ rig.lidar2ego)
        boxes = np.zeros((m, BOX_DIM), dtype=np.float64)
        labels = np.full(m, -1, dtype=np.int64)
        names = []
        velocity = np.zeros((m, 3))
        for i, ann in enumerate(anns):
            box2global = make_transform(quaternion_to_matrix(ann["rotation"]), ann["translation"])
            box2lidar = global2lidar @ box2global
            boxes[i, 0:3] = box2lidar[:3, 3]
            boxes[i, 3:6] = ann["size"]  # w, l, h
            boxes[i, 6] = np.arctan2(box2lidar[1, 0], box2lidar[0, 0])
            velocity[i] = self._box_velocity(ann)
            category = self._category_of_instance[ann["instance_token"]]
            cls = CATEGORY_TO_CLASS.get(category)
            if cls is not None:
                labels[i] = CLASS_NAMES.index(cls)
            names.append(cls if cls is not None else category)
        valid = np.all(np.isfinite(velocity[:, :2]), axis=1)
        velocity[:, 2] = 0.0  # mmdetection3d keeps the ground-plane velocity only
        velocity[~valid] = 0.0
        boxes[:, 7:9] = (velocity @ global2lidar[:3, :3].T)[:, :2]
        attributes = []
        for ann in anns:
            tokens = ann.get("attribute_tokens", [])
            attributes.append(self._get("attribute", tokens[0])["name"] if len(tokens) == 1 else "")
        return {
            "gt_boxes": boxes,
            "gt_labels": labels,
            "gt_names": tuple(names),
            "num_lidar_pts": np.array([a.get("num_lidar_pts", 0) for a in anns], dtype=np.int64),
            "num_radar_pts": np.array([a.get("num_radar_pts", 0) for a in anns], dtype=np.int64),
            "velocity_valid": valid,
            "instance_tokens": tuple(a["instance_token"] for a in anns),
            "annotation_tokens": tuple(a["token"] for a in anns),
            "attribute_names": tuple(attributes),
        }

    def _box_velocity(self, ann: dict) -> np.ndarray:
        """Global (3,) velocity exactly as the devkit's ``NuScenes.box_velocity``."""
        has_prev, has_next = ann["prev"] != "", ann["next"] != ""
        if not has_prev and not has_next:
            return np.full(3, np.nan)
        first = self._get("sample_annotation", ann["prev"]) if has_prev else ann
        last = self._get("sample_annotation", ann["next"]) if has_next else ann
        time_diff = 1e-6 * (
            self._get("sample", last["sample_token"])["timestamp"] - self._get("sample", first["sample_token"])["timestamp"]
        )
        max_diff = MAX_VELOCITY_TIME_DIFF_S * (2 if has_prev and has_next else 1)
        if time_diff > max_diff or time_diff <= 0:
            return np.full(3, np.nan)
        return (np.asarray(last["translation"], dtype=np.float64) - np.asarray(first["translation"], dtype=np.float64)) / time_diff

    def _past_sweeps(self, lidar_sd: dict, lidar2global: np.ndarray, count: int) -> tuple[Sweep, ...]:
        sweeps = []
        global2lidar = invert_transform(lidar2global)
        sd = lidar_sd
        while len(sweeps) < count and sd["prev"] != "":
            sd = self._get("sample_data", sd["prev"])
            cs = self._get("calibrated_sensor", sd["calibrated_sensor_token"])
            pose = self._get("ego_pose", sd["ego_pose_token"])
            sweep2global = _record_to_matrix(pose) @ _record_to_matrix(cs)
            sweep2key = global2lidar @ sweep2global
            points = load_points(self._file(sd)).copy()
            points[:, :3] = points[:, :3] @ sweep2key[:3, :3].T.astype(np.float32) + sweep2key[:3, 3].astype(np.float32)
            sweeps.append(
                Sweep(
                    token=sd["token"],
                    timestamp_us=int(sd["timestamp"]),
                    time_lag_s=1e-6 * (int(lidar_sd["timestamp"]) - int(sd["timestamp"])),
                    points=points,
                )
            )
        return tuple(sweeps)


def _record_to_matrix(record: dict) -> np.ndarray:
    return make_transform(quaternion_to_matrix(record["rotation"]), record["translation"])


def _load_table(table_dir: Path, name: str) -> list[dict]:
    path = table_dir / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"nuScenes table {name!r} not found: {path}")
    try:
        rows = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"nuScenes table {name!r} ({path}) is not valid JSON: {e}") from None
    if not isinstance(rows, list):
        raise ValueError(f"nuScenes table {name!r} ({path}) must be a JSON list of records, got {type(rows).__name__}")
    return rows
