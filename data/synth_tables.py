"""The nuScenes tables of a synthetic dataset (``data/synth_writer.py`` generates it): the rows of one scene as its
frames are simulated (``Tables``), and the 13 table files written at the end (``write_tables``). Tokens are pure
functions of the seed and what they name, so a dataset regenerates identically.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from streamdet.calibration.camera import matrix_to_quaternion
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.rotations import yaw_to_quaternion
from streamdet.data.nuscenes import LIDAR_CHANNEL
from streamdet.data.sample import POINT_TIME_SUFFIX
from streamdet.data.synth_masks import MASK_NONE, mask_path, write_mask
from streamdet.data.synth_world import KIND_SPECS, NUM_ANNOTATED_KINDS, Kind, Scene

if TYPE_CHECKING:
    from streamdet.data.synth_lidar import SimSweep
    from streamdet.data.synth_writer import RigRecords, SimFrame, SynthConfig

# Kind -> index into CLASS_NAMES for the annotated kinds (MASK_NONE for the others: a mask's class where no box is).
CLASS_OF_KIND = np.array([CLASS_NAMES.index(s.detection_class) if s.detection_class else MASK_NONE for s in KIND_SPECS], dtype=np.uint8)
VISIBILITY_LEVELS = (("1", "v0-40", 0.4), ("2", "v40-60", 0.6), ("3", "v60-80", 0.8), ("4", "v80-100", 1.01))
ATTRIBUTES = (
    "vehicle.moving",
    "vehicle.stopped",
    "vehicle.parked",
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "pedestrian.moving",
)
ATTRIBUTE_NAMES = ("", *ATTRIBUTES)  # attribute_indices' codes: 0 = none

TABLE_NAMES = (
    "category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose",
    "log", "scene", "sample", "sample_data", "sample_annotation", "map",
)  # fmt: skip


def token(*parts) -> str:
    """A 32-hex-digit token (nuScenes style), a pure function of its parts."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def link_records(records: list[dict]) -> None:
    for a, b in zip(records[:-1], records[1:]):
        a["next"] = b["token"]
        b["prev"] = a["token"]


class Tables:
    """Accumulates the table rows of one scene (and builds the tables all scenes share)."""

    NAMES = TABLE_NAMES
    SCENE_TABLES = ("instance", "calibrated_sensor", "ego_pose", "log", "scene", "sample", "sample_data", "sample_annotation")

    def __init__(self, seed: int) -> None:
        self.seed = seed
        self.rows: dict[str, list[dict]] = {name: [] for name in self.NAMES}
        self.category_token: dict[int, str] = {}
        self.attribute_token: dict[str, str] = {}
        self._scene_samples: list[dict] = []
        self._instances: dict[int, list[dict]] = {}

    def tok(self, *parts) -> str:
        return token("streamdet-synth", self.seed, *parts)

    def static(self, rig: RigRecords) -> dict[str, list[dict]]:
        """Fill the tables shared by all scenes (category, attribute, visibility, sensor); returns all rows."""
        for kind in range(NUM_ANNOTATED_KINDS):
            spec = KIND_SPECS[kind]
            token = self.tok("category", spec.category)
            self.category_token[kind] = token
            self.rows["category"].append({"token": token, "name": spec.category, "description": f"synthetic {spec.detection_class}"})
        for name in ATTRIBUTES:
            token = self.tok("attribute", name)
            self.attribute_token[name] = token
            self.rows["attribute"].append({"token": token, "name": name, "description": name.replace(".", ": ").replace("_", " ")})
        for token, level, _ in VISIBILITY_LEVELS:
            self.rows["visibility"].append({"description": f"visibility of whole object is between {level[1:]} %", "token": token, "level": level})
        for channel, modality in [(LIDAR_CHANNEL, "lidar")] + [(c["name"], "camera") for c in rig.cameras]:
            self.rows["sensor"].append({"token": self.tok("sensor", channel), "channel": channel, "modality": modality})
        return self.rows

    def scene_start(self, scene: Scene, rig: RigRecords) -> tuple[str, dict[str, str]]:
        log_token = self.tok("log", scene.name)
        self.rows["log"].append(
            {"token": log_token, "logfile": scene.name, "vehicle": "synth", "date_captured": "2020-09-13", "location": "synthetic-street"}
        )
        sensor_tokens = {}
        records = [(LIDAR_CHANNEL, rig.lidar["translation"], rig.lidar["rotation"], [])]
        records += [(c["name"], c["translation"], c["rotation"], c["camera_intrinsic"]) for c in rig.cameras]
        for channel, translation, rotation, intrinsic in records:
            token = self.tok("calibrated_sensor", scene.name, channel)
            sensor_tokens[channel] = token
            self.rows["calibrated_sensor"].append(
                {"token": token, "sensor_token": self.tok("sensor", channel), "translation": translation,
                 "rotation": rotation, "camera_intrinsic": intrinsic}
            )
        self._scene_samples = []
        self._instances = {}
        self._last_camera_row: dict[str, dict] = {}  # by channel: the scene's latest camera sample_data row
        return log_token, sensor_tokens

    def sample(self, scene: Scene, frame: SimFrame) -> str:
        token = self.tok("sample", scene.name, frame.index)
        row = {"token": token, "timestamp": frame.timestamp_us, "prev": "", "next": "", "scene_token": self.tok("scene", scene.name)}
        self.rows["sample"].append(row)
        self._scene_samples.append(row)
        return token

    def ego_pose(self, scene: Scene, t_s: float, key: str) -> str:
        pose = scene.ego2global(t_s)
        token = self.tok("ego_pose", scene.name, key)
        self.rows["ego_pose"].append(
            {"token": token, "timestamp": scene.timestamp_us(t_s), "rotation": matrix_to_quaternion(pose[:3, :3]).tolist(),
             "translation": pose[:3, 3].tolist()}
        )
        return token

    def lidar_data(self, out: Path, scene: Scene, sample_token: str, sweep: SimSweep, sensor_tokens: dict, key: bool) -> dict:
        ts = scene.timestamp_us(sweep.t_end_s)
        folder = "samples" if key else "sweeps"
        filename = f"{folder}/{LIDAR_CHANNEL}/{scene.name}__{LIDAR_CHANNEL}__{ts}.pcd.bin"
        path = out / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        np.ascontiguousarray(sweep.points, dtype="<f4").tofile(path)
        # streamdet extension beside the nuScenes file: each point's firing time after the sweep start.
        np.ascontiguousarray(sweep.time_s, dtype="<f4").tofile(path.with_name(path.name + POINT_TIME_SUFFIX))
        row = {
            "token": self.tok("sample_data", scene.name, LIDAR_CHANNEL, ts),
            "sample_token": sample_token,
            "ego_pose_token": self.ego_pose(scene, sweep.t_end_s, f"{LIDAR_CHANNEL}/{ts}"),
            "calibrated_sensor_token": sensor_tokens[LIDAR_CHANNEL],
            "timestamp": ts,
            "fileformat": "pcd",
            "is_key_frame": key,
            "height": 0,
            "width": 0,
            "filename": filename,
            "prev": "",
            "next": "",
        }
        self.rows["sample_data"].append(row)
        return row

    def camera_data(self, out: Path, scene: Scene, sample_token: str, frame: SimFrame, channel: str, sensor_tokens: dict,
                    config: SynthConfig) -> None:
        """The key frame's image of ``channel`` (samples/), its mask and its sample_data row."""
        t_cam = frame.camera_times_s[channel]  # the camera's exposure: when the LiDAR crossed its axis
        path = self._camera_file(out, scene, sample_token, channel, t_cam, frame.renders[channel].image, True, sensor_tokens, config)
        self.write_mask(path, scene, frame.renders[channel].object_id, frame.annotated)

    def camera_sweep_data(self, out: Path, scene: Scene, sample_token: str, channel: str, t_cam: float, image: np.ndarray,
                          sensor_tokens: dict, config: SynthConfig) -> None:
        """An image of ``channel`` between key frames (sweeps/, as nuScenes files its 12 Hz camera frames; no mask:
        nothing annotates it) and its sample_data row, filed under the next key frame's ``sample_token``."""
        self._camera_file(out, scene, sample_token, channel, t_cam, image, False, sensor_tokens, config)

    def _camera_file(self, out: Path, scene: Scene, sample_token: str, channel: str, t_cam: float, image: np.ndarray, key: bool,
                     sensor_tokens: dict, config: SynthConfig) -> Path:
        ts = scene.timestamp_us(t_cam)
        filename = f"{'samples' if key else 'sweeps'}/{channel}/{scene.name}__{channel}__{ts}.jpg"
        path = out / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, config.jpeg_quality])
        if not ok:
            raise RuntimeError(f"JPEG encoding failed for {filename}")
        path.write_bytes(buf.tobytes())
        prev = self._last_camera_row.get(channel)  # the camera's previous frame in this scene, key frame or not
        row = {
            "token": self.tok("sample_data", scene.name, channel, ts),
            "sample_token": sample_token,
            "ego_pose_token": self.ego_pose(scene, t_cam, f"{channel}/{ts}"),
            "calibrated_sensor_token": sensor_tokens[channel],
            "timestamp": ts,
            "fileformat": "jpg",
            "is_key_frame": key,
            "height": int(image.shape[0]),
            "width": int(image.shape[1]),
            "filename": filename,
            "prev": prev["token"] if prev else "",
            "next": "",
        }
        if prev:
            prev["next"] = row["token"]
        self.rows["sample_data"].append(row)
        self._last_camera_row[channel] = row
        return path

    def write_mask(self, image_path: Path, scene: Scene, object_id: np.ndarray, frame_annotated: np.ndarray) -> Path:
        """``<image>.mask.npz`` beside the image (``data/synth_masks.py``): class and instance of the annotated object at
        every pixel.

        Annotated means annotated in this key frame (``frame_annotated``, the indices ``annotations`` writes boxes
        for): an object of an annotated kind beyond ``annotation_range_m`` has no box here and is none (255), as a
        look-alike is; so every token is in the scene's ``instance`` table and every masked object has a box in this
        sample."""
        kinds = scene.objects.kind
        boxed = np.zeros(len(kinds), dtype=bool)
        boxed[np.asarray(frame_annotated, dtype=np.int64)] = True
        annotated = (object_id >= 0) & boxed[np.maximum(object_id, 0)]
        class_id = np.full(object_id.shape, MASK_NONE, dtype=np.uint8)
        class_id[annotated] = CLASS_OF_KIND[kinds[object_id[annotated]]]
        instance = np.where(annotated, object_id + 1, 0).astype(np.uint16)
        ids = np.unique(instance[instance > 0])
        tokens = np.array([self.tok("instance", scene.name, int(i) - 1) for i in ids], dtype=np.str_)
        return write_mask(mask_path(image_path), class_id, instance, ids, tokens)

    def annotations(self, scene: Scene, sample_token: str, frame: SimFrame) -> None:
        objs = scene.objects
        boxes = objs.boxes_at(frame.t_s)
        for i, k in enumerate(frame.annotated):
            k = int(k)
            inst = self._instances.setdefault(k, [])
            vis = frame.visibility[i]
            vis_token = next(t for t, _, hi in VISIBILITY_LEVELS if (0.0 if np.isnan(vis) else vis) < hi)
            attribute = attribute_of(int(objs.kind[k]), float(np.linalg.norm(objs.velocity[k])), bool(objs.flag[k]),
                                     bool(objs.parked[k]))
            row = {
                "token": self.tok("sample_annotation", scene.name, frame.index, k),
                "sample_token": sample_token,
                "instance_token": self.tok("instance", scene.name, k),
                "visibility_token": vis_token,
                "attribute_tokens": [self.attribute_token[attribute]] if attribute else [],
                "translation": boxes[k, :3].tolist(),
                "size": boxes[k, 3:6].tolist(),
                "rotation": yaw_to_quaternion(boxes[k, 6]).tolist(),
                "prev": "",
                "next": "",
                "num_lidar_pts": int(frame.num_lidar_pts[i]),
                "num_radar_pts": 0,
            }
            self.rows["sample_annotation"].append(row)
            inst.append(row)

    def scene_end(self, scene: Scene, log_token: str) -> None:
        link_records(self._scene_samples)
        self.rows["scene"].append(
            {
                "token": self.tok("scene", scene.name),
                "log_token": log_token,
                "nbr_samples": len(self._scene_samples),
                "first_sample_token": self._scene_samples[0]["token"],
                "last_sample_token": self._scene_samples[-1]["token"],
                "name": scene.name,
                "description": f"synthetic street, ego at {scene.ego_speed_mps:.1f} m/s, {int(scene.objects.annotated.sum())} road users",
            }
        )
        for k, anns in sorted(self._instances.items()):
            link_records(anns)
            self.rows["instance"].append(
                {
                    "token": self.tok("instance", scene.name, k),
                    "category_token": self.category_token[int(scene.objects.kind[k])],
                    "nbr_annotations": len(anns),
                    "first_annotation_token": anns[0]["token"],
                    "last_annotation_token": anns[-1]["token"],
                }
            )


def write_tables(table_dir: Path, root: Path, rows: dict[str, list[dict]], seed: int) -> None:
    map_file = "maps/synthetic-street.png"
    (root / "maps").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / map_file), np.zeros((8, 8), dtype=np.uint8))
    # The devkit reads map[0]["log_tokens"] at load time, so one map record covers every log.
    rows["map"] = [
        {"category": "semantic_prior", "token": token("streamdet-synth", seed, "map", "synthetic-street"), "filename": map_file,
         "log_tokens": [r["token"] for r in rows["log"]]}
    ]
    table_dir.mkdir(parents=True, exist_ok=True)
    for name in Tables.NAMES:
        (table_dir / f"{name}.json").write_text(json.dumps(rows[name], indent=0))


def attribute_indices(kind, speed_mps, flag, parked) -> np.ndarray:
    """Each object's nuScenes attribute as an index into ATTRIBUTE_NAMES (0: none), arrays broadcast: a vehicle moves
    above 0.3 m/s, else it is parked if the layout parked it (``parked``: ``Objects.parked``) and stopped otherwise
    (waiting in a lane of either street, at a bus stop); a cycle has a rider or not (``flag``); a pedestrian moves
    above 0.2 m/s or stands. The annotations (``Tables.annotations``) and the trajectories sidecar
    (``synth_trajectories``) both take it from here.

    Parked is what the layout decided, not where the object stands: a rule on the distance to the main road called
    cars waiting in a cross-street lane and buses at a stop parked."""
    kind, speed, flag, parked = np.broadcast_arrays(np.asarray(kind, np.int64), np.asarray(speed_mps, np.float64),
                                                    np.asarray(flag, bool), np.asarray(parked))  # fmt: skip
    if parked.dtype != bool:  # a distance passed where the flag belongs (the old signature) would read as True
        raise TypeError(f"attribute_indices: parked must be booleans (Objects.parked), got {parked.dtype}")
    index = ATTRIBUTE_NAMES.index
    vehicle = np.isin(kind, [int(Kind.CAR), int(Kind.TRUCK), int(Kind.BUS)])
    cycle = np.isin(kind, [int(Kind.BICYCLE), int(Kind.MOTORCYCLE)])
    walker = kind == int(Kind.PEDESTRIAN)
    choices = [
        (vehicle & (speed > 0.3), "vehicle.moving"), (vehicle & ~(speed > 0.3) & parked, "vehicle.parked"),
        (vehicle & ~(speed > 0.3) & ~parked, "vehicle.stopped"), (cycle & flag, "cycle.with_rider"),
        (cycle & ~flag, "cycle.without_rider"), (walker & (speed > 0.2), "pedestrian.moving"),
        (walker & ~(speed > 0.2), "pedestrian.standing"),
    ]  # fmt: skip
    return np.select([c for c, _ in choices], [index(name) for _, name in choices], default=0).astype(np.uint8)


def attribute_of(kind: int, speed: float, flag: bool, parked: bool) -> str:
    """One object's attribute name ("" for none): ``attribute_indices`` of one object."""
    return ATTRIBUTE_NAMES[int(attribute_indices(kind, speed, flag, bool(parked)))]
