"""A bag's camera rig as calibration.json: CameraInfo + TF of a recording, for ``streamdet-calib lut`` or
``StreamingDetector.set_calibration``, so an export runs with the car's own calibration."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

from streamdet.bag.source import BagSource, SourceConfig
from streamdet.bag.topics import EGO_FRAME, GLOBAL_FRAME, TopicMap
from streamdet.calibration.camera import Rig
from streamdet.core.file_output import atomic_write_file
from streamdet.data.nuscenes import CAMERA_CHANNELS
from streamdet.runtime_ort.ros.pointcloud2 import CloudFields


def bag_cameras(source: BagSource, topics: TopicMap) -> tuple[str, ...]:
    """The nuScenes cameras whose image topic (as ``topics`` maps it) the bag holds, in nuScenes order, then the
    other cameras ``topics`` names. A camera ``topics`` maps whose topic the bag lacks is a ValueError
    (``check_mapped_cameras``), not a camera quietly left out of the rig."""
    present = source.topics()
    check_mapped_cameras(source, topics, topics.cameras, present)
    known = [c for c in CAMERA_CHANNELS if topics.image_topic(c) in present]
    return tuple(known + [c for c in topics.cameras if c not in CAMERA_CHANNELS])


def check_mapped_cameras(source: BagSource, topics: TopicMap, cameras: Sequence[str],
                         present: dict[str, str] | None = None) -> None:  # fmt: skip
    """ValueError naming the topic and listing the bag's topics when a camera of ``cameras`` that ``topics`` maps
    explicitly (``--topics CAM=/topic``) has no such topic in the bag: the user named it, so a typo there must not
    become a rig without that camera (a default topic that is absent only means the bag has no such camera).
    ``present``: ``source.topics()``, where the caller has it."""
    mapped = [c for c in cameras if c in topics.cameras]
    if not mapped:
        return
    present = source.topics() if present is None else present
    for camera in mapped:
        if topics.cameras[camera] not in present:
            raise ValueError(f"{source.path} has no message on the image topic {topics.cameras[camera]!r} that --topics "
                             f"names for {camera}; its topics: {present}")  # fmt: skip


def rig_from_bag(
    path: str | Path, topics: TopicMap = TopicMap(), cameras: Sequence[str] | None = None, ego_frame: str = EGO_FRAME,
    global_frame: str | None = GLOBAL_FRAME,
) -> tuple[Rig, int]:  # fmt: skip
    """The rig at the first LiDAR message by which every camera has sent an image and a CameraInfo, and that
    message's stamp (ns). Its lidar2cam holds the ego motion of that moment, as a nuScenes sample's does."""
    probe = BagSource(path, SourceConfig(topics=topics))
    names = tuple(cameras) if cameras else bag_cameras(probe, topics)
    if not names:
        raise ValueError(f"{probe.path} holds no camera image topic of {list(CAMERA_CHANNELS)}; name the cameras with --topics")
    config = SourceConfig(topics=topics, camera_names=names, ego_frame=ego_frame, global_frame=global_frame,
                          cloud_fields=CloudFields(require_time=False))  # fmt: skip
    for event in BagSource(path, config).sweeps():
        image_set = event.image_set
        if image_set is not None and image_set.rig is not None and set(image_set.images) == set(names):
            return image_set.rig, event.cloud.stamp_ns
    check_mapped_cameras(probe, topics, names)  # --cameras naming one: why it never sent, more precisely than below
    infos = [topics.camera_info_topic(c) for c in names]
    raise ValueError(f"{probe.path}: no LiDAR message comes after an image and a CameraInfo of every camera {list(names)} "
                     f"(CameraInfo topics {infos})")  # fmt: skip


def write_calibration_json(rig: Rig, out: str | Path, note: str = "") -> Path:
    """``rig`` in the calibration.json format ``Rig.from_calibration_json`` reads, written atomically."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {**rig.to_dict(), "source": note} if note else rig.to_dict()
    text = json.dumps(doc, indent=1).encode()
    # a fresh mkstemp name beside ``out``: a fixed ``out.tmp`` would be opened through whatever already sits there (a
    # symlink to any file, the input bag included, which it then overwrote)
    return atomic_write_file(out, lambda f: f.write(text))
