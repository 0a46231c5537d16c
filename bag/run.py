"""``streamdet-bag run``: a bag's LiDAR and cameras through ``StreamingDetector`` in recorded order, detections
written back as ROS 2 topics beside the input ones, and the nuScenes results JSON as ``streamdet-run`` writes it.

For every LiDAR message: the new image set (if any) goes through the image lane first, with the rig built from
the bag's CameraInfo and TF when it differs from the LUT in use (as the dataset evaluation does per sample);
then each slice through the slice lane, published as ``/streamdet/detections`` (vision_msgs/Detection3DArray) and
``/streamdet/markers`` (visualization_msgs/MarkerArray) stamped with the slice's scan time; then the sweep's
slices merged with per-class NMS (``aggregate_sweep``) make the sweep's results entry. A LiDAR message stamped at or
before one already read is not detected (``BagSource.events()``; counted in the summary), and no sweep's entry ever
replaces another's: a results key taken twice keeps the first, counted. Every input message is
copied into the output bag unchanged, but for those on the topics this run writes (``OUTPUT_TOPICS``: a bag that
``streamdet-bag run`` wrote before): they are dropped, with a warning, so that the output holds this run's
detections only, not two runs' mixed on one topic.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from streamdet.bag import topics as T
from streamdet.bag.calibration import check_mapped_cameras
from streamdet.bag.source import BagSource, SourceConfig, SweepEvent
from streamdet.bag.writer import BagWriter
from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S
from streamdet.core.scan_layout import ScanLayout, check_layout, choose_layout
from streamdet.core.image_header import decoder_error_reason
from streamdet.evaluation.results import boxes_to_results, write_results_json
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.postprocess import Detections, aggregate_sweep
from streamdet.runtime_ort.ros.detections import detection3d_array_message, marker_array_message
from streamdet.runtime_ort.ros.pointcloud2 import CloudFields, TimedSlice

log = logging.getLogger(__name__)

# The layout where the bag's clouds have no per-point times and none is given: the runtime's default (a driver that
# publishes no times gives nothing to read the direction from; --scan-start-deg / --clockwise say it).
NO_TIMES_LAYOUT = ScanLayout(0.0, False, "the runtime's default: the clouds have no per-point times")
RESULTS_SUFFIX = ".results_nusc.json"  # the default results JSON: the output bag's name with this suffix
OUTPUT_TOPICS = (T.DETECTIONS_TOPIC, T.DETECTION_MARKERS_TOPIC)  # what a run writes; the input's are not copied


@dataclass(frozen=True)
class RunConfig:
    topics: T.TopicMap = field(default_factory=T.TopicMap)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    slice_per_message: bool = False  # the driver publishes slices; default: one message is a full sweep
    cloud_fields: CloudFields = field(default_factory=lambda: CloudFields(require_time=False))
    ego_frame: str = T.EGO_FRAME
    global_frame: str | None = T.GLOBAL_FRAME
    camera_timeout_s: float | None = DEFAULT_CAMERA_TIMEOUT_S  # SourceConfig.camera_timeout_s
    marker_lifetime_s: float = 0.0  # 0: a slice's boxes stay until the same slice of the next sweep replaces them
    # The LiDAR's scan layout (core/sectors.py), which replaces the detector config's: where its sweep starts and
    # whether it turns clockwise; None: from the bag's per-point times (BagSource.scan_layout), else NO_TIMES_LAYOUT
    start_deg: float | None = None
    clockwise: bool | None = None

    def __post_init__(self) -> None:
        start_deg, clockwise = check_layout(self.start_deg, self.clockwise)
        object.__setattr__(self, "start_deg", start_deg)  # Python numbers, as the CLI gives them
        object.__setattr__(self, "clockwise", clockwise)


@dataclass(frozen=True)
class RunSummary:
    bag_out: Path
    results_json: Path
    num_sweeps: int
    num_slices: int
    num_image_sets: int
    num_detections: int  # over all sweeps, after the sweep NMS
    cameras: tuple[str, ...]
    cameras_without_info: tuple[str, ...]  # their CameraInfo was missing for some image set (calibration kept)
    precision: str
    latency_ms: dict
    num_fallback_slices: int = 0  # slices the LiDAR-only fallback ran (DetectorConfig.fallback_export_dir)
    providers: tuple[str, ...] = ()  # onnxruntime's execution providers of the slice session
    cameras_timed_out: dict[str, int] = field(default_factory=dict)  # camera -> times it was left out (camera timeout)
    cameras_lagging: tuple[str, ...] = ()  # of those, cameras left out although they were sending (another clock?)
    input_dropped: dict[str, int] = field(default_factory=dict)  # topic of OUTPUT_TOPICS -> input messages not copied
    scan_layout: str = ""  # the layout the clouds were sliced with, and what said so (ScanLayout.describe)
    # LiDAR messages not detected for their header stamp (BagSource.events()), copied to the output as recorded:
    num_clouds_repeated: int = 0  # stamped as one already read (republished, recorded twice)
    num_clouds_behind: int = 0  # stamped before one already read (a clock step back, a reordered recording)
    # sweeps whose results key (sample token, or frame@stamp) an earlier sweep had: left out of the results JSON
    num_duplicate_keys: int = 0


def run_bag(
    bag: str | Path, export_dir: str | Path, out: str | Path, results_json: str | Path | None = None,
    config: RunConfig = RunConfig(), progress: Callable[[int], None] | None = None,
) -> RunSummary:  # fmt: skip
    """Detect every LiDAR message of ``bag`` with the export in ``export_dir``; write ``out`` (.mcap) and the
    results JSON (default: beside ``out``). ``progress(n)`` after each sweep."""
    out = Path(out)
    results_path = results_path_of(out, results_json)
    if results_path.resolve() == out.resolve():  # the JSON, written last, would replace the detections bag
        raise ValueError(f"the results JSON {results_path} is the output bag; write it to another file")
    layout = scan_layout_of(bag, config)
    log.info("%s: %s", bag, layout.describe())
    det = StreamingDetector(export_dir, replace(config.detector, start_deg=layout.start_deg, clockwise=layout.clockwise))
    source = BagSource(bag, SourceConfig(
        topics=config.topics, camera_names=det.camera_names if det.uses_images else (), num_slices=det.num_slices,
        start_deg=det.config.start_deg, clockwise=det.config.clockwise, slice_per_message=config.slice_per_message, cloud_fields=config.cloud_fields,
        ego_frame=config.ego_frame, global_frame=config.global_frame, camera_timeout_s=config.camera_timeout_s,
    ))  # fmt: skip
    if Path(source.path).resolve() == out.resolve():
        raise ValueError(f"--out {out} is the input bag; write the detections to another file")
    if Path(source.path).resolve() == results_path.resolve():
        raise ValueError(f"the results JSON {results_path} is the input bag; write it to another file")
    # a camera --topics maps to a topic the bag lacks would never send: refused, not run as a camera without images
    check_mapped_cameras(source, config.topics, source.config.camera_names)
    # a key that is no camera of the export (a typo, another rig's name) would map nothing: refused, not ignored
    unknown = sorted((set(config.topics.cameras) | set(config.topics.camera_infos)) - set(source.config.camera_names))
    if unknown:
        raise ValueError(f"--topics names {unknown}, no camera of the export "
                         f"({list(source.config.camera_names) or 'LiDAR-only: it has none'})")
    earlier = [t for t in OUTPUT_TOPICS if t in source.topics()]
    if earlier:  # said before the work: the output is not the input plus detections, as the user may expect
        log.warning("%s already holds %s (a bag streamdet-bag run wrote?): those messages are not copied to %s, which "
                    "holds this run's detections only", source.path, ", ".join(earlier), out)  # fmt: skip
    dropped: dict[str, int] = {}
    keyed_by_tokens = bool(source.sample_tokens())
    results: dict[str, list[dict]] = {}
    shown: dict[int, int] = {}  # slice index -> boxes its markers showed last
    counts = {"sweeps": 0, "slices": 0, "image_sets": 0, "detections": 0, "fallback": 0, "duplicate_keys": 0}
    pending: list[Detections] = []  # slices of the sweep being assembled (slice-per-message drivers)
    last_event: list[SweepEvent] = []  # the event of the newest slice in ``pending``

    def finish_sweep(event: SweepEvent) -> None:
        """The slices in ``pending`` merged into one sweep's detections, keyed by ``event`` (its last slice's)."""
        merged = aggregate_sweep(pending, det.config.nms)
        pending.clear()
        counts["sweeps"] += 1
        counts["detections"] += len(merged)
        token = event.sample_token or f"{event.cloud.frame_id}@{event.cloud.stamp_ns}"
        # a bag written by `streamdet-bag export` keys its key frames by sample token; any other, every sweep
        keyed = event.sample_token is not None or not keyed_by_tokens
        if keyed and token in results:
            # BagSource takes no stamp twice, so this is two stamps the bag's metadata gives one sample token: the
            # first sweep's results stay, never replaced without a word
            counts["duplicate_keys"] += 1
            if counts["duplicate_keys"] == 1:
                log.warning("%s: the sweep at LiDAR stamp %d ns has the results key %s of an earlier sweep: left out of "
                            "the results JSON (the first kept); later ones are counted, not reported", bag,
                            event.cloud.stamp_ns, token)  # fmt: skip
        elif keyed:
            results[token] = boxes_to_results(token, merged.boxes.astype(np.float64), merged.scores, merged.labels,
                                              event.lidar2ego, event.ego2global)  # fmt: skip
        if progress is not None:
            progress(counts["sweeps"])

    with BagWriter(out) as writer:
        for message, event in source.events():
            if message.topic in OUTPUT_TOPICS:  # an earlier run's detections: mixed with this run's, neither is readable
                dropped[message.topic] = dropped.get(message.topic, 0) + 1
                continue
            writer.schema(message.datatype, message.schema_text)
            writer.write(message.topic, message.datatype, message.message, message.log_time_ns, message.channel_metadata)
            if event is None:
                continue
            if event.image_set is not None and det.uses_images:
                _feed_images(det, event)
                counts["image_sets"] += 1
            if not event.slices:  # an empty message of a slicing driver (nothing in its sector): nothing to detect
                continue
            if pending and event.slices[0].index <= last_event[0].slices[-1].index:
                # a new rotation began before the last one's final slice came (it was empty, or lost): close that one
                finish_sweep(last_event[0])
            for s in event.slices:
                result = det.detect_slice(s.points, s.index, timestamp=s.scan_time_ns * 1e-9, num_slices=s.num_slices)
                _publish(writer, result.detections, s, message.log_time_ns, shown.get(s.index, 0), config)
                shown[s.index] = len(result.detections)
                pending.append(result.detections)
                counts["slices"] += 1
                counts["fallback"] += result.fallback
            last_event[:] = [event]
            last = event.slices[-1]
            if last.index == last.num_slices - 1:  # the sweep is complete when its last slice has been detected
                finish_sweep(event)
        if pending:  # the bag ended within a rotation whose last slice never came
            finish_sweep(last_event[0])
    results_path.parent.mkdir(parents=True, exist_ok=True)
    write_results_json(results_path, results, {"use_camera": det.uses_images, "use_lidar": True})
    without = tuple(c for c in det.camera_names if c in source.cameras_without_info)
    return RunSummary(out, results_path, counts["sweeps"], counts["slices"], counts["image_sets"], counts["detections"],
                      det.camera_names, without, det.precision_label, det.stats.summary(), counts["fallback"],
                      tuple(det.providers), dict(source.cameras_timed_out),
                      tuple(c for c in det.camera_names if c in source.cameras_lagging), dropped, layout.describe(),
                      source.num_clouds_repeated, source.num_clouds_behind, counts["duplicate_keys"])  # fmt: skip


def scan_layout_of(bag: str | Path, config: RunConfig) -> ScanLayout:
    """The layout ``run_bag`` slices with: ``config.start_deg`` / ``clockwise`` where given, the rest from the bag's
    per-point times (a full-sweep cloud's; a driver's slice messages: the first ones together, the start being the
    axis nearest where the first began), else NO_TIMES_LAYOUT. Given values the times contradict are kept, with a
    warning."""
    # read even where both are given: a layout the data contradicts is said
    probe = BagSource(bag, SourceConfig(topics=config.topics, slice_per_message=config.slice_per_message,
                                        cloud_fields=config.cloud_fields))  # fmt: skip
    found = probe.scan_layout()
    layout = choose_layout(found, NO_TIMES_LAYOUT, config.start_deg, config.clockwise)
    if found is not None and (layout.start_deg, layout.clockwise) != (found.start_deg, found.clockwise):
        log.warning("%s: slicing %s as given, but the clouds' per-point times show %s: slices then arrive out of "
                    "their order (--scan-start-deg / --clockwise)", bag, layout.describe(), found.describe())  # fmt: skip
    return layout


def results_path_of(out: str | Path, results_json: str | Path | None) -> Path:
    """Where the results JSON goes: ``results_json``, or beside the output bag under its name (``det.mcap`` ->
    ``det.results_nusc.json``), so that runs into one folder keep their own."""
    return Path(results_json) if results_json is not None else Path(out).with_name(Path(out).stem + RESULTS_SUFFIX)


def _feed_images(det: StreamingDetector, event: SweepEvent) -> None:
    """The image set through the image lane at the export's image size, after recalibrating when its rig differs.

    An image whose size differs from its camera's CameraInfo is refused (the rig's K is for that size, so every
    projection would be wrong); so is any image OpenCV cannot resize: a ValueError naming the camera and stamp.
    """
    image_set = event.image_set
    if not image_set.images:  # every camera timed out: slices read no image (or the LiDAR-only fallback) until one sends
        det.forget_images()
        return
    if image_set.rig is not None:
        calibrated = {cam.name: (cam.width, cam.height) for cam in image_set.rig.cameras}
        for name, rgb in image_set.images.items():
            if name in calibrated and (rgb.shape[1], rgb.shape[0]) != calibrated[name]:
                w, h = calibrated[name]
                raise ValueError(f"camera {name}: image at stamp {image_set.stamps_ns.get(name)} ns is "
                                 f"{rgb.shape[1]}x{rgb.shape[0]} px but its CameraInfo is for {w}x{h}")  # fmt: skip
    if image_set.rig is not None and image_set.rig.sha256() != det.lut.calibration_sha256:
        det.set_calibration(image_set.rig)  # another rig than the LUT's: rebuild the LUT, same graphs
    size = (det.image.width, det.image.height)
    images = {name: _resized(rgb, size, name, image_set.stamps_ns.get(name)) for name, rgb in image_set.images.items()}
    det.update_images(images, timestamp=image_set.stamp_ns * 1e-9)


def _resized(rgb: np.ndarray, size: tuple[int, int], camera: str = "", stamp_ns: int | None = None) -> np.ndarray:
    """As ``data.sample.load_image`` resizes: area averaging. ValueError naming the camera for an image OpenCV
    cannot resize (no pixels, a failed allocation) rather than a cv2.error traceback."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"camera {camera}: image at stamp {stamp_ns} ns is {rgb.shape}, not a non-empty (H, W, 3) image")
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    try:
        return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    except cv2.error as e:
        raise ValueError(f"camera {camera}: image at stamp {stamp_ns} ns ({rgb.shape[1]}x{rgb.shape[0]} px) "
                         f"cannot be resized to {size[0]}x{size[1]}: {decoder_error_reason(e)}") from None  # fmt: skip


def _publish(
    writer: BagWriter, dets: Detections, s: TimedSlice, log_time_ns: int, shown_before: int, config: RunConfig
) -> None:
    """One slice's Detection3DArray and MarkerArray; the slice's markers of the previous sweep beyond today's
    count are deleted (each slice has its own marker namespace, so slices never delete each other's boxes)."""
    boxes = detection3d_array_message(dets.boxes, dets.scores, dets.labels, s.scan_time_ns, s.frame_id)
    writer.write(T.DETECTIONS_TOPIC, T.DETECTION3D_ARRAY, boxes, log_time_ns)
    markers = marker_array_message(dets.boxes, dets.labels, s.scan_time_ns, s.frame_id, scores=dets.scores,
                                   ns=f"streamdet/slice_{s.index}", lifetime_s=config.marker_lifetime_s,
                                   stale_ids=range(len(dets), shown_before))  # fmt: skip
    writer.write(T.DETECTION_MARKERS_TOPIC, T.MARKER_ARRAY, markers, log_time_ns)
