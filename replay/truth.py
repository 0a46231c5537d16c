"""Ground truth at any moment of a drive, for scoring a detection at the time it is emitted.

Two sources, the better one when the dataset has it:

- **trajectories**: the synthetic world's ``trajectories.npz`` sidecar (``streamdet.data.synth_trajectories``),
  every object's box sampled at 100 Hz by the generator: exact at any time;
- **key frames interpolated** (the ASAP benchmark's way, for real nuScenes): between two successive annotations of
  an object (key frames it misses in between included) it is placed by linear interpolation of its centre and of its
  yaw along the shorter arc, with the velocity of that interval; outside the key frames that annotate it, it does
  not exist. Before the scene's first annotated key frame and after its last, no object is known: such query times
  are not scored (``GroundTruth.covers``).

Which objects count at a query time (the devkit's ``num_pts > 0`` rule) is decided with the LiDAR sweep ending then:
the number of its points inside the box grown by ``POINT_MARGIN_M``. An object is *moving* when its speed exceeds
``MOVING_SPEED_MPS``.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.core.rotations import quaternion_to_yaw, yaw_to_quaternion
from streamdet.data.nuscenes import CATEGORY_TO_CLASS, NuScenesReader
from streamdet.data.synth_trajectories import Trajectories, load_trajectories
from streamdet.evaluation.detection_eval import points_in_boxes

POINT_MARGIN_M = 0.2  # the box is grown by this on each side when counting points (points fire up to a rotation earlier)
MOVING_SPEED_MPS = 0.5
TRAJECTORIES, INTERPOLATED = "trajectories", "key frames interpolated"


@dataclass(frozen=True, eq=False)
class TruthBoxes:
    """The ground-truth objects at one time, global frame."""

    boxes: np.ndarray  # (M, 9) x, y, z, w, l, h, yaw, vx, vy
    names: np.ndarray  # (M,) str detection class
    # (M,) str nuScenes attribute ("" = unknown: the synthetic trajectories carry none); None: all unknown
    attributes: np.ndarray | None = None

    @property
    def moving(self) -> np.ndarray:
        return np.hypot(self.boxes[:, 7], self.boxes[:, 8]) > MOVING_SPEED_MPS

    def attribute_names(self) -> np.ndarray:
        """(M,) str: each object's attribute, "" where unknown."""
        return self.attributes if self.attributes is not None else np.full(len(self.boxes), "", dtype=object)

    def select(self, mask: np.ndarray) -> "TruthBoxes":
        return TruthBoxes(self.boxes[mask], self.names[mask], None if self.attributes is None else self.attributes[mask])


class GroundTruth:
    """``at(t_us)``: the objects of one scene at a dataset time; ``source`` says how they were obtained."""

    def __init__(self, trajectories: Trajectories | None, tracks: dict[str, list[tuple[int, np.ndarray, str]]] | None) -> None:
        if (trajectories is None) == (tracks is None):
            raise ValueError("GroundTruth needs exactly one of trajectories and key-frame tracks")
        self._trajectories = trajectories
        self._tracks = tracks
        self.source = TRAJECTORIES if trajectories is not None else INTERPOLATED
        # interpolated: the times the key frames annotate, first to last (None: nothing annotated)
        stamps = [e[0] for track in (tracks or {}).values() for e in track]
        self._span_us = (min(stamps), max(stamps)) if stamps else None

    def covers(self, t_us: float) -> bool:
        """Whether the truth knows the world at ``t_us``: always with trajectories; with interpolated key frames only
        between the scene's first and last annotated key frame (before and after, every object would be missing
        and every detection scored as a false positive)."""
        if self._span_us is None:
            return True
        return self._span_us[0] - 1.0 <= t_us <= self._span_us[1] + 1.0

    def at(self, t_us: float) -> TruthBoxes:
        if self._trajectories is not None:
            boxes = self._trajectories.boxes_at(t_us)
            return TruthBoxes(boxes, self._trajectories.names, self._trajectories.attributes_at(t_us))
        rows, names, attributes = [], [], []
        for track in self._tracks.values():
            box = _interpolate(track, t_us)
            if box is not None:
                rows.append(box)
                names.append(track[0][2])
                attributes.append(_attribute_at(track, t_us))
        boxes = np.array(rows, dtype=np.float64).reshape(-1, 9)  # (M, 9), also when no object exists at t_us
        return TruthBoxes(boxes, np.array(names, dtype=np.str_), np.array(attributes, dtype=object))


def load_ground_truth(root: str | Path, version: str, scene_name: str, prefer_trajectories: bool = True,
                      reader: NuScenesReader | None = None) -> GroundTruth:  # fmt: skip
    """The scene's ground truth: its trajectories where the dataset has them, else its key frames interpolated
    (from ``reader``, the dataset's tables; None: read them here)."""
    if prefer_trajectories:
        trajectories = load_trajectories(root, scene_name)
        if trajectories is not None:
            return GroundTruth(trajectories, None)
    return GroundTruth(None, key_frame_tracks(reader or NuScenesReader(root, version), scene_name))


def key_frame_tracks(reader: NuScenesReader, scene_name: str) -> dict[str, list[tuple[int, np.ndarray, str, str]]]:
    """Per instance, its key-frame annotations in time order: (timestamp us, (9,) box with velocity 0, class,
    attribute name or "").
    The rows are the reader's, checked as it reads them (a malformed one is a ValueError naming it)."""
    scenes = [s for s in reader.rows("scene") if reader.row("scene", s)["name"] == scene_name]
    if not scenes:
        raise ValueError(f"scene {scene_name!r} is not in {reader.root / reader.version}")
    samples = (reader.row("sample", r) for r in reader.rows("sample"))
    stamp = {s["token"]: int(s["timestamp"]) for s in samples if s["scene_token"] == scenes[0]["token"]}
    tracks: dict[str, list[tuple[int, np.ndarray, str]]] = defaultdict(list)
    for ann in reader.rows("sample_annotation"):
        if ann["sample_token"] not in stamp:  # the reader checked every row's sample_token when it indexed them
            continue
        ann = reader.row("sample_annotation", ann)
        instance = reader.ref("sample_annotation", ann, "instance_token", "instance")
        cls = CATEGORY_TO_CLASS.get(reader.ref("instance", instance, "category_token", "category")["name"])
        if cls is None:
            continue
        yaw = float(quaternion_to_yaw(ann["rotation"]))
        box = np.array([*ann["translation"], *ann["size"], yaw, 0.0, 0.0], dtype=np.float64)
        tracks[ann["instance_token"]].append((stamp[ann["sample_token"]], box, cls, reader.attribute_name(ann)))
    return {k: sorted(v, key=lambda e: e[0]) for k, v in tracks.items()}


def _interpolate(track: list[tuple[int, np.ndarray, str]], t_us: float) -> np.ndarray | None:
    """The track's box at t_us between two of its key frames (None outside them); velocity of that interval."""
    times = [e[0] for e in track]
    if len(track) == 1:
        return track[0][1].copy() if abs(t_us - times[0]) < 1.0 else None
    if not times[0] <= t_us <= times[-1]:
        return None
    i = min(int(np.searchsorted(times, t_us, side="right")) - 1, len(track) - 2)
    (ta, a), (tb, b) = track[i][:2], track[i + 1][:2]
    w = (t_us - ta) / (tb - ta)
    out = a + w * (b - a)
    out[6] = a[6] + w * (np.mod(b[6] - a[6] + np.pi, 2 * np.pi) - np.pi)
    out[3:6] = a[3:6]
    out[7:9] = (b[:2] - a[:2]) / ((tb - ta) * 1e-6)
    return out


def _attribute_at(track: list[tuple], t_us: float) -> str:
    """The attribute of the track's annotation at or before ``t_us`` (its first one before its span): an attribute
    holds from the key frame that annotates it until the next. "" where the track carries none."""
    times = [e[0] for e in track]
    i = max(int(np.searchsorted(times, t_us, side="right")) - 1, 0)
    entry = track[i]
    return str(entry[3]) if len(entry) > 3 else ""


def count_points(truth: TruthBoxes, points_global: np.ndarray, max_range_m: float, ego_xy: np.ndarray) -> np.ndarray:
    """(M,) points of ``points_global`` (P, 3) inside each box grown by POINT_MARGIN_M (0 beyond ``max_range_m``)."""
    counts = np.zeros(len(truth.boxes), dtype=np.int64)
    near = np.flatnonzero(np.hypot(*(truth.boxes[:, :2] - ego_xy).T) < max_range_m)
    if near.size == 0 or len(points_global) == 0:
        return counts
    b = truth.boxes[near]
    # (B, 10) translation, size w l h, quaternion w x y z of the yaw
    rows = np.concatenate([b[:, 0:3], b[:, 3:6] + 2 * POINT_MARGIN_M, yaw_to_quaternion(b[:, 6])], axis=1)
    lo, hi = b[:, :2].min(axis=0) - 15.0, b[:, :2].max(axis=0) + 15.0  # no box is longer than 30 m
    pts = points_global[np.all((points_global[:, :2] >= lo) & (points_global[:, :2] <= hi), axis=1)]
    for start in range(0, len(pts), 8192):  # (P, B, 3) intermediates stay small
        counts[near] += points_in_boxes(pts[start : start + 8192], rows).sum(axis=0)
    return counts
