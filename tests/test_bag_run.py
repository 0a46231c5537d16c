"""`streamdet-bag run` on an exported bag gives the detections of the dataset evaluation on the same scene, writes
them as ROS 2 topics per slice (read back with rosbags), and works on a bag with a car's own topic names."""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.bag.cli import main as bag_main
from streamdet.bag.run import RunConfig, run_bag
from streamdet.bag.source import BagSource, SourceConfig
from streamdet.bag.topics import TopicMap
from streamdet.bag.writer import BagWriter
from streamdet.core.boxes import pair_boxes
from streamdet.core.classes import CLASS_NAMES
from streamdet.data.nuscenes import NuScenesReader
from streamdet.evaluation.dataset_eval import OnnxSweepDetector
from streamdet.evaluation.results import results_to_boxes
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.ros.pointcloud2 import decode_pointcloud2, pointcloud2_message, split_cloud

rosbags_highlevel = pytest.importorskip("rosbags.highlevel")
rosbags_typesys = pytest.importorskip("rosbags.typesys")

ROOT = Path(__file__).resolve().parents[1]
N_SLICES = 8
RENAMED = {
    "/LIDAR_TOP": "/sensing/lidar/top/pointcloud_raw",
    "/CAM_FRONT/image_rect_compressed": "/camera/front/image/compressed",
    "/CAM_FRONT/camera_info": "/camera/front/camera_info",
    "/tf": "/tf_car",
}


@pytest.fixture(scope="module")
def export_dir(tiny_export: Path) -> Path:
    return tiny_export  # 8 slices, shared read-only


@pytest.fixture(scope="module")
def bag(tiny_synth_data: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "drive.mcap"
    result = CliRunner().invoke(bag_main, ["export", "--data", str(tiny_synth_data), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def ran(bag: Path, export_dir: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "detections.mcap"
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), "--export-dir", str(export_dir), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "2 sweeps, 16 slices, 2 image sets" in result.output
    assert "sweeps detected: 2 done in " in result.stderr  # not a terminal: a count in lines (streamdet.progress)
    return out


@pytest.fixture(scope="module")
def reference(tiny_synth_data: Path, export_dir: Path) -> dict:
    """Each sample's detections by the dataset evaluation's detector, from the nuScenes tables."""
    reader = NuScenesReader(tiny_synth_data, "v1.0-synth")
    detect = OnnxSweepDetector(export_dir)
    return {t: (reader.get(t), detect(reader.get(t))) for t in reader.sample_tokens}


def read_with_rosbags(path: Path):
    typestore = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_HUMBLE)
    with rosbags_highlevel.AnyReader([path], default_typestore=typestore) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def assert_same_detections(results_path: Path, reference: dict) -> float:
    """Every detection of the bag run paired with one of the reference (same label, nearest centre): the same count,
    scores and boxes. Paired by position, not by sorting on score: an untrained model's near-equal scores may order
    two boxes differently once they went through the results JSON."""
    results = json.loads(results_path.read_text())["results"]
    assert set(results) == set(reference)
    worst = 0.0
    for token, (sample, dets) in reference.items():
        assert len(dets) > 0  # the comparison means something
        boxes, scores, labels = results_to_boxes(results[token], sample.lidar2ego, sample.ego2global)
        theirs = dets.boxes.astype(np.float64)
        assert len(boxes) == len(theirs)
        ia, ib, _ = pair_boxes(boxes, labels, theirs, dets.labels, radius_m=1e-3)
        assert len(ia) == len(boxes)  # every box has a partner within a millimetre
        np.testing.assert_allclose(scores[ia], dets.scores[ib], rtol=0, atol=1e-6)
        worst = max(worst, float(np.abs(boxes[ia, :7] - theirs[ib, :7]).max()))
    assert worst < 1e-4  # metres (and radians for yaw)
    return worst


def test_same_detections_as_the_dataset_evaluation(ran: Path, reference: dict):
    assert_same_detections(ran.with_name("detections.results_nusc.json"), reference)


def test_output_bag_holds_the_inputs_and_the_detections_per_slice(bag: Path, ran: Path, reference: dict):
    inputs = read_with_rosbags(bag)
    outputs = read_with_rosbags(ran)
    count = lambda msgs, topic: sum(1 for m in msgs if m[0] == topic)  # noqa: E731
    for topic in {m[0] for m in inputs}:
        assert count(outputs, topic) == count(inputs, topic), topic
    detections = [(t, m) for topic, msgtype, t, m in outputs if topic == "/streamdet/detections"]
    markers = [m for topic, _, _, m in outputs if topic == "/streamdet/markers"]
    assert len(detections) == len(markers) == 2 * N_SLICES
    assert {msgtype for topic, msgtype, _, _ in outputs if topic == "/streamdet/detections"} == {"vision_msgs/msg/Detection3DArray"}
    clouds = [m for topic, _, _, m in inputs if topic == "/LIDAR_TOP"]
    layout = BagSource(bag, SourceConfig()).scan_layout()  # the run slices as the clouds' times show the LiDAR turns
    expected_stamps = [s.scan_time_ns for c in clouds
                       for s in split_cloud(decode_pointcloud2(c), N_SLICES, layout.start_deg, layout.clockwise)]  # fmt: skip
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in detections]
    assert stamps == expected_stamps  # each slice stamped with its scan time
    assert all(m.header.frame_id == "LIDAR_TOP" for _, m in detections)
    names = {r.hypothesis.class_id for _, m in detections for d in m.detections for r in d.results}
    assert names and names <= set(CLASS_NAMES)
    per_sweep = [sum(len(m.detections) for _, m in detections[k * N_SLICES : (k + 1) * N_SLICES]) for k in range(2)]
    merged = [len(d) for _, d in reference.values()]
    assert all(p >= m for p, m in zip(per_sweep, merged))  # the sweep NMS only removes boxes


def _copy(bag: Path, out: Path, topic_of) -> Path:
    """The bag with each message under ``topic_of(message)``, left out where that is None."""
    source = BagSource(bag, SourceConfig())
    with BagWriter(out) as writer:
        for name, data in source.metadata().items():
            writer.metadata(name, data)
        for msg in source.messages():
            topic = topic_of(msg)
            if topic is None:
                continue
            writer.schema(msg.datatype, msg.schema_text)
            writer.write(topic, msg.datatype, msg.message, msg.log_time_ns)
    return out


def _renamed_copy(bag: Path, out: Path) -> Path:
    """The bag with a car's own topic names (and the frames left as they are)."""
    return _copy(bag, out, lambda msg: RENAMED.get(msg.topic, msg.topic))


def test_a_bag_with_other_topic_names_through_topics(bag: Path, export_dir: Path, reference: dict, tmp_path):
    renamed = _renamed_copy(bag, tmp_path / "car.mcap")
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(renamed), "--export-dir", str(export_dir), "--out", str(tmp_path / "a.mcap")])
    assert result.exit_code != 0
    assert "has no message on the LiDAR topic '/LIDAR_TOP'" in result.output and "Traceback" not in result.output
    partial = "lidar=/sensing/lidar/top/pointcloud_raw,tf=/tf_car"  # CAM_FRONT left at its default name
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(renamed), "--export-dir", str(export_dir), "--out", str(tmp_path / "c.mcap"),
                                           "--topics", partial])  # fmt: skip
    assert result.exit_code == 0, result.output  # CAM_FRONT absent: no image, no CameraInfo, no rig from the bag
    assert "no CameraInfo for ['CAM_FRONT'] at some image sets" in result.output
    topics = "lidar=/sensing/lidar/top/pointcloud_raw,CAM_FRONT=/camera/front/image/compressed,tf=/tf_car"
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(renamed), "--export-dir", str(export_dir), "--out", str(tmp_path / "b.mcap"),
                                           "--topics", topics])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert_same_detections(tmp_path / "b.results_nusc.json", reference)


def test_run_errors_are_one_line(bag: Path, export_dir: Path, tmp_path):
    def run(*args: str) -> str:
        result = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), *args])
        assert result.exit_code != 0 and "Traceback" not in result.output
        return result.output

    assert "holds no manifest.json" in run("--export-dir", str(tmp_path), "--out", str(tmp_path / "x.mcap"))
    assert "must be KEY=/topic" in run("--export-dir", str(export_dir), "--out", str(tmp_path / "x.mcap"), "--topics", "lidar:/points")
    assert "is the input bag" in run("--export-dir", str(export_dir), "--out", str(bag))
    out = run("--export-dir", str(export_dir), "--out", str(tmp_path / "x.mcap"), "--global-frame", "odom")
    assert "no TF path from 'odom' to 'base_link'" in out


def test_a_bag_without_sample_tokens_keys_results_by_stamp(bag: Path, export_dir: Path, tmp_path):
    plain = tmp_path / "plain.mcap"
    source = BagSource(bag, SourceConfig())
    with BagWriter(plain) as writer:  # no streamdet metadata: a bag recorded on a car
        for msg in source.messages():
            writer.schema(msg.datatype, msg.schema_text)
            writer.write(msg.topic, msg.datatype, msg.message, msg.log_time_ns)
    summary = run_bag(plain, export_dir, tmp_path / "out.mcap", config=RunConfig(topics=TopicMap()))
    keys = list(json.loads(summary.results_json.read_text())["results"])
    assert len(keys) == 2 and all(k.startswith("LIDAR_TOP@") for k in keys)


def test_node_recipe_helpers(bag: Path, export_dir: Path):
    """The non-rclpy part of docs/ros2_node_example.py, on the bag's messages (rclpy itself is not installed)."""
    path = ROOT / "docs" / "ros2_node_example.py"
    compile(path.read_text(), str(path), "exec")
    spec = importlib.util.spec_from_file_location("ros2_node_example", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    detector = StreamingDetector(export_dir)
    messages = read_with_rosbags(bag)
    images = {t.split("/")[1]: m for t, _, _, m in messages if t.endswith("image_rect_compressed")}
    frames = example.CameraFrames()
    assert frames.update(detector) is None  # nothing yet
    for cam, m in images.items():
        frames.add(detector, cam, m)
    assert frames.update(detector).cameras_missing == () and frames.update(detector) is None  # nothing new since
    cloud = next(m for t, _, _, m in messages if t == "/LIDAR_TOP")
    cloud_s = cloud.header.stamp.sec + cloud.header.stamp.nanosec * 1e-9
    assert abs(detector.image_timestamp - cloud_s) < 1.0  # the images on the slices' clock, not time.monotonic()
    cam = next(iter(images))
    frames.add(detector, cam, images[cam])  # one camera's new frame: the update still gives every camera
    update = frames.update(detector)
    assert update.cameras_used == tuple(n for n in detector.camera_names if n in images) and update.cameras_missing == ()
    slices = example.detect_cloud(detector, cloud)
    assert len(slices) == N_SLICES
    with BagWriter(bag.with_name("node.mcap")) as writer:  # the dicts are valid messages of their types
        for detections, markers in slices:
            writer.write("/d", "vision_msgs/msg/Detection3DArray", detections, 1)
            writer.write("/m", "visualization_msgs/msg/MarkerArray", markers, 1)
    assert sum(len(d["detections"]) for d, _ in slices) > 0
    # a camera that stops: left out once its image is older than the timeout against the cloud's stamp
    frames = example.CameraFrames(timeout_s=0.2)
    for c, m in images.items():
        frames.add(detector, c, m)
    stamp = max(frames.stamps_s.values())
    assert frames.update(detector, stamp + 0.1).cameras_missing == ()
    for c in list(images)[1:]:  # every camera but the first sends again, 0.25 s later
        later = copy.deepcopy(images[c])
        later.header.stamp.nanosec += 250_000_000
        frames.add(detector, c, later)
    cam0 = list(images)[0]
    update = frames.update(detector, stamp + 0.3)
    assert cam0 not in update.cameras_used and cam0 in update.cameras_missing
    assert frames.update(detector, stamp + 0.9) is None  # the others: 0.25 s apart, so out after three periods
    assert frames.update(detector, stamp + 1.05) is None and detector.image_state is None  # every camera out: dropped
    lag = example.CameraFrames(timeout_s=0.2)  # a camera that sends, stamped 5 s behind the cloud
    lag.add(detector, cam0, images[cam0])
    assert lag.update(detector, stamp + 5.0) is None and lag.lagging == {cam0}
    with pytest.raises(ValueError, match="timeout_s must be None or a finite number of seconds > 0"):
        example.CameraFrames(timeout_s=0)
    with pytest.raises(ImportError):
        example.main()  # no rclpy here


def _rerecord(bag: Path, out: Path, edit) -> Path:
    """``bag`` written again to ``out``: each message as ``edit(msg)`` says, a list of (message, log time ns) to write
    in its place (none: dropped)."""
    source = BagSource(bag, SourceConfig())
    with BagWriter(out) as writer:
        for name, data in source.metadata().items():
            writer.metadata(name, data)
        for msg in source.messages():
            writer.schema(msg.datatype, msg.schema_text)
            for message, log_time_ns in edit(msg):
                writer.write(msg.topic, msg.datatype, message, log_time_ns)
    return out


def _sliced_bag(bag: Path, sliced: Path, empty: tuple[int, ...] = ()) -> Path:
    """``bag`` with each sweep re-recorded as N_SLICES messages of one sector each, in the order its LiDAR scans them
    (the layout its per-point times show), each stamped like its sweep (the sample token's key); the sectors in
    ``empty`` as messages without points."""
    from streamdet.core.scan_layout import layout_from_times
    from streamdet.core.sectors import slice_index_of
    from streamdet.runtime_ort.ros.pointcloud2 import pointcloud2_message

    def edit(msg):
        if msg.topic != "/LIDAR_TOP":
            return [(msg.message, msg.log_time_ns)]
        cloud = decode_pointcloud2(msg.message)
        layout = layout_from_times(cloud.points, cloud.time_s)
        k_of = slice_index_of(cloud.points[:, 0], cloud.points[:, 1], N_SLICES, layout.start_deg, layout.clockwise)
        parts = [(k_of == k) & (k not in empty) for k in range(N_SLICES)]
        return [(pointcloud2_message(cloud.points[part], cloud.stamp_ns, cloud.frame_id, cloud.time_s[part].astype(np.float32)),
                 msg.log_time_ns + k) for k, part in enumerate(parts)]  # fmt: skip

    return _rerecord(bag, sliced, edit)


def test_a_driver_publishing_slices(bag: Path, export_dir: Path, reference: dict, tmp_path):
    """Each sweep re-recorded as 8 messages of one sector each: --slice-per-message gives the same detections."""
    sliced = _sliced_bag(bag, tmp_path / "sliced.mcap")
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(sliced), "--export-dir", str(export_dir), "--out",
                                           str(tmp_path / "det.mcap"), "--slice-per-message"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "2 sweeps, 16 slices" in result.output
    assert_same_detections(tmp_path / "det.results_nusc.json", reference)


@pytest.mark.parametrize("empty", [(3,), (N_SLICES - 1,), (0, N_SLICES - 1)])
def test_empty_slice_messages_are_skipped_and_every_sweep_still_closes(bag: Path, export_dir: Path, tmp_path, empty):
    """A slicing driver's message with no points (nothing returned in its sector) names no slice: it is skipped, and
    a sweep whose last slice was such a message closes when the next rotation begins, or when the bag ends."""
    sliced = _sliced_bag(bag, tmp_path / "sliced.mcap", empty)
    # a bag whose first slice message is empty shows where its second one began, not where the sweep starts: said
    start = ["--scan-start-deg", "180"] if 0 in empty else []
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(sliced), "--export-dir", str(export_dir), "--out",
                                           str(tmp_path / "det.mcap"), "--slice-per-message", *start])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"2 sweeps, {2 * (N_SLICES - len(empty))} slices" in result.output
    assert len(json.loads((tmp_path / "det.results_nusc.json").read_text())["results"]) == 2


def test_every_option_has_help():
    import click

    for name, command in bag_main.commands.items():
        for param in command.params:
            if isinstance(param, click.Option):
                assert param.help, f"streamdet-bag {name} {param.opts[0]} has no help text"
        result = CliRunner().invoke(bag_main, [name, "--help"])
        assert result.exit_code == 0 and "Usage:" in result.output
    assert set(bag_main.commands) == {"export", "run", "calibration"}


def test_channels_in_other_encodings_are_skipped(bag: Path, tmp_path, caplog):
    """A Foxglove JSON (or protobuf) topic beside the ROS 2 ones: skipped with a warning, the rest read."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    mixed = tmp_path / "mixed.mcap"
    with open(bag, "rb") as src, open(mixed, "wb") as dst:
        writer = Writer(dst)
        writer.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in make_reader(src).iter_messages(log_time_order=True):  # a raw copy
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        events = writer.register_channel("/events", "json", writer.register_schema("Event", "jsonschema", b"{}"))
        writer.add_message(events, 0, json.dumps({"sample": "x"}).encode(), 0)
        writer.finish()
    with caplog.at_level("WARNING", logger="streamdet.bag.source"):
        topics = [m.topic for m in BagSource(mixed, SourceConfig()).messages()]
    assert "/events" not in topics and topics == [m.topic for m in BagSource(bag, SourceConfig()).messages()]
    assert "topic /events is json, not ROS 2 CDR: skipped" in caplog.text


def _copy_without_cameras(bag: Path, out: Path) -> Path:
    """The bag with every camera message left out (the cameras died before the drive)."""
    return _copy(bag, out, lambda msg: None if msg.datatype.endswith(("/CompressedImage", "/CameraInfo")) else msg.topic)


def test_the_lidar_only_fallback_runs_the_slices_it_should(bag: Path, export_dir: Path, tiny_lidar_export: Path, tmp_path):
    """--fallback-export: with images in every sweep no slice falls back; with every camera gone every slice does,
    and the detections are the LiDAR-only export's own."""
    base = ["run", "--export-dir", str(export_dir), "--fallback-export", str(tiny_lidar_export)]
    res = CliRunner().invoke(bag_main, [*base, "--bag", str(bag), "--out", str(tmp_path / "a.mcap")])
    assert res.exit_code == 0, res.output
    assert "0 of 16 slices ran the LiDAR-only fallback" in res.output

    dark = _copy_without_cameras(bag, tmp_path / "dark.mcap")
    res = CliRunner().invoke(bag_main, [*base, "--bag", str(dark), "--fallback-after-ms", "500", "--out", str(tmp_path / "b.mcap"),
                                        "--results", str(tmp_path / "b.json")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "16 of 16 slices ran the LiDAR-only fallback" in res.output and "older than 500 ms" in res.output
    lidar = run_bag(dark, tiny_lidar_export, tmp_path / "c.mcap", tmp_path / "c.json")
    ours = json.loads((tmp_path / "b.json").read_text())["results"]
    theirs = json.loads(lidar.results_json.read_text())["results"]
    assert ours.keys() == theirs.keys() and sum(map(len, ours.values())) > 0
    for token in ours:  # the same boxes and scores (both runs write the same JSON from the same graph)
        assert [d["detection_score"] for d in ours[token]] == [d["detection_score"] for d in theirs[token]]

    res = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), "--export-dir", str(export_dir), "--fallback-after-ms", "50",
                                        "--out", str(tmp_path / "e.mcap")])  # fmt: skip
    assert res.exit_code != 0 and "Traceback" not in res.output  # an age without a fallback export is refused


def test_run_on_a_truncated_bag_is_one_line_naming_it(bag: Path, export_dir: Path, tmp_path):
    data = bag.read_bytes()
    for name, payload in (("cut20", data[:20]), ("half", data[: len(data) // 2])):
        bad = tmp_path / f"{name}.mcap"
        bad.write_bytes(payload)
        result = CliRunner().invoke(bag_main, ["run", "--bag", str(bad), "--export-dir", str(export_dir), "--out", str(tmp_path / "x.mcap")])
        assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
        assert f"{bad}: not a readable MCAP bag (truncated or corrupted): " in result.output
        assert len(result.output.strip().splitlines()) == 1


def test_an_absurd_point_time_is_dropped_not_a_writer_crash(export_dir: Path, tmp_path):
    """A cloud with one finite but absurd per-point time (1e20 s): that point is dropped, the slices keep the scan
    times of the others, and every detection is stamped as before (it used to end in struct.error in the writer)."""
    from streamdet.runtime_ort.ros.pointcloud2 import pointcloud2_message

    rng = np.random.default_rng(0)
    points = np.zeros((3000, 5), np.float32)
    points[:, :3] = rng.uniform(-40, 40, (3000, 3))
    points[:, 2] = rng.uniform(-2, 2, 3000)
    times = np.linspace(-0.05, 0.0, 3000).astype(np.float32)
    times[0] = 1e20
    stamp = 1_700_000_000_000_000_000
    path = tmp_path / "time.mcap"
    with BagWriter(path) as writer:
        writer.write("/LIDAR_TOP", "sensor_msgs/msg/PointCloud2", pointcloud2_message(points, stamp, "LIDAR_TOP", times), stamp)
    config = RunConfig(ego_frame="LIDAR_TOP", global_frame=None)
    summary = run_bag(path, export_dir, tmp_path / "out.mcap", config=config)
    assert summary.num_sweeps == 1 and summary.num_slices == N_SLICES
    stamps = [m.header.stamp for t, _, _, m in read_with_rosbags(summary.bag_out) if t == "/streamdet/detections"]
    assert len(stamps) == N_SLICES
    assert all(abs(s.sec * 10**9 + s.nanosec - stamp) <= 50_000_000 for s in stamps)


# ---- a camera that stops sending (SourceConfig.camera_timeout_s, --camera-timeout-ms) --------------------------------
def _bag_dropping(bag: Path, out: Path, cameras: tuple[str, ...]) -> Path:
    """``bag`` re-recorded without the images of ``cameras`` after its first LiDAR message (they stop sending)."""
    seen_lidar = [False]

    def edit(msg):
        seen_lidar[0] |= msg.topic == "/LIDAR_TOP"
        stopped = seen_lidar[0] and any(msg.topic == f"/{c}/image_rect_compressed" for c in cameras)
        return [] if stopped else [(msg.message, msg.log_time_ns)]

    return _rerecord(bag, out, edit)


@pytest.mark.parametrize("timeout_s", [0.2, None, 1.0])
def test_a_camera_that_stops_is_left_out_of_the_image_sets(bag: Path, export_dir: Path, tmp_path, timeout_s):
    """The bag's sweeps are 0.5 s apart: under a 0.2 s timeout CAM_BACK's first image is not in the second set; with
    none, or one longer than the gap, its old image still is."""
    dropped = _bag_dropping(bag, tmp_path / "dropped.mcap", ("CAM_BACK",))
    names = StreamingDetector(export_dir).camera_names
    source = BagSource(dropped, SourceConfig(camera_names=names, camera_timeout_s=timeout_s))
    sets = [event.image_set for event in source.sweeps()]
    assert len(sets) == 2 and set(sets[0].images) == set(names)
    left_out = timeout_s is not None and timeout_s < 0.5
    assert ("CAM_BACK" in sets[1].images) is not left_out
    assert source.cameras_timed_out == ({"CAM_BACK": 1} if left_out else {})


def test_every_camera_stopping_drops_the_image_bev(bag: Path, export_dir: Path, tmp_path):
    names = StreamingDetector(export_dir).camera_names
    dropped = _bag_dropping(bag, tmp_path / "dropped.mcap", names)
    sets = [event.image_set for event in BagSource(dropped, SourceConfig(camera_names=names, camera_timeout_s=0.2)).sweeps()]
    assert sets[1] is not None and sets[1].images == {} and sets[1].stamp_ns is None and sets[1].rig is None
    out = tmp_path / "det.mcap"
    summary = run_bag(dropped, export_dir, out, config=RunConfig(camera_timeout_s=0.2))
    assert summary.num_sweeps == 2 and summary.cameras_timed_out == {n: 1 for n in names}


@pytest.mark.parametrize("ms, said", [("200", True), ("0", False)])
def test_run_says_which_cameras_it_left_out(bag: Path, export_dir: Path, tmp_path, ms, said):
    dropped = _bag_dropping(bag, tmp_path / "dropped.mcap", ("CAM_BACK", "CAM_FRONT"))
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(dropped), "--export-dir", str(export_dir), "--out",
                                           str(tmp_path / "det.mcap"), "--camera-timeout-ms", ms])  # fmt: skip
    assert result.exit_code == 0, result.output
    line = "stopped sending for --camera-timeout-ms and were left out (their features zeros): CAM_FRONT 1x, CAM_BACK 1x"
    assert (line in result.output) is said


@pytest.mark.parametrize("bad", ["-1", "nan", "1e9"])
def test_run_refuses_a_bad_camera_timeout(bag: Path, export_dir: Path, tmp_path, bad):
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), "--export-dir", str(export_dir), "--out",
                                           str(tmp_path / "det.mcap"), "--camera-timeout-ms", bad])  # fmt: skip
    assert result.exit_code == 2 and "--camera-timeout-ms" in result.output


def _bag_lagging(bag: Path, out: Path, camera: str, behind_s: float) -> Path:
    """``bag`` with ``camera``'s images stamped ``behind_s`` earlier (its clock behind the LiDAR's)."""

    def edit(msg):
        if msg.topic == f"/{camera}/image_rect_compressed":
            msg.message.header.stamp.sec -= int(behind_s)  # decoded afresh for this loop: its own copy
        return [(msg.message, msg.log_time_ns)]

    return _rerecord(bag, out, edit)


def test_a_camera_on_another_clock_is_named(bag: Path, export_dir: Path, tmp_path, caplog):
    lagging = _bag_lagging(bag, tmp_path / "lagging.mcap", "CAM_BACK", 5)
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(lagging), "--export-dir", str(export_dir), "--out",
                                           str(tmp_path / "det.mcap")])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "['CAM_BACK'] sent images stamped more than --camera-timeout-ms behind the LiDAR's" in result.output
    assert "CAM_BACK 2x" in result.output  # at both sweeps: each set without it


def test_run_slices_in_the_layout_the_bag_s_times_show(bag: Path, export_dir: Path, tmp_path, caplog):
    """The synthetic drive's clouds (world 6) and the real nuScenes sweep's (exported with the times of its LiDAR) turn
    clockwise from 180 deg, a bag of world 5 counter-clockwise from 0: run reads the layout from the times, and warns
    where the flags given contradict them (ROS review H3: a clockwise bag split 19 sweeps into 133 without a word)."""
    synth = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), "--export-dir", str(export_dir), "--out",
                                          str(tmp_path / "a.mcap")])  # fmt: skip
    assert synth.exit_code == 0, synth.output
    assert "LiDAR scan layout: clockwise from 180 deg (from the per-point times of /LIDAR_TOP)" in synth.output
    # world 5's sensor: the same clouds mirrored about the x axis turn counter-clockwise from 180 (y -> -y)
    source = BagSource(bag, SourceConfig())
    mirrored = tmp_path / "mirrored.mcap"
    with BagWriter(mirrored) as writer:
        for msg in source.messages():
            writer.schema(msg.datatype, msg.schema_text)
            if msg.topic == "/LIDAR_TOP":
                cloud = decode_pointcloud2(msg.message)
                points = cloud.points.copy()
                points[:, 1] *= -1
                writer.write(msg.topic, msg.datatype, pointcloud2_message(points, cloud.stamp_ns, cloud.frame_id,
                                                                          cloud.time_s.astype(np.float32)), msg.log_time_ns)  # fmt: skip
            else:
                writer.write(msg.topic, msg.datatype, msg.message, msg.log_time_ns)
    assert BagSource(mirrored, SourceConfig()).scan_layout().clockwise is False
    real = tmp_path / "real.mcap"
    assert CliRunner().invoke(bag_main, ["export", "--out", str(real)]).exit_code == 0
    found = CliRunner().invoke(bag_main, ["run", "--bag", str(real), "--export-dir", str(export_dir), "--out",
                                          str(tmp_path / "b.mcap")])  # fmt: skip
    assert found.exit_code == 0, found.output
    assert "LiDAR scan layout: clockwise from 180 deg (from the per-point times of /LIDAR_TOP)" in found.output
    with caplog.at_level("WARNING", logger="streamdet.bag.run"):
        given = CliRunner().invoke(bag_main, ["run", "--bag", str(real), "--export-dir", str(export_dir), "--out",
                                              str(tmp_path / "c.mcap"), "--counter-clockwise"])  # fmt: skip
    assert given.exit_code == 0, given.output
    assert "counter-clockwise from 180 deg (partly given" in given.output
    assert any("but the clouds' per-point times show" in r.getMessage() for r in caplog.records)


def test_run_copies_the_recorded_channels_qos(bag: Path, export_dir: Path, tmp_path):
    """A recorded channel's metadata (rosbag2's offered_qos_profiles: /tf_static transient-local) reaches the output,
    so `ros2 bag play` of it latches /tf_static again (ROS review M5: it was dropped)."""
    from mcap.reader import make_reader

    qos = "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
    source = BagSource(bag, SourceConfig())
    recorded = tmp_path / "recorded.mcap"
    with BagWriter(recorded) as writer:
        for name, data in source.metadata().items():
            writer.metadata(name, data)
        for msg in source.messages():
            writer.schema(msg.datatype, msg.schema_text)
            extra = {"offered_qos_profiles": qos} if msg.topic == "/tf_static" else None
            writer.write(msg.topic, msg.datatype, msg.message, msg.log_time_ns, extra)
    out = tmp_path / "det.mcap"
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(recorded), "--export-dir", str(export_dir), "--out", str(out)])
    assert result.exit_code == 0, result.output
    with open(out, "rb") as f:
        channels = {c.topic: dict(c.metadata) for c in make_reader(f).get_summary().channels.values()}
    assert channels["/tf_static"] == {"offered_qos_profiles": qos}
    assert channels["/LIDAR_TOP"] == {}
