"""A reader of the official nuScenes JSON tables and file layout, without the nuscenes-devkit package.

``DATAROOT/<version>/*.json`` holds the tables (v1.0-mini, v1.0-trainval, or the synthetic v1.0-synth written
by ``streamdet-synth``); ``DATAROOT/samples/...`` and ``DATAROOT/sweeps/...`` the files, named by
``sample_data.filename``. The geometry follows the devkit:

- boxes go global -> ego (at the LiDAR timestamp) -> LiDAR, quaternions composed the same way; yaw is the
  rotation about z of the box in the LiDAR frame, ``atan2(R[1, 0], R[0, 0])`` (pyquaternion's yaw);
- velocity is ``NuScenes.box_velocity`` (centred difference of the neighbouring annotations' global centres,
  one-sided at a track's ends, NaN for a lone annotation or a gap over 1.5 s, 3 s when centred), rotated into
  the LiDAR frame with its z set to 0 first as mmdetection3d does; NaN becomes 0 with ``velocity_valid`` False;
- the annotations as the devkit scores them (global box, ``box_velocity``) ride along in
  ``Sample.extras[GLOBAL_ANNOTATIONS]``, for the evaluation;
- ``Sample.point_time_s`` comes from the optional ``<file>.time`` beside a LiDAR file (synthetic data), else None;
- past sweeps follow the LiDAR ``sample_data.prev`` chain and are moved into the key frame's LiDAR frame via the
  global frame, with their time lag (key frame minus sweep timestamp), as nuScenes multi-sweep detectors do. Each
  link must name a ``LIDAR_TOP`` row older than the one before and not yet on the chain (ValueError otherwise).

The tables are input, not trusted: a malformed row is a ValueError naming the table, its file, the row number,
its token and the field (``_TABLE_FIELDS`` says what each field must hold), never a TypeError / OverflowError /
bare KeyError. Every row must be an object with a unique string token (checked at load, with the fields the
indexes use); the other fields of a row are checked the first time ``get`` uses it, so opening trainval's
millions of rows costs no second pass, and a row is checked once per reader. Files named by
``sample_data.filename`` must be a relative path inside the dataset root, without ``..`` (``sample.dataset_file``;
symlinks the dataset holds are followed: set-ups link ``samples/`` and ``sweeps/`` to other disks).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from streamdet.calibration.camera import (
    QUATERNION_NORM_TOL, CalibrationError, Rig, invert_transform, make_transform, quaternion_to_matrix)
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.file_input import missing_reason
from streamdet.core.json_input import read_json, short_repr
from streamdet.core.rotations import matrix_to_yaw
from streamdet.core.table_version import table_version_problem
from streamdet.data.sample import (
    COUNT, FLAG, NAME, TEXT, TEXTS, FieldKind, Sample, Sweep, check_fields, dataset_file, load_point_times,
    load_points, numbers)

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
# Sample.extras key: every annotation of the sample as the table holds it (global frame, rows of gt_boxes):
# {"translation": (M, 3), "size": (M, 3) w l h, "rotation": (M, 4) w x y z, "velocity": (M, 3) box_velocity, NaN where
# unknown}. The devkit scores these; the LiDAR-frame gt_boxes keep the yaw only and the velocity's LiDAR xy, which
# do not map back to them exactly (the LiDAR is tilted from the ground), so the evaluation reads them from here.
GLOBAL_ANNOTATIONS = "global_annotations"
MAX_TABLE_BYTES = 16 << 30  # trainval's largest table (sample_data) is about 1 GiB: a bound, not a limit in use


def _is_unit_quaternion(v: object) -> bool:
    return numbers(4).test(v) and abs(sum(x * x for x in v) ** 0.5 - 1.0) <= QUATERNION_NORM_TOL  # type: ignore[union-attr]


def _is_intrinsic(v: object) -> bool:
    return v == [] or (type(v) is list and len(v) == 3 and all(numbers(3).test(r) for r in v))


QUATERNION = FieldKind(_is_unit_quaternion, f"a unit quaternion (4 finite numbers w, x, y, z; norm within {QUATERNION_NORM_TOL})")
INTRINSIC = FieldKind(_is_intrinsic, "a 3x3 matrix of finite numbers, or [] (non-camera sensors)")
LINK = TEXT  # prev / next: "" at the end of a chain, else a token of the same table
# The fields the reader uses, per table: what each must hold. Tokens naming rows of other tables are non-empty
# strings here; that they name a row is checked where they are followed (``_ref``).
_TABLE_FIELDS: dict[str, dict[str, FieldKind]] = {
    "category": {"token": NAME, "name": NAME},
    "attribute": {"token": NAME, "name": NAME},
    "instance": {"token": NAME, "category_token": NAME},
    "sensor": {"token": NAME, "channel": NAME},
    "calibrated_sensor": {"token": NAME, "sensor_token": NAME, "translation": numbers(3), "rotation": QUATERNION,
                          "camera_intrinsic": INTRINSIC},
    "ego_pose": {"token": NAME, "translation": numbers(3), "rotation": QUATERNION},
    "scene": {"token": NAME, "name": TEXT},
    "sample": {"token": NAME, "timestamp": COUNT, "scene_token": NAME},
    "sample_data": {"token": NAME, "sample_token": NAME, "ego_pose_token": NAME, "calibrated_sensor_token": NAME,
                    "timestamp": COUNT, "is_key_frame": FLAG, "filename": NAME, "prev": LINK, "width": COUNT,
                    "height": COUNT},
    "sample_annotation": {"token": NAME, "sample_token": NAME, "instance_token": NAME, "translation": numbers(3),
                          "size": numbers(3, positive=True), "rotation": QUATERNION, "prev": LINK, "next": LINK,
                          "attribute_tokens": TEXTS, "num_lidar_pts": COUNT, "num_radar_pts": COUNT},
}  # fmt: skip
# Fields a row may lack: the devkit's defaults apply (no intrinsics for a LiDAR, no attribute, 0 points).
_OPTIONAL_FIELDS: dict[str, frozenset[str]] = {
    "calibrated_sensor": frozenset({"camera_intrinsic"}),
    "sample_annotation": frozenset({"attribute_tokens", "num_lidar_pts", "num_radar_pts"}),
}


class NuScenesReader:
    """Samples (key frames) of a nuScenes-format dataset, in the order of the ``sample`` table."""

    def __init__(self, root: str | Path, version: str = "v1.0-mini") -> None:
        problem = table_version_problem(version)
        if problem is not None:  # a path would read tables from outside the dataset (core/table_version.py)
            raise ValueError(f"version {problem}")
        self.root = Path(root)
        self.version = version
        table_dir = self.root / version
        if not table_dir.is_dir():
            raise FileNotFoundError(f"nuScenes table folder not found: {table_dir} (version {version!r} under {self.root})")
        self._table_dir = table_dir
        self._tables = {name: _load_table(table_dir, name) for name in REQUIRED_TABLES}
        self._checked: set[int] = set()  # id() of the rows whose fields are checked (rows live as long as the reader)
        self._by_token = {name: self._index(name) for name in REQUIRED_TABLES}
        self._samples = self._tables["sample"]
        channel_of_cs = {
            cs["token"]: self._ref("calibrated_sensor", self._row("calibrated_sensor", cs), "sensor_token", "sensor")["channel"]
            for cs in self._tables["calibrated_sensor"]
        }  # a small table: every row checked now
        self._key_data: dict[str, dict[str, str]] = {s["token"]: {} for s in self._samples}
        # The big tables (millions of rows in trainval): only the fields these indexes read, trusted on the fast path;
        # a row that breaks it (missing field, wrong type, dangling token) is found and named by _bad_row.
        for i, sd in enumerate(self._tables["sample_data"]):
            try:
                channel = channel_of_cs[sd["calibrated_sensor_token"]]
                if sd["is_key_frame"] is True:
                    self._key_data[sd["sample_token"]][channel] = sd["token"]
                elif sd["is_key_frame"] is not False:
                    raise TypeError("is_key_frame")
            except (KeyError, TypeError):
                raise self._bad_row("sample_data", i, {"calibrated_sensor_token": "calibrated_sensor", "is_key_frame": None,
                                                       "sample_token": "sample"}) from None  # fmt: skip
        self._anns: dict[str, list[str]] = {s["token"]: [] for s in self._samples}
        for i, ann in enumerate(self._tables["sample_annotation"]):
            try:
                self._anns[ann["sample_token"]].append(ann["token"])
            except (KeyError, TypeError):
                raise self._bad_row("sample_annotation", i, {"sample_token": "sample"}) from None
        self._category_of_instance = {
            inst["token"]: self._ref("instance", self._row("instance", inst), "category_token", "category")["name"]
            for inst in self._tables["instance"]
        }

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def sample_tokens(self) -> list[str]:
        return [s["token"] for s in self._samples]

    def scene_name(self, sample_token: str) -> str:
        return self._ref("sample", self._get("sample", sample_token), "scene_token", "scene")["name"]

    # ---- the checked tables, for readers of other views of the dataset (replay/nuscenes_source.py) ----------------
    def rows(self, table: str) -> list[dict]:
        """The rows of ``table`` as stored, unchecked but for their tokens: pass a row to ``row`` before reading it."""
        return self._tables[table]

    def row(self, table: str, row: dict) -> dict:
        """``row`` of ``table`` with every field a reader uses checked (ValueError naming table, row and field)."""
        return self._row(table, row)

    def by_token(self, table: str, token: str) -> dict:
        """The checked row of ``table`` with ``token``; KeyError when there is none."""
        return self._get(table, token)

    def ref(self, table: str, row: dict, field: str, target: str) -> dict:
        """The checked row of ``target`` that the checked ``row`` of ``table`` names in ``field``."""
        return self._ref(table, row, field, target)

    def channel(self, sample_data: dict) -> str:
        """The sensor channel (``LIDAR_TOP``, ``CAM_FRONT``, ...) of a checked sample_data row."""
        cs = self._ref("sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor")
        return self._ref("calibrated_sensor", cs, "sensor_token", "sensor")["channel"]

    def file(self, sample_data: dict) -> Path:
        """The file of a checked sample_data row: a relative path inside the dataset root (``sample.dataset_file``)."""
        return self._file(sample_data)

    def get(self, token_or_index: str | int, num_past_sweeps: int = 0) -> Sample:
        """The sample with its LiDAR sweep, up to ``num_past_sweeps`` earlier sweeps, images, rig and boxes."""
        if isinstance(token_or_index, (int, np.integer)) and not isinstance(token_or_index, bool):
            if not -len(self) <= token_or_index < len(self):
                raise IndexError(f"sample index {token_or_index} out of range for {len(self)} samples")
            record = self._row("sample", self._samples[token_or_index])
        else:
            record = self._get("sample", token_or_index)
        if not isinstance(num_past_sweeps, (int, np.integer)) or num_past_sweeps < 0:
            raise ValueError(f"num_past_sweeps must be a non-negative integer, got {num_past_sweeps!r}")
        data = self._key_data[record["token"]]
        if LIDAR_CHANNEL not in data:
            raise ValueError(f"{self.row_name('sample', record)}: no key-frame {LIDAR_CHANNEL} sample_data names this sample")
        lidar_sd = self._row("sample_data", self._by_token["sample_data"][data[LIDAR_CHANNEL]])
        lidar_cs = self._ref("sample_data", lidar_sd, "calibrated_sensor_token", "calibrated_sensor")
        lidar_pose = self._ref("sample_data", lidar_sd, "ego_pose_token", "ego_pose")
        cams = []
        image_paths = {}
        for channel in [c for c in CAMERA_CHANNELS if c in data] + sorted(
            c for c in data if c.startswith("CAM_") and c not in CAMERA_CHANNELS
        ):
            sd = self._row("sample_data", self._by_token["sample_data"][data[channel]])
            cams.append(
                {
                    "name": channel,
                    "calibrated_sensor": self._ref("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor"),
                    "ego_pose": self._ref("sample_data", sd, "ego_pose_token", "ego_pose"),
                    "width": sd["width"],
                    "height": sd["height"],
                    "timestamp_us": sd["timestamp"],
                }
            )
            image_paths[channel] = self._file(sd)
        if not cams:
            raise ValueError(f"{self.row_name('sample', record)}: no key-frame camera sample_data names this sample")
        try:
            rig = Rig.from_nuscenes_records(lidar_cs, lidar_pose, cams)
        except CalibrationError as e:  # the fields are well-formed but do not make a rig (a zero image size, say)
            raise ValueError(f"{self.row_name('sample', record)}: its sensors do not form a camera rig: {e}") from None
        lidar2global = rig.ego2global @ rig.lidar2ego
        boxes = self._boxes(record["token"], rig)
        lidar_path = self._file(lidar_sd)
        points = load_points(lidar_path)
        return Sample(
            token=record["token"],
            timestamp_us=lidar_sd["timestamp"],
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
        """The row of ``table`` a caller asks for by token: KeyError when there is none (a lookup, not a defect)."""
        row = self._by_token[table].get(token)
        if row is None:
            raise KeyError(f"token {token!r} not found in table {table!r} of {self.root / self.version}")
        return self._row(table, row)

    def _row(self, table: str, row: dict) -> dict:
        """``row`` of ``table`` with every field the reader uses checked (once per row)."""
        if id(row) not in self._checked:
            check_fields(row, _TABLE_FIELDS[table], lambda: self.row_name(table, row), _OPTIONAL_FIELDS.get(table, frozenset()))
            self._checked.add(id(row))
        return row

    def _ref(self, table: str, row: dict, field: str, target: str) -> dict:
        """The row of ``target`` that the checked ``row`` of ``table`` names in ``field``, checked in turn."""
        found = self._by_token[target].get(row[field])
        if found is None:
            raise ValueError(f"{self.row_name(table, row)}: field {field!r} names {short_repr(row[field])}, "
                             f"which is no token of table {target!r}")  # fmt: skip
        return self._row(target, found)

    def row_name(self, table: str, row: object, index: int | None = None) -> str:
        """'nuScenes table 'T' (path) row N (token '...')' for an error message; finds N when not given (only
        errors pay for the search)."""
        if index is None:
            index = next((i for i, r in enumerate(self._tables[table]) if r is row), -1)
        token = row.get("token") if type(row) is dict else None
        named = f" (token {short_repr(token)})" if type(token) is str else ""
        return f"nuScenes table {table!r} ({self._table_dir / table}.json) row {index}{named}"

    def _bad_row(self, table: str, index: int, refs: dict[str, str | None]) -> ValueError:
        """Why row ``index`` of ``table`` broke an index: a field of ``refs`` missing or of the wrong kind, or a
        token naming no row of the table ``refs[field]``. Only called after the fast path failed on that row."""
        row = self._tables[table][index]
        where = self.row_name(table, row, index)
        check_fields(row, {"token": NAME} | {f: _TABLE_FIELDS[table][f] for f in refs}, where)
        for field, target in refs.items():
            if target is not None and row[field] not in self._by_token[target]:
                return ValueError(f"{where}: field {field!r} names {short_repr(row[field])}, which is no token of table {target!r}")
        return ValueError(f"{where}: malformed row {short_repr(row)}")

    def _index(self, table: str) -> dict[str, dict]:
        """Rows of ``table`` by token: every row an object with a unique, non-empty string token."""
        rows = self._tables[table]
        try:
            index = {r["token"]: r for r in rows}  # fast: a non-object row, a missing or unhashable token raise
        except (KeyError, TypeError):
            index = {}
        if len(index) == len(rows) and "" not in index and set(map(type, index)) <= {str}:
            return index
        first: dict[object, int] = {}
        for i, row in enumerate(rows):  # slow, naming the first bad row
            check_fields(row, {"token": NAME}, lambda: self.row_name(table, row, i))
            if row["token"] in first:
                raise ValueError(f"{self.row_name(table, row, i)}: the token is also that of row {first[row['token']]}: "
                                 "tokens must be unique")  # fmt: skip
            first[row["token"]] = i
        raise AssertionError(f"table {table!r}: index check failed but no row is bad")  # unreachable

    def _file(self, sd: dict) -> Path:
        """The file of a checked sample_data row, a relative path inside the dataset root (``sample.dataset_file``)."""
        path = dataset_file(self.root, sd["filename"], lambda: f"{self.row_name('sample_data', sd)}: field 'filename'")
        if not path.is_file():
            if path.exists():  # a FIFO, a device or a folder: never opened
                raise ValueError(f"file of sample_data {sd['token']} is not a regular file (a FIFO, a device or a folder?): {path}")
            link = _dead_link(self.root, path)
            if link == path:  # "not found" would send the user looking for a file whose link they can see
                raise FileNotFoundError(f"file of sample_data {sd['token']} is {missing_reason(link)}: {path}")
            if link is not None:
                raise FileNotFoundError(f"file of sample_data {sd['token']} cannot be reached: {link} is "
                                        f"{missing_reason(link)}: {path}")  # fmt: skip
            raise FileNotFoundError(f"file of sample_data {sd['token']} not found: {path}")
        return path

    def _boxes(self, sample_token: str, rig: Rig) -> dict:
        anns = [self._row("sample_annotation", self._by_token["sample_annotation"][t]) for t in self._anns[sample_token]]
        m = len(anns)
        global2lidar = invert_transform(rig.ego2global @ rig.lidar2ego)
        boxes = np.zeros((m, BOX_DIM), dtype=np.float64)
        labels = np.full(m, -1, dtype=np.int64)
        names = []
        attributes = []
        velocity = np.zeros((m, 3))
        global_boxes = np.zeros((m, 10))  # translation, size, rotation as annotated
        for i, ann in enumerate(anns):
            global_boxes[i] = [*ann["translation"], *ann["size"], *ann["rotation"]]
            box2global = make_transform(quaternion_to_matrix(ann["rotation"]), ann["translation"])
            box2lidar = global2lidar @ box2global
            boxes[i, 0:3] = box2lidar[:3, 3]
            boxes[i, 3:6] = ann["size"]  # w, l, h
            boxes[i, 6] = matrix_to_yaw(box2lidar[:3, :3])
            velocity[i] = self._box_velocity(ann)
            category = self._category_of_instance.get(ann["instance_token"])
            if category is None:
                self._ref("sample_annotation", ann, "instance_token", "instance")  # raises: names the dangling token
            cls = CATEGORY_TO_CLASS.get(category)
            if cls is not None:
                labels[i] = CLASS_NAMES.index(cls)
            names.append(cls if cls is not None else category)
            attributes.append(self.attribute_name(ann))
        valid = np.all(np.isfinite(velocity[:, :2]), axis=1)
        annotated = {"translation": global_boxes[:, 0:3], "size": global_boxes[:, 3:6], "rotation": global_boxes[:, 6:10],
                     "velocity": velocity.copy()}  # fmt: skip
        velocity[:, 2] = 0.0  # mmdetection3d keeps the ground-plane velocity only
        velocity[~valid] = 0.0
        boxes[:, 7:9] = (velocity @ global2lidar[:3, :3].T)[:, :2]
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
            "extras": {GLOBAL_ANNOTATIONS: annotated},
        }

    def attribute_name(self, ann: dict) -> str:
        """The attribute name of a checked annotation: its single attribute's, else "" (none, or several)."""
        tokens = ann.get("attribute_tokens", [])
        if len(tokens) != 1:
            return ""
        row = self._by_token["attribute"].get(tokens[0])
        if row is None:
            raise ValueError(f"{self.row_name('sample_annotation', ann)}: field 'attribute_tokens' names {tokens[0]!r}, "
                             "which is no token of table 'attribute'")  # fmt: skip
        return self._row("attribute", row)["name"]

    def _box_velocity(self, ann: dict) -> np.ndarray:
        """Global (3,) velocity exactly as the devkit's ``NuScenes.box_velocity``."""
        has_prev, has_next = ann["prev"] != "", ann["next"] != ""
        if not has_prev and not has_next:
            return np.full(3, np.nan)
        first = self._ref("sample_annotation", ann, "prev", "sample_annotation") if has_prev else ann
        last = self._ref("sample_annotation", ann, "next", "sample_annotation") if has_next else ann
        # Each timestamp in seconds first, then the difference, as the devkit: 1e-6 * (t_last - t_first) rounds
        # otherwise (to the float64 step of a timestamp in seconds), which moves the velocity in its 8th digit.
        time_diff = (1e-6 * self._ref("sample_annotation", last, "sample_token", "sample")["timestamp"]
                     - 1e-6 * self._ref("sample_annotation", first, "sample_token", "sample")["timestamp"])  # fmt: skip
        max_diff = MAX_VELOCITY_TIME_DIFF_S * (2 if has_prev and has_next else 1)
        if time_diff > max_diff or time_diff <= 0:
            return np.full(3, np.nan)
        return (np.asarray(last["translation"], dtype=np.float64) - np.asarray(first["translation"], dtype=np.float64)) / time_diff

    def _past_sweeps(self, lidar_sd: dict, lidar2global: np.ndarray, count: int) -> tuple[Sweep, ...]:
        sweeps = []
        global2lidar = invert_transform(lidar2global)
        sd = lidar_sd
        on_chain = {lidar_sd["token"]}
        while len(sweeps) < count and sd["prev"] != "":
            after, sd = sd, self._ref("sample_data", sd, "prev", "sample_data")
            self._check_past_sweep(after, sd, lidar_sd, on_chain)
            on_chain.add(sd["token"])
            cs = self._ref("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
            pose = self._ref("sample_data", sd, "ego_pose_token", "ego_pose")
            sweep2global = _record_to_matrix(pose) @ _record_to_matrix(cs)
            sweep2key = global2lidar @ sweep2global
            points = load_points(self._file(sd)).copy()
            points[:, :3] = points[:, :3] @ sweep2key[:3, :3].T.astype(np.float32) + sweep2key[:3, 3].astype(np.float32)
            sweeps.append(
                Sweep(
                    token=sd["token"],
                    timestamp_us=sd["timestamp"],
                    time_lag_s=1e-6 * (lidar_sd["timestamp"] - sd["timestamp"]),
                    points=points,
                )
            )
        return tuple(sweeps)

    def _check_past_sweep(self, after: dict, sd: dict, lidar_sd: dict, on_chain: set[str]) -> None:
        """``sd``, which the 'prev' of ``after`` names, as a past sweep of ``lidar_sd``: a loop would hand the key frame
        back as its own past sweep (lag 0), another channel's file would be read as points (a JPEG whose size is a
        multiple of 20 bytes reads as garbage coordinates), and a sweep not older than the next a lag <= 0."""
        if sd["token"] in on_chain:
            raise ValueError(f"{self.row_name('sample_data', after)}: field 'prev' names {short_repr(after['prev'])}, a "
                             f"sweep already on the {LIDAR_CHANNEL} 'prev' chain of key frame {short_repr(lidar_sd['token'])}: "
                             "the chain loops")  # fmt: skip
        channel = self.channel(sd)
        if channel != LIDAR_CHANNEL:
            raise ValueError(f"{self.row_name('sample_data', after)}: field 'prev' names {short_repr(after['prev'])}, a "
                             f"{channel} sample_data, not a {LIDAR_CHANNEL} sweep")  # fmt: skip
        if not sd["timestamp"] < after["timestamp"]:
            raise ValueError(f"{self.row_name('sample_data', sd)}: field 'timestamp' is {sd['timestamp']}, not before the "
                             f"{after['timestamp']} of the {LIDAR_CHANNEL} sweep whose 'prev' names it "
                             f"({short_repr(after['token'])}): a past sweep must be older")  # fmt: skip


def _dead_link(root: Path, path: Path) -> Path | None:
    """The first symlink from ``root`` down to ``path`` (its folders, then the file) that leads nowhere: a loop, or a
    link to what is not there (``samples/`` linked to a disk that is not mounted); None where there is none."""
    at = root
    for part in path.relative_to(root).parts:
        at = at / part
        if not at.exists():
            return at if os.path.islink(at) else None
    return None


def _record_to_matrix(record: dict) -> np.ndarray:
    return make_transform(quaternion_to_matrix(record["rotation"]), record["translation"])


def _load_table(table_dir: Path, name: str) -> list:
    """The rows of ``table_dir/name.json`` (a JSON list; the rows are checked by the reader)."""
    path = table_dir / f"{name}.json"
    if not path.is_file():
        if path.exists():  # a FIFO, a device or a folder: never opened
            raise ValueError(f"nuScenes table {name!r} is not a regular file (a FIFO, a device or a folder?): {path}")
        raise FileNotFoundError(f"nuScenes table {name!r} not found: {path}")
    rows = read_json(path, "nuScenes table", MAX_TABLE_BYTES)
    if not isinstance(rows, list):
        raise ValueError(f"nuScenes table {name!r} ({path}) must be a JSON list of records, got {type(rows).__name__}")
    return rows
