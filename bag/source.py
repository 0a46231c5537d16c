"""A ROS 2 bag read back as the runtime's inputs: timed LiDAR slices and camera image sets, in recorded order.

``BagSource.events()`` walks every message of the bag in log-time order (so a caller can copy the input topics
through) and attaches to each LiDAR message a ``SweepEvent``: the cloud, its slices with their scan times, the
LiDAR pose, and the ``ImageSet`` to feed first (the newest image of every camera and the rig they were taken
with) when new images arrived since the previous cloud. That is all a player needs, so a replay tool can take
this source beside the nuScenes one; ``streamdet-bag run`` feeds it to ``StreamingDetector`` directly.

Reading uses mcap + mcap-ros2-support (the ``ros`` extra), decoding each message with the schema stored in the
bag, so bags recorded with any ROS 2 message package are read, and only the topics named in ``TopicMap`` are
interpreted.

Every topic the ``TopicMap`` gives a role (the LiDAR, each camera's images and CameraInfo, /tf, /tf_static) must
carry that role's message type: another one (a topic mapped to the wrong role) is a ValueError naming the topic,
the type found and the one expected, before anything is read. A LiDAR message stamped at or before one already read
(republished, recorded twice, a clock step back) is skipped, counted and warned once: it is never detected as a new
sweep (``events()``).

A bag that cannot be read (truncated, or corrupted: a bad record length, a chunk that fails its CRC or does not
decompress, a message that does not decode with its schema) raises ``BagReadError``, a ValueError naming the bag,
whichever of the reading libraries noticed it. Chunk CRCs are checked, so flipped bytes are found rather than read.
"""

from __future__ import annotations

import importlib
import json
import logging
import struct
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from streamdet.bag import topics as T
from streamdet.bag.deps import require
from streamdet.calibration.camera import Rig, make_transform, quaternion_to_matrix
from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S, CameraTimeout, check_camera_timeout
from streamdet.core.scan_layout import ScanLayout, layout_from_times
from streamdet.core.sectors import azimuth_deg
from streamdet.runtime_ort.ros.camera_info import IDENTITY_RECORD, rig_from_ros
from streamdet.runtime_ort.ros.header import header_stamp_ns
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb, image_to_rgb
from streamdet.runtime_ort.ros.pointcloud2 import (
    Cloud,
    CloudClockError,
    CloudFields,
    TimedSlice,
    decode_pointcloud2,
    slice_from_message,
    split_cloud,
)
from streamdet.runtime_ort.ros.tf import TfBuffer

log = logging.getLogger(__name__)

DEFAULT_TF_TOLERANCE_NS = 50_000_000  # a pose lookup may take the nearest pose this far past the last one
# With slice_per_message, a message is taken as one slice only if one slice-wide arc holds most of its points
# (min_slice_share). A driver's slice puts nearly all its points in one such arc, whatever its phase against
# streamdet's sectors; a full sweep spreads them over the whole circle, about 1/n per arc, and taking it as one slice
# would let the slice graph see only that sector's quadrants: most of the sweep would be silently dropped.
ARC_BINS_PER_SLICE = 8  # azimuth resolution of that test: an eighth of a slice's width


class BagReadError(ValueError):
    """The bag is truncated or corrupted: the message names the bag and quotes the reading library."""


@dataclass(frozen=True, eq=False)
class BagMessage:
    """One message as recorded."""

    topic: str
    datatype: str  # schema name, e.g. "sensor_msgs/msg/PointCloud2"
    schema_text: str  # the schema stored in the bag
    log_time_ns: int
    message: Any  # decoded (attributes named as the ROS fields)
    channel_metadata: dict[str, str] = field(default_factory=dict)  # the recorded channel's (offered_qos_profiles, ...)


@dataclass(frozen=True, eq=False)
class ImageSet:
    """The newest image of every camera seen so far and not timed out (``SourceConfig.camera_timeout_s``), and the rig
    they were taken with. No image at all: every camera timed out, the image BEV is to be dropped."""

    images: dict[str, np.ndarray]  # camera -> (H, W, 3) uint8 RGB as recorded
    stamps_ns: dict[str, int]  # camera -> image stamp
    rig: Rig | None  # None: no CameraInfo / TF for the cameras yet (the export's own LUT stays in use)

    @property
    def stamp_ns(self) -> int | None:
        return max(self.stamps_ns.values()) if self.stamps_ns else None


@dataclass(frozen=True, eq=False)
class SweepEvent:
    """A LiDAR message turned into the runtime's slices."""

    cloud: Cloud
    slices: list[TimedSlice]  # scan order
    lidar2ego: np.ndarray  # (4, 4)
    ego2global: np.ndarray  # (4, 4) at the cloud's stamp; identity without a global frame
    sample_token: str | None  # from the bag's streamdet metadata (bags written by streamdet-bag export)
    image_set: ImageSet | None  # feed before the slices; None: no new image since the previous cloud


# BagSource.scan_layout reads at most this many LiDAR messages, and at least this many slices of a slicing driver.
LAYOUT_MESSAGES = 64
LAYOUT_MIN_SLICES = 4

@dataclass(frozen=True)
class SourceConfig:
    topics: T.TopicMap = field(default_factory=T.TopicMap)
    camera_names: tuple[str, ...] = ()  # the cameras to read, in the rig's order (the export's)
    num_slices: int = 8
    start_deg: float = 0.0  # the LiDAR's scan layout (core/sectors.py; the detector's DetectorConfig.start_deg, clockwise)
    clockwise: bool = False
    slice_per_message: bool = False  # the driver publishes slices: one message = one slice
    cloud_fields: CloudFields = field(default_factory=lambda: CloudFields(require_time=False))
    ego_frame: str = T.EGO_FRAME
    global_frame: str | None = T.GLOBAL_FRAME  # None: the stack has no localisation; ego motion is ignored
    tf_tolerance_ns: int = DEFAULT_TF_TOLERANCE_NS
    # a camera whose newest image is older than this (seconds of header stamps, against the LiDAR message's) is left
    # out of the image sets from then on, its features zeros, until it sends again: a dead camera's last image is not
    # fused on (three of its own frame periods where longer: core/camera_timeout.py). None: never left out
    camera_timeout_s: float | None = DEFAULT_CAMERA_TIMEOUT_S

    def __post_init__(self) -> None:
        self.topics.check_distinct(tuple(self.camera_names))  # one topic feeding two roles reads garbage into one
        check_camera_timeout(self.camera_timeout_s, "SourceConfig.camera_timeout_s")


class BagSource:
    """Iterates a ``.mcap`` ROS 2 bag (or a rosbag2 folder holding one)."""

    def __init__(self, path: str | Path, config: SourceConfig) -> None:
        self.path = _mcap_file(Path(path))
        self.config = config
        self._reader_mod = require("mcap.reader")
        self._decoder_mod = require("mcap_ros2.decoder")
        self._read_errors = _read_errors()
        self._warned_missing: tuple[str, ...] = ()
        self._warned_times = False
        self.cameras_without_info: set[str] = set()  # cameras whose CameraInfo was missing when an image set was made
        self.cameras_timed_out: dict[str, int] = {}  # camera -> times its images stopped for the camera timeout
        # cameras timed out although they had just sent an image: stamped on another clock than the LiDAR? (logged once)
        self.cameras_lagging: set[str] = set()
        self.num_time_dropped = 0  # LiDAR points dropped for a non-finite or implausible per-point time, all clouds
        # LiDAR messages read without per-point times because their time column was on another clock or unit
        # (CloudClockError; only where CloudFields.require_time is False), their slices stamped with the cloud's stamp
        self.num_clouds_untimed = 0
        self._warned_clock = False
        # LiDAR messages skipped for their header stamp (events()): one equal to the newest read (the same cloud again:
        # republished, recorded twice; with slice_per_message, a slice of the rotation read again), one earlier than it
        # (a clock step back, a reordered recording). Detecting either would run the detector back in time and give a
        # sweep the results key of one already detected.
        self.num_clouds_repeated = 0
        self.num_clouds_behind = 0
        self._warned_stamps: set[str] = set()

    def metadata(self) -> dict[str, dict[str, str]]:
        """The bag's MCAP metadata records by name."""
        with open(self.path, "rb") as f, self._reading():
            return {m.name: dict(m.metadata) for m in self._reader(f).iter_metadata()}

    def sample_tokens(self) -> dict[str, str]:
        """LiDAR stamp (ns, as text) -> nuScenes sample token, from the metadata ``streamdet-bag export`` writes;
        empty for a bag recorded elsewhere."""
        text = self.metadata().get(T.METADATA_NAME, {}).get("sample_tokens", "{}")
        try:
            tokens = json.loads(text)
        except ValueError as e:  # JSONDecodeError, or an integer too long to convert
            raise BagReadError(f"{self.path}: metadata {T.METADATA_NAME}.sample_tokens is not JSON ({e}): "
                               f"{text[:80]!r}") from None
        if not (isinstance(tokens, dict) and all(isinstance(v, str) for v in tokens.values())):
            raise BagReadError(f"{self.path}: metadata {T.METADATA_NAME}.sample_tokens must be an object of stamp -> "
                               f"token strings, got {text[:80]!r}")  # fmt: skip
        return tokens

    def topics(self) -> dict[str, str]:
        """topic -> message type of every channel in the bag."""
        return dict(self._channel_types())

    def _channel_types(self) -> list[tuple[str, str]]:
        """(topic, message type) of every channel the bag's summary lists ("" for a schemaless one), in its order: a
        topic recorded on two channels is listed twice. Empty for a bag without a summary or whose summary lists no
        channel (its messages still read, unindexed)."""
        with open(self.path, "rb") as f, self._reading():
            summary = self._reader(f).get_summary()
        if summary is None:
            return []
        out = []
        for ch in summary.channels.values():
            if ch.schema_id == 0:  # MCAP's "no schema" (a schemaless JSON channel, say): no message type
                out.append((ch.topic, ""))
            elif ch.schema_id in summary.schemas:
                out.append((ch.topic, summary.schemas[ch.schema_id].name))
            else:  # a corrupted summary
                raise BagReadError(f"{self.path}: {_CORRUPT}: channel {ch.topic!r} names schema {ch.schema_id}, "
                                   "which the bag does not hold")  # fmt: skip
        return out

    def messages(self, topics: tuple[str, ...] | None = None) -> Iterator[BagMessage]:
        """Every ROS 2 (CDR) message (of ``topics``; None: all), decoded, in log-time order; channels in other
        encodings (a Foxglove protobuf or JSON topic) are skipped with a warning."""
        factory = self._decoder_mod.DecoderFactory()
        skipped: set[str] = set()
        with open(self.path, "rb") as f:
            with self._reading():
                records = self._reader(f).iter_messages(topics=None if topics is None else list(topics), log_time_order=True)
            while True:
                # only the library's work is guarded, never the consumer's: a yield sits outside every guard.
                # KeyError: mcap looks up the channel and schema ids a chunk names in the summary
                with self._reading(also=(KeyError,)):
                    item = next(records, None)
                if item is None:
                    return
                schema, channel, record = item
                where = f"message on {channel.topic} at log time {record.log_time} ns"
                # NameError and TypeError: how the vendored rosidl parser refuses a bad field or constant name or
                # type in the schema text (guarded here alone: nothing else it runs is given bytes of the bag)
                with self._reading(where, also=(NameError, TypeError)):
                    decode = factory.decoder_for(channel.message_encoding, schema)
                if decode is None:
                    if channel.topic not in skipped:
                        log.warning("%s: topic %s is %s, not ROS 2 CDR: skipped", self.path, channel.topic,
                                    channel.message_encoding)  # fmt: skip
                        skipped.add(channel.topic)
                    continue
                with self._reading(where):
                    message = BagMessage(channel.topic, schema.name, schema.data.decode(), int(record.log_time),
                                         decode(record.data), dict(channel.metadata))  # fmt: skip
                yield message

    def scan_layout(self, max_messages: int = LAYOUT_MESSAGES) -> ScanLayout | None:
        """How the LiDAR turns, from the per-point times of its first clouds (``core/scan_layout.py``): their points
        together, by absolute time (one full-sweep message, or the first LAYOUT_MIN_SLICES or more messages of a
        driver publishing slices, whose start is then the axis nearest where the first one began); None where the
        clouds have no usable times."""
        points, times = [], []
        lidar = self.config.topics.lidar
        roles = self._roles()
        self._check_topic_types(roles)  # a camera topic named as the LiDAR's would be decoded as a cloud
        first_stamp = None
        for i, message in enumerate(self.messages((lidar,))):
            if i >= max_messages:
                break
            self._check_topic_type(message.topic, message.datatype, roles)  # a bag without a summary: checked here
            try:
                cloud = decode_pointcloud2(message.message, replace(self.config.cloud_fields, require_time=False))
            except (ValueError, CloudClockError):  # read again, and refused with its name, by events()
                continue
            if cloud.time_s is None or not len(cloud.points):
                continue
            first_stamp = cloud.stamp_ns if first_stamp is None else first_stamp
            points.append(cloud.points[:, :2])
            times.append((cloud.stamp_ns - first_stamp) * 1e-9 + cloud.time_s.astype(np.float64))  # one clock
            found = layout_from_times(np.concatenate(points), np.concatenate(times))
            # slices: a few of them, so that a quarter turn is not read off one slice's jitter
            if found is not None and (not self.config.slice_per_message or len(points) >= LAYOUT_MIN_SLICES):
                return ScanLayout(found.start_deg, found.clockwise, f"from the per-point times of {lidar}")
        return None

    def events(self) -> Iterator[tuple[BagMessage, SweepEvent | None]]:
        """Every message with, for each LiDAR message, the sweep event it makes; None for one skipped for its stamp:
        at or before the newest one taken (with ``slice_per_message``, before it, or at it and a slice the rotation
        had already sent), counted in ``num_clouds_repeated`` / ``num_clouds_behind``. Its images wait for the next
        cloud taken. Skipped rather than detected, as tf2 drops old data: a sweep back in time would be cut with the
        wrong ego poses, run the detector's caches backwards, and replace the results of the sweep whose stamp (and
        so sample token) it carries."""
        cfg = self.config
        topics = cfg.topics
        image_topics = {topics.image_topic(c): c for c in cfg.camera_names}
        info_topics = {topics.camera_info_topic(c): c for c in cfg.camera_names}
        tokens = self.sample_tokens()
        roles = self._roles()
        self._check_topic_types(roles)
        tf = TfBuffer(max_extrapolation_ns=cfg.tf_tolerance_ns)
        infos: dict[str, Any] = {}
        latest: dict[str, Any] = {}  # camera -> newest image message, decoded only when a set is made
        timeout = CameraTimeout(cfg.camera_timeout_s, "SourceConfig.camera_timeout_s")
        fresh = False
        saw_lidar = False
        newest: int | None = None  # header stamp of the newest LiDAR message taken (ns)
        last_index = -1  # slice_per_message: the last slice index taken at that stamp
        for msg in self.messages():
            event = None
            self._check_topic_type(msg.topic, msg.datatype, roles)  # a bag without a summary: its channels unlisted
            if msg.topic == topics.tf_static:
                tf.add(msg.message, static=True)
            elif msg.topic == topics.tf:
                tf.add(msg.message)
            elif msg.topic in info_topics:
                infos[info_topics[msg.topic]] = msg.message
            elif msg.topic in image_topics:
                camera = image_topics[msg.topic]
                latest[camera] = msg.message
                timeout.seen(camera, header_stamp_ns(msg.message) * 1e-9)
                fresh = True
            elif msg.topic == topics.lidar:
                saw_lidar = True
                stamp = header_stamp_ns(msg.message)
                # a full sweep is one message per stamp; a driver's slices of one rotation may share its stamp
                if newest is not None and (stamp < newest or (stamp == newest and not cfg.slice_per_message)):
                    self._skip_cloud(stamp, newest, msg.log_time_ns)  # its images wait for the next cloud taken
                    yield msg, None
                    continue
                event = self._sweep(msg.message, tf, tokens)
                if stamp == newest and event.slices and event.slices[0].index <= last_index:
                    # a slice of the rotation at this stamp again (republished): not a new rotation at the same stamp
                    self._skip_cloud(stamp, newest, msg.log_time_ns, event.slices[0].index)
                    yield msg, None
                    continue
                if stamp != newest:
                    newest, last_index = stamp, -1
                if event.slices:
                    last_index = event.slices[-1].index
                lidar_s = stamp * 1e-9
                gone, lagging = timeout.check(list(latest), lidar_s)
                for camera in lagging:  # it does send: its images are stamped far behind the LiDAR's
                    self._lagging(camera, lidar_s - header_stamp_ns(latest[camera]) * 1e-9)
                for camera in gone:
                    del latest[camera]  # its features are zeros from this set on, until it sends again
                    self.cameras_timed_out[camera] = self.cameras_timed_out.get(camera, 0) + 1
                    fresh = True
                image_set = None
                if fresh:
                    image_set = self._image_set(latest, infos, tf, msg.message) if latest else ImageSet({}, {}, None)
                fresh = False
                event = replace(event, image_set=image_set)
            yield msg, event
        if not saw_lidar:
            raise ValueError(f"{self.path} has no message on the LiDAR topic {topics.lidar!r}; its topics: {self.topics()}")

    def sweeps(self) -> Iterator[SweepEvent]:
        """The sweep events alone."""
        for _, event in self.events():
            if event is not None:
                yield event

    # ---- internals ------------------------------------------------------------------------------------
    def _reader(self, f: BinaryIO) -> Any:
        # CRCs checked: a flipped byte in a chunk is then reported as corruption instead of read as data
        return self._reader_mod.make_reader(f, validate_crcs=True)

    @contextmanager
    def _reading(self, where: str = "", also: tuple[type[BaseException], ...] = ()) -> Iterator[None]:
        """The reading libraries' errors (and ``also``, what the guarded call raises for bad bytes beside them) as
        one BagReadError naming the bag (and ``where`` in it)."""
        try:
            yield
        except self._read_errors + also as e:
            raise self._corrupt(e, where) from e
        except RuntimeError as e:  # lz4.frame reports a corrupt block as a bare RuntimeError
            if not _is_lz4_error(e):
                raise
            raise self._corrupt(e, where) from e

    def _corrupt(self, e: BaseException, where: str) -> BagReadError:
        kind = type(e).__name__ if type(e).__name__ != "error" else f"{type(e).__module__}.error"  # struct.error
        detail = f"{kind}: {e}" if str(e) else kind
        return BagReadError(f"{self.path}: {_CORRUPT}{f' ({where})' if where else ''}: {' '.join(detail.split())}")

    def _roles(self) -> dict[str, tuple[str, str, tuple[str, ...]]]:
        """topic -> (--topics key, role, the message types it may carry) of every topic this source interprets: the
        LiDAR, TF, static TF, and the image and CameraInfo topics of the cameras it reads."""
        topics = self.config.topics
        roles = {topics.lidar: ("lidar", "LiDAR", (T.POINTCLOUD2,)), topics.tf: ("tf", "TF", (T.TF_MESSAGE,)),
                 topics.tf_static: ("tf_static", "static TF", (T.TF_MESSAGE,))}  # fmt: skip
        for camera in self.config.camera_names:
            roles[topics.image_topic(camera)] = (camera, f"{camera} image", (T.COMPRESSED_IMAGE, T.IMAGE))
            roles[topics.camera_info_topic(camera)] = (f"{camera}.info", f"{camera} CameraInfo", (T.CAMERA_INFO,))
        return roles

    def _check_topic_types(self, roles: dict[str, tuple[str, str, tuple[str, ...]]]) -> None:
        """Every channel of a topic in ``roles`` (``_roles()``) must carry that role's message type, checked before
        anything is read: a topic mapped to the wrong role (an image topic named as the CameraInfo one, a camera topic
        as the LiDAR's) would have its messages taken for another type, and fail deep in an adapter without naming the
        topic, or (the LiDAR's) make the bag seem to hold no cloud. ValueError naming the topic, the type found and the
        one expected, and the bag's topics of that type."""
        for topic, datatype in self._channel_types():
            self._check_topic_type(topic, datatype, roles)

    def _check_topic_type(self, topic: str, datatype: str, roles: dict[str, tuple[str, str, tuple[str, ...]]]) -> None:
        """``_check_topic_types`` for one channel or message (``datatype``: its type, "" for schemaless)."""
        role = roles.get(topic)
        if role is None or _is_type(datatype, role[2]):
            return
        key, what, expected = role
        kind = datatype or "schemaless (no message type)"
        names = "/".join(e.rsplit("/", 1)[-1] for e in expected)
        channels = self._channel_types()  # none listed (a bag without a summary): no list, rather than a wrong "[]"
        candidates = sorted({t for t, found in channels if _is_type(found, expected)})
        listed = f" ({names} topics in the bag: {candidates})" if channels else ""
        raise ValueError(f"{self.path}: the {what} topic {topic!r} carries {kind} messages, not {' or '.join(expected)}; "
                         f"name the {what} topic with --topics {key}=/topic{listed}")  # fmt: skip

    def _skip_cloud(self, stamp: int, newest: int, log_time_ns: int, slice_index: int | None = None) -> None:
        """Count a LiDAR message skipped for its stamp (``events()``); the first of each kind is warned."""
        lidar = self.config.topics.lidar
        if stamp == newest:
            self.num_clouds_repeated += 1
            kind = "repeated"
            said = ("repeats the stamp of one already read" if slice_index is None else
                    f"repeats slice {slice_index} of the rotation already read at that stamp")  # fmt: skip
            why = "detected again, it would take the results key of the one already detected"
        else:
            self.num_clouds_behind += 1
            kind = "behind"
            said = f"is stamped {(newest - stamp) * 1e-9:.6g} s before one already read ({newest} ns; a clock step back?)"
            why = "it would run the detector back in time, and take the results key of any sweep of its stamp"
        if kind in self._warned_stamps:
            return
        self._warned_stamps.add(kind)  # once per bag and kind: a driver that does it once may do it every time
        log.warning("%s: %s message at stamp %d ns (log time %d ns) %s: skipped, not detected (%s); later ones are "
                    "counted, not reported", self.path, lidar, stamp, log_time_ns, said, why)  # fmt: skip

    def _sweep(self, message: Any, tf: TfBuffer, tokens: dict) -> SweepEvent:
        """The event of a LiDAR message, without its image set (events() adds it once the message is taken)."""
        cfg = self.config
        cloud = self._cloud(message)
        if cfg.slice_per_message:
            self._check_one_slice(cloud)
            # an empty message names no sector (nothing was returned there): no slice, the run goes on
            slices = [slice_from_message(cloud, cfg.num_slices, cfg.start_deg, clockwise=cfg.clockwise)] if len(cloud.points) else []
        else:
            slices = split_cloud(cloud, cfg.num_slices, cfg.start_deg, cfg.clockwise)
        lidar2ego = _matrix(self._lookup(tf, cfg.ego_frame, cloud.frame_id, cloud.stamp_ns))
        pose = self._lookup(tf, cfg.global_frame, cfg.ego_frame, cloud.stamp_ns) if cfg.global_frame else IDENTITY_RECORD
        return SweepEvent(cloud, slices, lidar2ego, _matrix(pose), tokens.get(str(cloud.stamp_ns)), None)

    def _cloud(self, message: Any) -> Cloud:
        """The LiDAR message decoded; a malformed one is named by topic and stamp, dropped points are reported."""
        topic = self.config.topics.lidar
        fields = self.config.cloud_fields
        try:
            try:
                cloud = decode_pointcloud2(message, fields)
            except CloudClockError as e:
                if fields.require_time:  # the caller asked for per-point times: without them is not what it ran
                    raise
                # the bag is read anyway: a clock offset costs the slices their scan times, never their points
                cloud = decode_pointcloud2(message, replace(fields, time=None))
                self._untimed(e)
        except ValueError as e:
            raise ValueError(f"{self.path}: {topic} message at stamp {_stamp_text(message)}: {e}") from None
        self.num_time_dropped += cloud.num_time_dropped
        if cloud.num_time_dropped and not self._warned_times:
            # once per bag: a clock or unit mismatch drops points of every cloud, one line says it
            log.warning("%s: %s message at stamp %d ns: dropped %d of %d points whose per-point time (first: %.6g s "
                        "after the stamp) is not finite or lies more than %g s from the stamp (corrupted, or another "
                        "clock or unit); later clouds are not reported", self.path, topic, cloud.stamp_ns,
                        cloud.num_time_dropped, len(cloud.points) + cloud.num_time_dropped + cloud.num_dropped,
                        cloud.dropped_time_s, self.config.cloud_fields.max_time_offset_s)  # fmt: skip
            self._warned_times = True
        return cloud

    def _untimed(self, e: CloudClockError) -> None:
        self.num_clouds_untimed += 1
        if not self._warned_clock:
            self._warned_clock = True  # once per bag: every cloud of a driver on another clock says the same
            log.warning("%s: %s: read without per-point times, each slice stamped with its cloud's stamp; later clouds "
                        "are not reported (SourceConfig.cloud_fields)", self.path, " ".join(str(e).split()))  # fmt: skip

    def _check_one_slice(self, cloud: Cloud) -> None:
        """With slice_per_message, refuse a message that spreads over more than one slice's arc (a full sweep): the
        slice graph would see only one sector's quadrants of it (ValueError naming the message and the flag)."""
        n = self.config.num_slices
        share = slice_arc_share(cloud.points, n, self.config.start_deg)
        if share >= min_slice_share(n):
            return
        raise ValueError(f"{self.path}: {self.config.topics.lidar} message at stamp {cloud.stamp_ns} ns is not one slice: "
                         f"at most {share:.0%} of its {len(cloud.points)} points lie within one slice's arc ({360 / n:g} "
                         f"deg, 1 of {n}), as in a full sweep; drop --slice-per-message (SourceConfig.slice_per_message) "
                         "for a driver that publishes full sweeps")  # fmt: skip

    def _lookup(self, tf: TfBuffer, parent: str, child: str, stamp: int) -> dict:
        if parent == child.lstrip("/"):
            return IDENTITY_RECORD
        try:
            return tf.lookup(parent, child, stamp)
        except (KeyError, ValueError) as e:
            raise ValueError(f"{self.path}: {e.args[0]}") from None

    def _lagging(self, camera: str, behind_s: float) -> None:
        if camera not in self.cameras_lagging:
            self.cameras_lagging.add(camera)
            log.warning("%s: camera %s sends images, but stamped %.3g s behind the LiDAR's (a clock not synchronised with "
                        "the LiDAR's?): left out for the camera timeout, its features zeros", self.path, camera, behind_s)  # fmt: skip

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


_CORRUPT = "not a readable MCAP bag (truncated or corrupted)"


def _is_type(datatype: str, expected: tuple[str, ...]) -> bool:
    # rosbag2 writes pkg/msg/Type; a bag converted from ROS 1 may name it pkg/Type
    return any(datatype in (e, e.replace("/msg/", "/")) for e in expected)


def min_slice_share(num_slices: int) -> float:
    """The least share of a message's points one slice-wide arc must hold for the message to be one slice: midway
    between a full sweep's even spread (1 / num_slices per arc) and a slice's (all of them), so neither a driver
    slice cut at another phase nor an unevenly filled sweep lands on the wrong side."""
    return (1.0 + 1.0 / num_slices) / 2.0


def slice_arc_share(points: np.ndarray, num_slices: int, start_deg: float = 0.0) -> float:
    """The largest share of ``points`` (N, >=2) that one arc of a slice's width (360 / num_slices deg) holds, the arc
    placed anywhere (in steps of 1 / ARC_BINS_PER_SLICE slice): near 1 for a message that is one slice, also one cut
    at another phase than streamdet's sectors; about 1 / num_slices for a full sweep. 1.0 for one slice per sweep or
    no points."""
    if num_slices <= 1 or len(points) == 0:
        return 1.0
    bins = num_slices * ARC_BINS_PER_SLICE
    rel = np.mod(azimuth_deg(points[:, 0], points[:, 1]) - start_deg, 360.0)
    which = np.minimum((rel * (bins / 360.0)).astype(np.int64), bins - 1)  # rel can round up to 360
    counts = np.bincount(which, minlength=bins)
    ring = np.concatenate([counts, counts[: ARC_BINS_PER_SLICE - 1]])  # arcs that wrap past 360 deg
    window = np.convolve(ring, np.ones(ARC_BINS_PER_SLICE, np.int64), mode="valid")
    return float(window.max()) / len(points)


def _read_errors() -> tuple[type[BaseException], ...]:
    """What the reading libraries raise on bad bytes: mcap's McapError (mcap_ros2's decode errors derive from it),
    struct.error and EOFError of a short record, OSError of a seek past the start of a tiny file, ValueError (a bad
    CRC, UTF-8 or CDR header), zstandard's ZstdError and the vendored ROS message parser's errors where importable.
    Not TypeError, AttributeError or the like: those are bugs and keep their traceback."""
    errors: list[type[BaseException]] = [require("mcap.exceptions").McapError, struct.error, EOFError, OSError, ValueError]
    for module, names in (("zstandard", ("ZstdError",)),
                          ("mcap_ros2._vendor.rosidl_adapter.parser", ("InvalidSpecification", "InvalidValue"))):  # fmt: skip
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        errors += [getattr(mod, n) for n in names if isinstance(getattr(mod, n, None), type)]
    return tuple(errors)


def _is_lz4_error(e: RuntimeError) -> bool:
    # lz4.frame has no error class of its own; its messages name the failing LZ4F_ call
    return "LZ4F_" in str(e)


def _stamp_text(message: Any) -> str:
    try:
        return f"{header_stamp_ns(message)} ns"
    except (AttributeError, ValueError):
        return "(unreadable)"


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
        if path.exists():  # a FIFO or a device: never opened
            raise ValueError(f"{path} is not a regular file (a FIFO or a device?): not a bag")
        raise FileNotFoundError(f"bag not found: {path}")
    return path
