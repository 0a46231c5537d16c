"""A ROS 2 bag read back as the runtime's inputs: timed LiDAR slices and camera image sets, in recorded order.

``BagSource.events()`` walks every message of the bag in log-time order (so a caller can copy the input topics
through) and attaches to each LiDAR message a ``SweepEvent``: the cloud, its slices with their scan times, the
LiDAR pose, and the ``ImageSet`` to feed first (the newest image of every camera and the rig they were taken
with) when new images arrived since the previous cloud. That is all a player needs, so a replay tool can take
this source beside the nuScenes one; ``streamdet-bag run`` feeds it to ``StreamingDetector`` directly.

Reading uses mcap + mcap-ros2-support (the ``ros`` extra), decoding each message with the schema stored in the
bag, so bags recorded with any ROS 2 message package are read, and only the topics named in ``TopicMap`` are
interpreted.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from streamdet.bag import topics as T
from streamdet.bag.deps import require
from streamdet.calibration.camera import Rig, make_transform, quaternion_to_matrix
from streamdet.runtime_ort.ros.camera_info import IDENTITY_RECORD, rig_from_ros
from streamdet.runtime_ort.ros.header import header_stamp_ns
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb, image_to_rgb
from streamdet.runtime_ort.ros.pointcloud2 import (
    Cloud,
    CloudFields,
    TimedSlice,
    decode_pointcloud2,
    slice_from_message,
    split_cloud,
)
from streamdet.runtime_ort.ros.tf import TfBuffer

log = logging.getLogger(__name__)

DEFAULT_TF_TOLERANCE_NS = 50_000_000  # a pose lookup may take the nearest pose this far past the last one


@dataclass(frozen=True, eq=False)
class BagMessage:
    """One message as recorded."""

    topic: str
    datatype: str  # schema name, e.g. "sensor_msgs/msg/PointCloud2"
    schema_text: str  # the schema stored in the bag
    log_time_ns: int
    message: Any  # decoded (attributes named as the ROS fields)


@dataclass(frozen=True, eq=False)
class ImageSet:
    """The newest image of every camera seen so far, and the rig they were taken with."""

    images: dict[str, np.ndarray]  # camera -> (H, W, 3) uint8 RGB as recorded
    stamps_ns: dict[str, int]  # camera -> image stamp
    rig: Rig | None  # None: no CameraInfo / TF for the cameras yet (the export's own LUT stays in use)

    @property
    def stamp_ns(self) -> int:
        return max(self.stamps_ns.values())


@dataclass(frozen=True, eq=False)
class SweepEvent:
    """A LiDAR message turned into the runtime's slices."""

    cloud: Cloud
    slices: list[TimedSlice]  # scan order
    lidar2ego: np.ndarray  # (4, 4)
    ego2global: np.ndarray  # (4, 4) at the cloud's stamp; identity without a global frame
    sample_token: str | None  # from the bag's streamdet metadata (bags written by streamdet-bag export)
    image_set: ImageSet | None  # feed before the slices; None: no new image since the previous cloud


@dataclass(frozen=True)
class SourceConfig:
    topics: T.TopicMap = field(default_factory=T.TopicMap)
    camera_names: tuple[str, ...] = ()  # the cameras to read, in the rig's order (the export's)
    num_slices: int = 8
    start_deg: float = 0.0
    slice_per_message: bool = False  # the driver publishes slices: one message = one slice
    cloud_fields: CloudFields = field(default_factory=lambda: CloudFields(require_time=False))
    ego_frame: str = T.EGO_FRAME
    global_frame: str | None = T.GLOBAL_FRAME  # None: the stack has no localisation; ego motion is ignored
    tf_tolerance_ns: int = DEFAULT_TF_TOLERANCE_NS


class BagSource:
    """Iterates a ``.mcap`` ROS 2 bag (or a rosbag2 folder holding one)."""

    def __init__(self, path: str | Path, config: SourceConfig) -> None:
        self.path = _mcap_file(Path(path))
        self.config = config
        self._reader_mod = require("mcap.reader")
        self._decoder_mod = require("mcap_ros2.decoder")
        self._warned_missing: tuple[str, ...] = ()
        self.cameras_without_info: set[str] = set()  # cameras whose CameraInfo was missing when an image set was made

    def metadata(self) -> dict[str, dict[str, str]]:
        """The bag's MCAP metadata records by name."""
        with open(self.path, "rb") as f:
            return {m.name: dict(m.metadata) for m in self._reader_mod.make_reader(f).iter_metadata()}

    def topics(self) -> dict[str, str]:
        """topic -> message type of every channel in the bag."""
        with open(self.path, "rb") as f:
            summary = self._reader_mod.make_reader(f).get_summary()
        if summary is None:
            return {}
        return {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}

    def messages(self) -> Iterator[BagMessage]:
        """Every ROS 2 (CDR) message, decoded, in log-time order; channels in other encodings (a Foxglove protobuf
        or JSON topic) are skipped with a warning."""
        factory = self._decoder_mod.DecoderFactory()
        skipped: set[str] = set()
        with open(self.path, "rb") as f:
            reader = self._reader_mod.make_reader(f)
            for schema, channel, record in reader.iter_messages(log_time_order=True):
                decode = factory.decoder_for(channel.message_encoding, schema)
                if decode is None:
                    if channel.topic not in skipped:
                        log.warning("%s: topic %s is %s, not ROS 2 CDR: skipped", self.path, channel.topic,
                                    channel.message_encoding)  # fmt: skip
                        skipped.add(channel.topic)
                    continue
                yield BagMessage(channel.topic, schema.name, schema.data.decode(), int(record.log_time), decode(record.data))

    def events(self) -> Iterator[tuple[BagMessage, SweepEvent | None]]:
        """Every message with, for each LiDAR message, the sweep event it makes."""
        cfg = self.config
        topics = cfg.topics
        image_topics = {topics.image_topic(c): c for c in cfg.camera_names}
        info_topics = {topics.camera_info_topic(c): c for c in cfg.camera_names}
        tokens = json.loads(self.metadata().get(T.METADATA_NAME, {}).get("sample_tokens", "{}"))
        tf = TfBuffer(max_extrapolation_ns=cfg.tf_tolerance_ns)
        infos: dict[str, Any] = {}
        latest: dict[str, Any] = {}  # camera -> newest image message, decoded only when a set is made
        fresh = False
        saw_lidar = False
        for msg in self.messages():
            event = None
            if msg.topic == topics.tf_static:
                tf.add(msg.message, static=True)
            elif msg.topic == topics.tf:
                tf.add(msg.message)
            elif msg.topic in info_topics:
                infos[info_topics[msg.topic]] = msg.message
            elif msg.topic in image_topics:
                latest[image_topics[msg.topic]] = msg.message
                fresh = True
            elif msg.topic == topics.lidar:
                saw_lidar = True
                image_set = self._image_set(latest, infos, tf, msg.message) if fresh else None
                fresh = False
                event = self._sweep(msg.message, tf, tokens, image_set)
            yield msg, event
        if not saw_lidar:
            raise ValueError(f"{self.path} has no message on the LiDAR topic {topics.lidar!r}; its topics: {self.topics()}")

    def sweeps(self) -> Iterator[SweepEvent]:
        """The sweep events alone."""
        for _, event in self.events():
            if event is not None:
                yield event

    # ---- internals ------------------------------------------------------------------------------------
    def _sweep(self, message: Any, tf: TfBuffer, tokens: dict, image_set: ImageSet | None) -> SweepEvent:
        cfg = self.config
        cloud = decode_pointcloud2(message, cfg.cloud_fields)
        if cfg.slice_per_message:
            slices = [slice_from_message(cloud, cfg.num_slices, cfg.start_deg)]
        else:
            slices = split_cloud(cloud, cfg.num_slices, cfg.start_deg)
        lidar2ego = _matrix(self._lookup(tf, cfg.ego_frame, cloud.frame_id, cloud.stamp_ns))
        pose = self._lookup(tf, cfg.global_frame, cfg.ego_frame, cloud.stamp_ns) if cfg.global_frame else IDENTITY_RECORD
        return SweepEvent(cloud, slices, lidar2ego, _matrix(pose), tokens.get(str(cloud.stamp_ns)), image_set)

    def _lookup(self, tf: TfBuffer, parent: str, child: str, stamp: int) -> dict:
        if parent == child.lstrip("/"):
            return IDENTITY_RECORD
        try:
            return tf.lookup(parent, child, stamp)
        except (KeyError, ValueError) as e:
            raise ValueError(f"{self.path}: {e.args[0]}") from None

    def _image_set(self, latest: dict, infos: dict, tf: TfBuffer, lidar_message: Any) -> ImageSet:
        cfg = self.config
        names = [c for c in cfg.camera_names if c in latest]
        images = {c: _rgb(latest[c], c) for c in names}
        stamps = {c: header_stamp_ns(latest[c]) for c in names}
        rig = None
        missing = tuple(c for c in cfg.camera_names if c not in infos)
        if missing and missing != self._warned_missing:
            # a recording may start between a camera's images and its first CameraInfo, and a stack without
            # CameraInfo runs on the export's calibration: neither is an error, both are worth a line
            topics = [cfg.topics.camera_info_topic(c) for c in missing]
            log.warning("%s: no CameraInfo yet on %s: the calibration in use stays (the export's, at first)", self.path, topics)
            self._warned_missing = missing
        self.cameras_without_info.update(missing)
        if not missing:
            try:
                rig = rig_from_ros(infos, tf, str(lidar_message.header.frame_id), header_stamp_ns(lidar_message), stamps,
                                   cfg.ego_frame, cfg.global_frame, order=cfg.camera_names)  # fmt: skip
            except (KeyError, ValueError) as e:
                raise ValueError(f"{self.path}: cannot build the camera rig: {e.args[0]}") from None
        return ImageSet(images, stamps, rig)


def _rgb(message: Any, camera: str) -> np.ndarray:
    try:
        return compressed_image_to_rgb(message) if hasattr(message, "format") else image_to_rgb(message)
    except ValueError as e:
        raise ValueError(f"camera {camera}: {e}") from None


def _matrix(record: dict) -> np.ndarray:
    return make_transform(quaternion_to_matrix(record["rotation"]), record["translation"])


def _mcap_file(path: Path) -> Path:
    if path.is_dir():
        files = sorted(path.glob("*.mcap"))
        if len(files) != 1:
            raise ValueError(f"{path} is a folder holding {len(files)} .mcap files; name the bag file")
        return files[0]
    if not path.is_file():
        raise FileNotFoundError(f"bag not found: {path}")
    return path
