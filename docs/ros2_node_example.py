"""A ROS 2 node that runs streamdet: subscribe to the LiDAR and cameras, detect each slice, publish the boxes.

Drop it into a ROS 2 (Humble or newer) Python package with streamdet installed beside it from its checkout, as the
README does (``pip install /path/to/streamdet``, the vehicle runtime alone, or ``pip install -e /path/to/streamdet``
to follow the checkout; not from a package registry), and run it with
``ros2 run <your_package> streamdet_node --ros-args -p export_dir:=/path/to/export``. It needs rclpy,
sensor_msgs, vision_msgs, visualization_msgs and rosidl_runtime_py, none of which is installed where streamdet is
developed, so the node itself has never run there; the functions and the classes above ``main`` are run on a bag's
messages by tests/test_bag_run.py, and ``main``'s callbacks on stand-in rclpy modules by
tests/test_ros_embed_review.py. docs/ros2.md explains each step.

One bad message (a JPEG truncated on a lossy link, a short PointCloud2 after a driver restart) must not end the node:
rclpy re-raises a callback's exception out of ``rclpy.spin``. So each callback catches the ValueErrors a message
causes (``RosMessageError``: the adapters' refusals; the detector's refusals of its input), logs them at most every
few seconds per source (``ErrorLog``) and goes on with the next message. Other exceptions are bugs, and end it.

Kept short, it runs the image lane inside the cloud callback of a single-threaded executor, so a cloud waits for the
image update before it: a vehicle node moves the image lane off that path (``StreamingRunner``, README "Python API",
or its own callback group on a MultiThreadedExecutor) and freezes the heap after start-up
(``streamdet.runtime_ort.heap``). It fuses with the export's calibration; a rig of its own comes from CameraInfo and
TF (docs/ros2.md, ``rig_from_ros`` and ``set_calibration``).
"""

from __future__ import annotations

import logging
import time
import weakref
from typing import Callable

import cv2
import numpy as np

from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S, CameraTimeout
from streamdet.core.providers import parse_providers
from streamdet.runtime_ort.detector import DetectorConfig, ImageUpdate, StreamingDetector
from streamdet.runtime_ort.ros.detections import detection3d_array_message, marker_array_message
from streamdet.runtime_ort.ros.header import header_stamp_ns
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb
from streamdet.runtime_ort.ros.pointcloud2 import Cloud, CloudClockError, CloudFields, decode_pointcloud2, split_cloud

log = logging.getLogger("streamdet_node")

# Per-point times where the cloud has them: each slice is then stamped when it was scanned, not with the cloud's stamp.
TIMED = CloudFields(require_time=False)
UNTIMED = CloudFields(time=None)


class ErrorLog:
    """Logs a bad message's error at most once per ``period_s`` for each source (a camera, the LiDAR), with how many
    were not logged meanwhile: a camera sending corrupt frames at 30 Hz must neither flood the log nor go unseen."""

    def __init__(self, period_s: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = period_s
        self.clock = clock
        self.count = 0  # every error reported, logged or not
        self._last: dict[str, float] = {}
        self._quiet: dict[str, int] = {}

    def report(self, source: str, error: BaseException | str) -> None:
        self.count += 1
        now = self.clock()
        last = self._last.get(source)
        if last is not None and now - last < self.period_s:
            self._quiet[source] = self._quiet.get(source, 0) + 1
            return
        self._last[source] = now
        quiet = self._quiet.pop(source, 0)
        more = f" ({quiet} more since the last report)" if quiet else ""
        log.warning("%s: %s%s", source, " ".join(str(error).split()), more)


_ERRORS = ErrorLog()  # for callers that keep none of their own
# detector -> {slice index: boxes its markers showed last}: a caller that keeps no record still deletes what it left
_SHOWN: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def decode_cloud(cloud_msg, errors: ErrorLog | None = None) -> Cloud:
    """The cloud with its per-point times; without them (every slice stamped with the cloud's stamp, reported to
    ``errors``) when its time column is on another clock or in another unit than its header (``CloudClockError``):
    dropping those points, or refusing every cloud, would leave the detector blind."""
    try:
        return decode_pointcloud2(cloud_msg, TIMED)
    except CloudClockError as e:
        (errors or _ERRORS).report("LiDAR per-point time", f"{e}; read without per-point times")
        return decode_pointcloud2(cloud_msg, UNTIMED)


def detect_cloud(
    detector: StreamingDetector, cloud_msg, shown: dict[int, int] | None = None, errors: ErrorLog | None = None
) -> list[tuple[dict, dict]]:
    """(Detection3DArray, MarkerArray) message dicts of every slice of one PointCloud2, in scan order.

    ``shown`` (slice index -> boxes its markers showed; None: a record kept for ``detector``) is updated once every
    slice is done: a slice that finds fewer boxes than last time deletes the markers beyond its count, which would
    otherwise stay on screen (lifetime 0), as ``streamdet-bag run`` does. A RosMessageError (or the detector's
    ValueError) leaves it as it was, so the next cloud deletes what is really on screen."""
    shown = _SHOWN.setdefault(detector, {}) if shown is None else shown
    cloud = decode_cloud(cloud_msg, errors)
    out, counts = [], {}
    for s in split_cloud(cloud, detector.num_slices, detector.config.start_deg, detector.config.clockwise):
        d = detector.detect_slice(s.points, s.index, timestamp=s.scan_time_ns * 1e-9).detections
        counts[s.index] = len(d.scores)
        stale = range(len(d.scores), shown.get(s.index, 0))
        out.append((detection3d_array_message(d.boxes, d.scores, d.labels, s.scan_time_ns, s.frame_id),
                    marker_array_message(d.boxes, d.labels, s.scan_time_ns, s.frame_id, d.scores, ns=f"slice_{s.index}",
                                         stale_ids=stale)))  # fmt: skip
    shown.update(counts)
    return out


def camera_image(detector: StreamingDetector, image_msg) -> np.ndarray:
    """A CompressedImage as the RGB image the detector's image lane takes (resized to the export's size)."""
    rgb = compressed_image_to_rgb(image_msg)
    size = (detector.image.width, detector.image.height)
    return rgb if rgb.shape[1::-1] == size else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


class CameraFrames:
    """The newest image of every camera with its capture time, fed to the image lane whole when any camera sent a
    new one: a camera left out of an update would be lifted as zeros. The times are the messages' header stamps,
    the clock of the slices' scan times, so the image age at fusion (and the LiDAR-only fallback) reads true.

    A camera that has sent nothing for ``timeout_s`` (against the cloud's stamp; three of its own frame periods where
    longer: streamdet.core.camera_timeout) is dropped, so a dead camera's last image is not fused on: the next update
    lifts its features as zeros (``ImageUpdate.cameras_missing``); a quadrant none of whose cameras is left is cleared
    by that update (``ImageUpdate.cleared``), and with every camera gone the image BEV is dropped (slices read the
    camera-less BEV, or the LiDAR-only fallback). None: kept however old."""

    def __init__(self, timeout_s: float | None = DEFAULT_CAMERA_TIMEOUT_S) -> None:
        self.images: dict[str, np.ndarray] = {}
        self.stamps_s: dict[str, float] = {}
        self.new = False  # a frame arrived, or a camera timed out, since the last update
        self.timeout = CameraTimeout(timeout_s, "CameraFrames timeout_s")
        self.lagging: set[str] = set()  # timed out although sending: stamped on another clock? (warned once each)

    def add(self, detector: StreamingDetector, camera: str, image_msg) -> None:
        self.images[camera] = camera_image(detector, image_msg)
        self.stamps_s[camera] = header_stamp_ns(image_msg, "sensor_msgs/CompressedImage") * 1e-9
        self.timeout.seen(camera, self.stamps_s[camera])
        self.new = True

    def update(self, detector: StreamingDetector, now_s: float | None = None) -> ImageUpdate | None:
        """The image lane on the newest frame of every camera, if one is new since the last call (or a camera timed
        out at ``now_s``, the cloud's stamp); None if none is."""
        gone, lagging = ([], []) if now_s is None else self.timeout.check(list(self.images), now_s)
        for camera in set(lagging) - self.lagging:
            self.lagging.add(camera)
            log.warning("camera %s sends images stamped %.3g s behind the cloud's: is its clock synchronised with the "
                        "LiDAR's? Left out meanwhile", camera, now_s - self.stamps_s[camera])  # fmt: skip
        for camera in gone:
            del self.images[camera], self.stamps_s[camera]
            self.new = True
        if not self.new:
            return None
        self.new = False
        if not self.images:  # every camera timed out
            detector.forget_images()
            return None
        return detector.update_images(dict(self.images), timestamp=max(self.stamps_s.values()),
                                      camera_timestamps=dict(self.stamps_s))  # fmt: skip


def main() -> None:  # the ROS boilerplate
    import rclpy
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from rosidl_runtime_py.set_message_fields import set_message_fields
    from sensor_msgs.msg import CompressedImage, PointCloud2
    from vision_msgs.msg import Detection3DArray
    from visualization_msgs.msg import MarkerArray

    def filled(cls, values: dict):
        msg = cls()
        set_message_fields(msg, values)
        return msg

    class StreamdetNode(Node):
        def __init__(self) -> None:
            super().__init__("streamdet")
            number = ParameterDescriptor(dynamic_typing=True)  # -p camera_timeout_s:=0 (an int) is taken as well as 0.0
            export_dir = self.declare_parameter("export_dir", "exports/small_v3").value
            # a LiDAR-only export for when the cameras are gone or late ("" : none): runtime_ort/fallback.py
            fallback = self.declare_parameter("fallback_export_dir", "").value or None
            max_age_s = float(self.declare_parameter("fallback_after_s", 0.5, number).value)
            # onnxruntime's providers by preference, "cuda,cpu" or "tensorrt,cuda" ("auto": CUDA where present, else CPU)
            providers = parse_providers(self.declare_parameter("providers", "auto").value, "parameter providers")
            # seconds without an image after which a camera is left out (0: never): streamdet.core.camera_timeout
            camera_timeout_s = float(self.declare_parameter("camera_timeout_s", DEFAULT_CAMERA_TIMEOUT_S, number).value)
            # the LiDAR's scan layout (core/sectors.py): where its sweep starts, which way it turns (a Velodyne as
            # nuScenes' LIDAR_TOP: 180.0 and true); slices are cut and numbered in the order it scans them
            start_deg = float(self.declare_parameter("scan_start_deg", 0.0, number).value)
            clockwise = bool(self.declare_parameter("clockwise", False).value)
            self.detector = StreamingDetector(export_dir, DetectorConfig(
                fallback_export_dir=fallback, fallback_after_s=max_age_s if fallback else None, providers=providers,
                start_deg=start_deg, clockwise=clockwise))  # fmt: skip
            self.detector.warm_up()  # before the first message: onnxruntime's first runs of a graph are slow
            self.frames = CameraFrames(camera_timeout_s or None)
            self.shown: dict[int, int] = {}  # slice -> boxes its markers show, so fewer next time deletes the rest
            self.errors = ErrorLog()
            self.boxes = self.create_publisher(Detection3DArray, "/streamdet/detections", 10)
            self.markers = self.create_publisher(MarkerArray, "/streamdet/markers", 10)
            # best effort, newest only, as sensor drivers publish (a reliable subscription never matches their
            # best-effort publishers and receives nothing)
            self.create_subscription(PointCloud2, "/LIDAR_TOP", self.on_cloud, qos_profile_sensor_data)
            for cam in self.detector.camera_names:
                self.create_subscription(CompressedImage, f"/{cam}/image_rect_compressed",
                                         lambda msg, cam=cam: self.on_image(cam, msg), qos_profile_sensor_data)  # fmt: skip

        def on_image(self, cam: str, msg) -> None:
            try:
                self.frames.add(self.detector, cam, msg)
            except ValueError as e:  # this image only (RosMessageError: truncated, not colour, ...): the last one stays
                self.errors.report(f"{cam} image", e)

        def on_cloud(self, msg) -> None:
            try:
                stamp_s = header_stamp_ns(msg, "sensor_msgs/PointCloud2") * 1e-9
            except ValueError as e:
                self.errors.report("LiDAR cloud", e)
                return
            try:
                # the image lane first, so the slices see the newest cameras (and none that stopped sending)
                self.frames.update(self.detector, stamp_s)
            except ValueError as e:  # the slices run on the image BEV in use
                self.errors.report("image lane", e)
            try:
                published = detect_cloud(self.detector, msg, self.shown, self.errors)
            except ValueError as e:  # this cloud only (RosMessageError: short data, a missing field, ...)
                self.errors.report("LiDAR cloud", e)
                return
            for detections, markers in published:
                self.boxes.publish(filled(Detection3DArray, detections))
                self.markers.publish(filled(MarkerArray, markers))

    rclpy.init()
    rclpy.spin(StreamdetNode())


if __name__ == "__main__":
    main()
