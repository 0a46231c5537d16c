"""A recorded drive (``recording.Recording``) written as a ROS 2 MCAP bag, the topics a real car records.

| topic | type | frame |
|---|---|---|
| ``/tf_static`` | tf2_msgs/TFMessage | ``base_link -> LIDAR_TOP``, ``base_link -> CAM_*`` (mountings), once at the start |
| ``/tf`` | tf2_msgs/TFMessage | ``map -> base_link`` at every sensor time (the ego poses) |
| ``/LIDAR_TOP`` | sensor_msgs/PointCloud2 | ``LIDAR_TOP``; x y z intensity ring + per-point ``time`` |
| ``/CAM_*/image_rect_compressed`` | sensor_msgs/CompressedImage | ``CAM_*``; the dataset's JPEG, byte for byte |
| ``/CAM_*/camera_info`` | sensor_msgs/CameraInfo | ``CAM_*``; K, no distortion |
| ``/markers/annotations`` | visualization_msgs/MarkerArray | ``LIDAR_TOP``; ground truth at each key frame |

Every message is stamped and logged at its sensor time (nuScenes timestamps, microseconds -> nanoseconds); at
one instant the order is TF, CameraInfo, image, cloud, markers, so a reader sees a frame's images and poses
before its cloud. The cloud's stamp is the end of the sweep (nuScenes) and ``time`` is float32 seconds relative
to it (negative, Velodyne's convention); for data without per-point times (the real nuScenes sample) the time is
derived from each point's azimuth, as the runtime's slicing does. An MCAP metadata record ``streamdet`` names the
scene and the key frames' sample tokens by LiDAR stamp, which ``streamdet-bag run`` uses to key its results.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from streamdet.bag import topics as T
from streamdet.bag.recording import Recording
from streamdet.bag.writer import BagWriter
from streamdet.core.image_header import check_image_header
from streamdet.core.points import SWEEP_DURATION_S
from streamdet.core.scan_layout import NUSCENES_LIDAR_TOP
from streamdet.core.slicing import relative_time_s
from streamdet.data.sample import read_image_bytes
from streamdet.runtime_ort.ros.camera_info import camera_info_message
from streamdet.runtime_ort.ros.detections import marker_array_message
from streamdet.runtime_ort.ros.images import compressed_image_message, compressed_image_to_rgb
from streamdet.runtime_ort.ros.pointcloud2 import pointcloud2_message
from streamdet.runtime_ort.ros.tf import transform_stamped_msg

NS_PER_US = 1000
# order of messages sharing one stamp
_TF, _INFO, _IMAGE, _CLOUD, _MARKERS = range(5)


@dataclass(frozen=True)
class ExportSummary:
    path: Path
    scene: str
    num_sweeps: int
    num_images: int
    num_key_frames: int
    num_messages: int
    duration_s: float


def export_recording(
    recording: Recording, out: str | Path, progress: Callable[[int, int], None] | None = None
) -> ExportSummary:
    """Write ``recording`` to the MCAP file ``out``; ``progress(done, total)`` per sensor message."""
    events: list[tuple[int, int, str, str, Callable[[], dict]]] = []  # (stamp ns, order, topic, type, message)
    poses: dict[int, dict] = {}
    for sweep in recording.sweeps:
        stamp = sweep.timestamp_us * NS_PER_US
        poses[stamp] = sweep.ego_pose
        events.append((stamp, _CLOUD, T.LIDAR_TOPIC, T.POINTCLOUD2, _cloud(sweep, stamp)))
        if sweep.gt is not None:
            events.append((stamp, _MARKERS, T.GT_MARKERS_TOPIC, T.MARKER_ARRAY, _gt_markers(sweep.gt, stamp)))
    for image in recording.images:
        stamp = image.timestamp_us * NS_PER_US
        poses[stamp] = image.ego_pose
        events.append((stamp, _INFO, T.camera_info_topic_of(T.image_topic(image.name)), T.CAMERA_INFO,
                       _info(image, stamp)))  # fmt: skip
        events.append((stamp, _IMAGE, T.image_topic(image.name), T.COMPRESSED_IMAGE,
                       _image(image, stamp, (image.width, image.height))))  # fmt: skip
    for stamp, pose in poses.items():
        events.append((stamp, _TF, T.TF_TOPIC, T.TF_MESSAGE, _ego_pose(pose, stamp)))
    events.sort(key=lambda e: (e[0], e[1]))
    if not events:
        raise ValueError(f"scene {recording.scene!r} holds no sensor data")
    start = events[0][0]
    mounts = [transform_stamped_msg(T.EGO_FRAME, T.LIDAR_FRAME, recording.lidar_mount, start)]
    mounts += [transform_stamped_msg(T.EGO_FRAME, name, rec, start) for name, rec in recording.camera_mounts.items()]
    tokens = {str(s.timestamp_us * NS_PER_US): s.sample_token for s in recording.sweeps if s.sample_token}
    with BagWriter(out) as writer:
        writer.metadata(T.METADATA_NAME, {"scene": recording.scene, "sample_tokens": json.dumps(tokens),
                                          "lidar_topic": T.LIDAR_TOPIC})  # fmt: skip
        writer.write(T.TF_STATIC_TOPIC, T.TF_MESSAGE, {"transforms": mounts}, start)
        for i, (stamp, _, topic, datatype, make) in enumerate(events):
            writer.write(topic, datatype, make(), stamp)
            if progress is not None:
                progress(i + 1, len(events))
        count = writer.count
    return ExportSummary(
        path=Path(out),
        scene=recording.scene,
        num_sweeps=len(recording.sweeps),
        num_images=len(recording.images),
        num_key_frames=len(tokens),
        num_messages=count,
        duration_s=(events[-1][0] - start) / 1e9,
    )


def cloud_time_s(
    points: np.ndarray, time_s: np.ndarray | None, sweep_duration_s: float = SWEEP_DURATION_S
) -> np.ndarray:
    """(N,) float32 per-point time relative to the sweep's stamp (its end): the recorded time after the sweep
    start minus the sweep duration, or, without recorded times (real nuScenes sweeps), the time nuScenes' LIDAR_TOP
    reaches the point's azimuth (clockwise from 180 deg, ``core.scan_layout.NUSCENES_LIDAR_TOP``): derived, within
    a few ms of the real firing."""
    if time_s is None:
        layout = NUSCENES_LIDAR_TOP
        time_s = relative_time_s(points, layout.start_deg, sweep_duration_s, layout.clockwise).astype(np.float32)
    return np.asarray(time_s, dtype=np.float32) - np.float32(sweep_duration_s)


def _cloud(sweep, stamp: int) -> Callable[[], dict]:
    def make() -> dict:
        points, time_s = sweep.load()
        return pointcloud2_message(points, stamp, T.LIDAR_FRAME, cloud_time_s(points, time_s))

    return make


def _ego_pose(pose: dict, stamp: int) -> Callable[[], dict]:
    return lambda: {"transforms": [transform_stamped_msg(T.GLOBAL_FRAME, T.EGO_FRAME, pose, stamp)]}


def _image(image, stamp: int, size: tuple[int, int] | None = None) -> Callable[[], dict]:
    """The image file as a CompressedImage, refused (ValueError naming the file) where ``streamdet-bag run`` would
    refuse the message: not decodable by the runtime's decoder (a truncated JPEG), or of another size than ``size``
    (width, height), the one its camera is calibrated for. Found here, the bag is never written; found there, only
    after a bag that looked fine was copied to the car."""

    def make() -> dict:
        data = read_image_bytes(image.path)  # bounded, a regular file: a FIFO or a device never blocks the export
        header = check_image_header(data, f"image {image.path}")  # a JPEG or PNG of a sane size, labelled as it is
        if size is not None and (header.width, header.height) != tuple(size):
            raise ValueError(f"image {image.path} is {header.width}x{header.height} px but its camera {image.name} is "
                             f"calibrated for {size[0]}x{size[1]}")  # fmt: skip
        message = compressed_image_message(data.tobytes(), stamp, image.name, header.format)
        try:
            compressed_image_to_rgb(SimpleNamespace(**message))  # as bag run decodes it; the pixels are not kept
        except ValueError as e:
            raise ValueError(f"image {image.path}: {e}") from None
        return message

    return make


def _info(image, stamp: int) -> Callable[[], dict]:
    return lambda: camera_info_message(image.K, image.width, image.height, stamp, image.name)


def _gt_markers(gt, stamp: int) -> Callable[[], dict]:
    return lambda: marker_array_message(gt.boxes, gt.labels, stamp, T.LIDAR_FRAME, names=list(gt.names), ns="ground_truth",
                                        replace=True)  # fmt: skip
