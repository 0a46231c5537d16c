"""Topic names and frames of the bags ``streamdet-bag`` writes, and the mapping to a real car's topic names.

The layout is the one of Foxglove's nuScenes-to-MCAP converter: one frame per sensor channel, ``base_link`` for
the ego vehicle, ``map`` for the global frame; images on ``/<CAM>/image_rect_compressed`` beside
``/<CAM>/camera_info``. Sensor mountings go to ``/tf_static`` (as a car's URDF publishes them), ego poses to ``/tf``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

LIDAR_FRAME = "LIDAR_TOP"
EGO_FRAME = "base_link"
GLOBAL_FRAME = "map"
LIDAR_TOPIC = "/LIDAR_TOP"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
GT_MARKERS_TOPIC = "/markers/annotations"
DETECTIONS_TOPIC = "/streamdet/detections"
DETECTION_MARKERS_TOPIC = "/streamdet/markers"
METADATA_NAME = "streamdet"  # MCAP metadata record: scene name, key-frame sample tokens by LiDAR stamp

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DETECTION3D_ARRAY = "vision_msgs/msg/Detection3DArray"


def image_topic(camera: str) -> str:
    return f"/{camera}/image_rect_compressed"


def camera_info_topic_of(image_topic_name: str) -> str:
    """The CameraInfo topic beside an image topic (image_transport's layout): ``/cam/image/compressed`` ->
    ``/cam/camera_info``, ``/CAM_FRONT/image_rect_compressed`` -> ``/CAM_FRONT/camera_info``."""
    base = image_topic_name[: -len("/compressed")] if image_topic_name.endswith("/compressed") else image_topic_name
    head = base.rsplit("/", 1)[0]
    return f"{head}/camera_info"


@dataclass(frozen=True)
class TopicMap:
    """Which topic holds the LiDAR, each camera's images and CameraInfo, and TF."""

    lidar: str = LIDAR_TOPIC
    cameras: dict[str, str] = field(default_factory=dict)  # camera name -> image topic; empty: /<CAM>/image_rect_compressed
    camera_infos: dict[str, str] = field(default_factory=dict)  # camera name -> CameraInfo topic; default: beside the image
    tf: str = TF_TOPIC
    tf_static: str = TF_STATIC_TOPIC

    def image_topic(self, camera: str) -> str:
        return self.cameras.get(camera, image_topic(camera))

    def camera_info_topic(self, camera: str) -> str:
        return self.camera_infos.get(camera, camera_info_topic_of(self.image_topic(camera)))

    def check_distinct(self, cameras: tuple[str, ...] = ()) -> None:
        """ValueError naming both when two roles read one topic (``lidar=/x,CAM_FRONT=/x``, two cameras on one image
        topic, a camera on the default topic of another): the bag's messages of that topic would feed both. Roles: the
        LiDAR, TF, static TF and the image and CameraInfo topics of ``cameras`` and of every camera the map names."""
        roles = {"lidar": self.lidar, "tf": self.tf, "tf_static": self.tf_static}
        for camera in dict.fromkeys((*cameras, *self.cameras, *self.camera_infos)):
            roles[camera] = self.image_topic(camera)
            roles[f"{camera}.info"] = self.camera_info_topic(camera)
        owner: dict[str, str] = {}
        for role, topic in roles.items():
            if topic in owner:
                raise ValueError(f"topics: {owner[topic]} and {role} both read {topic!r}; give each its own topic (--topics)")
            owner[topic] = role

    @classmethod
    def parse(cls, text: str | None) -> "TopicMap":
        """``lidar=/points_raw,CAM_FRONT=/camera/front/image/compressed,CAM_FRONT.info=/camera/front/info,tf=/tf``.

        Keys: ``lidar``, ``tf``, ``tf_static``, a camera name (its image topic) or ``<camera>.info`` (its CameraInfo).
        None: the defaults. An empty entry, a key given twice or two keys on one topic is a ValueError naming them.
        """
        if text is None:
            return cls()
        lidar, tf, tf_static = LIDAR_TOPIC, TF_TOPIC, TF_STATIC_TOPIC
        cameras: dict[str, str] = {}
        infos: dict[str, str] = {}
        seen: dict[str, str] = {}  # key -> its entry
        shown = text if len(text) <= 60 else text[:57] + "..."
        for k, item in enumerate(text.split(","), start=1):
            if not item.strip():  # "lidar=/a,,tf=/b" or "": a slip of the keyboard, not a request for the defaults
                raise ValueError(f"--topics entry {k} of {shown!r} is empty (a stray comma?)")
            key, sep, topic = item.strip().partition("=")
            key, topic = key.strip(), topic.strip()
            if not sep or not key or not topic.startswith("/"):
                raise ValueError(
                    f"--topics entry {item!r} must be KEY=/topic (KEY: lidar, tf, tf_static, a camera name or CAMERA.info)"
                )
            if key in seen:  # which of the two was meant? Refused rather than the last one silently taken
                raise ValueError(f"--topics names {key!r} twice: {seen[key]!r} and {item.strip()!r}; keep one")
            seen[key] = item.strip()
            if key == "lidar":
                lidar = topic
            elif key == "tf":
                tf = topic
            elif key == "tf_static":
                tf_static = topic
            elif key.endswith(".info"):
                infos[key[: -len(".info")]] = topic
            else:
                cameras[key] = topic
        parsed = cls(lidar, cameras, infos, tf, tf_static)
        parsed.check_distinct()
        return parsed
