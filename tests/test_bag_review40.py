"""`streamdet-bag` on review 40's hostile bags (replay report M1, M2).

M1: every topic a role reads (the LiDAR, each camera's images and CameraInfo, /tf, /tf_static) is checked for its
message type before reading, as the LiDAR topic was: a topic mapped to the wrong role is one line naming the topic,
the type found and the one expected (exit 1, as the bag's other input errors), never an AttributeError from an
adapter; also in a bag whose summary lists no channel, where the type is only known message by message.

M2: a LiDAR message stamped at or before one already read (republished, recorded twice, a clock step back) is
skipped, counted and warned once, never detected again over an earlier sweep's results; a results key two sweeps
share keeps the first. `run` says both counts."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("mcap_ros2.writer")

from streamdet.bag import topics as T  # noqa: E402
from streamdet.bag.run import run_bag  # noqa: E402
from streamdet.bag.source import BagSource, SourceConfig  # noqa: E402
from streamdet.bag.writer import BagWriter  # noqa: E402
from streamdet.core.sectors import slice_index_of  # noqa: E402
from streamdet.runtime_ort.ros.camera_info import camera_info_message  # noqa: E402
from streamdet.runtime_ort.ros.images import compressed_image_message  # noqa: E402
from streamdet.runtime_ort.ros.pointcloud2 import pointcloud2_message  # noqa: E402
from streamdet.runtime_ort.ros.tf import transform_stamped_msg  # noqa: E402

# the bag CLI checks' own helpers and small-bag pieces
from test_bag_cli_outputs import NO_TF, STAMP_NS, SWEEP_NS, invoke, one_line_error, sweep_points  # noqa: E402

INFO_TOPIC = "/CAM_FRONT/camera_info"
IMAGE_TOPIC = "/CAM_FRONT/image_rect_compressed"


@pytest.fixture(scope="module")
def bag(tiny_synth_data: Path, tmp_path_factory) -> Path:
    """The tiny scene as `export` writes it: two key frames, six cameras, sample tokens in the metadata."""
    out = tmp_path_factory.mktemp("bag") / "drive.mcap"
    result = invoke("export", "--data", tiny_synth_data, "--out", out)
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def clean(bag: Path, tiny_export: Path, tmp_path_factory) -> dict:
    """The results of `run` on the bag as exported."""
    summary = run_bag(bag, tiny_export, tmp_path_factory.mktemp("clean") / "det.mcap")
    assert summary.num_sweeps == 2
    return json.loads(summary.results_json.read_text())["results"]


def copy_bag(bag: Path, out: Path, edit, metadata=lambda name, data: data) -> Path:
    """``bag`` written again to ``out``: each message as ``edit(msg)`` says, a list of (topic, its type, message, log
    time ns) to write in its place (none: dropped); each metadata record as ``metadata(name, data)`` says."""
    source = BagSource(bag, SourceConfig())
    with BagWriter(out) as writer:
        for name, data in source.metadata().items():
            writer.metadata(name, metadata(name, data))
        for msg in source.messages():
            for topic, datatype, message, log_time_ns in edit(msg):
                writer.schema(datatype, msg.schema_text)
                writer.write(topic, datatype, message, log_time_ns)
    return out


def unindexed(bag: Path, out: Path) -> Path:
    """``bag`` without indexes or a summary listing its channels (a writer that keeps none): its messages still read,
    but their types are only known as each one is read."""
    from mcap.reader import make_reader
    from mcap.writer import IndexType, Writer

    with open(bag, "rb") as src, open(out, "wb") as dst:
        writer = Writer(dst, index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
                        use_statistics=False, use_summary_offsets=False)  # fmt: skip
        writer.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in make_reader(src).iter_messages(log_time_order=True):  # a raw copy
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()
    assert BagSource(out, SourceConfig()).topics() == {}  # the up-front check sees nothing here
    return out


def assert_same_results(got: dict, expected: dict) -> None:
    assert list(got) == list(expected)
    for token, entries in got.items():
        assert len(entries) == len(expected[token])
        for a, b in zip(entries, expected[token]):
            np.testing.assert_allclose(a["translation"], b["translation"], atol=1e-6)
            assert a["detection_name"] == b["detection_name"]


# ---- M1: the message type of every mapped topic ------------------------------------------------------------------


def small_bag(path: Path, topic: str, datatype: str, message: dict) -> Path:
    """The camera's mounting, one cloud, a CAM_FRONT image and CameraInfo after it, then ``message`` on ``topic``
    (in place of the one of the right type there), then a second cloud."""
    image = cv2.imencode(".jpg", np.zeros((90, 160, 3), np.uint8))[1].tobytes()
    info = camera_info_message(np.array([[100.0, 0, 80], [0, 100.0, 45], [0, 0, 1]]), 160, 90, STAMP_NS, "CAM_FRONT")
    mount = transform_stamped_msg("LIDAR_TOP", "CAM_FRONT", {"rotation": [1.0, 0, 0, 0], "translation": [0.0, 0, 0]}, STAMP_NS)
    with BagWriter(path) as writer:
        if topic != T.TF_STATIC_TOPIC:
            writer.write(T.TF_STATIC_TOPIC, T.TF_MESSAGE, {"transforms": [mount]}, STAMP_NS - 1)
        writer.write(T.LIDAR_TOPIC, T.POINTCLOUD2, pointcloud2_message(sweep_points(), STAMP_NS, "LIDAR_TOP"), STAMP_NS)
        if topic != IMAGE_TOPIC:
            writer.write(IMAGE_TOPIC, T.COMPRESSED_IMAGE, compressed_image_message(image, STAMP_NS, "CAM_FRONT"), STAMP_NS + 1)
        if topic != INFO_TOPIC:
            writer.write(INFO_TOPIC, T.CAMERA_INFO, info, STAMP_NS + 2)
        writer.write(topic, datatype, message, STAMP_NS + 3)
        stamp = STAMP_NS + SWEEP_NS
        writer.write(T.LIDAR_TOPIC, T.POINTCLOUD2, pointcloud2_message(sweep_points(seed=1), stamp, "LIDAR_TOP"), stamp)
    return path


def _wrong(kind: str) -> tuple[str, dict]:
    image = compressed_image_message(b"\xff\xd8\xff", STAMP_NS, "CAM_FRONT")
    info = camera_info_message(np.eye(3), 16, 16, STAMP_NS, "CAM_FRONT")
    return {"cloud": (T.POINTCLOUD2, pointcloud2_message(sweep_points(10), STAMP_NS, "LIDAR_TOP")),
            "image": (T.COMPRESSED_IMAGE, image), "info": (T.CAMERA_INFO, info)}[kind]  # fmt: skip


# (topic, what is recorded on it, the role named, the type expected, the --topics key to fix it)
WRONG_TYPES = [
    (IMAGE_TOPIC, "cloud", "CAM_FRONT image", f"{T.COMPRESSED_IMAGE} or {T.IMAGE}", "CAM_FRONT"),
    (INFO_TOPIC, "image", "CAM_FRONT CameraInfo", T.CAMERA_INFO, "CAM_FRONT.info"),
    (T.TF_TOPIC, "info", "TF", T.TF_MESSAGE, "tf"),
    (T.TF_STATIC_TOPIC, "image", "static TF", T.TF_MESSAGE, "tf_static"),
]


@pytest.mark.parametrize("indexed", [True, False], ids=["summary", "no-summary"])
@pytest.mark.parametrize("topic, kind, what, expected, key", WRONG_TYPES, ids=[w[0] for w in WRONG_TYPES])
def test_a_mapped_topic_of_another_type_is_named(tmp_path: Path, topic, kind, what, expected, key, indexed):
    datatype, message = _wrong(kind)
    path = small_bag(tmp_path / "x.mcap", topic, datatype, message)
    if not indexed:
        path = unindexed(path, tmp_path / "unindexed.mcap")
    source = BagSource(path, SourceConfig(camera_names=("CAM_FRONT",), **NO_TF))
    with pytest.raises(ValueError) as info:
        list(source.sweeps())
    said = str(info.value)
    assert f"{path}: the {what} topic {topic!r} carries {datatype} messages, not {expected}" in said, said
    assert f"--topics {key}=/topic" in said and "\n" not in said
    assert ("topics in the bag:" in said) is indexed  # a bag without a summary lists none: no list rather than "[]"


def test_a_topic_of_the_right_type_reads(tmp_path: Path):
    path = small_bag(tmp_path / "x.mcap", "/other", T.CAMERA_INFO, _wrong("info")[1])
    events = list(BagSource(path, SourceConfig(camera_names=("CAM_FRONT",), **NO_TF)).sweeps())
    assert events[0].image_set is None and set(events[1].image_set.images) == {"CAM_FRONT"} and events[1].image_set.rig


SWAPPED = f"CAM_FRONT={INFO_TOPIC},CAM_FRONT.info={IMAGE_TOPIC}"  # the report's typo: image and info swapped


def test_calibration_with_image_and_info_topics_swapped(bag: Path, tmp_path: Path):
    result = invoke("calibration", "--bag", bag, "--out", tmp_path / "c.json", "--topics", SWAPPED)
    assert result.exit_code == 1
    line = one_line_error(result, "topic", "carries", "--topics CAM_FRONT")
    assert (f"the CAM_FRONT image topic '{INFO_TOPIC}' carries {T.CAMERA_INFO} messages" in line
            or f"the CAM_FRONT CameraInfo topic '{IMAGE_TOPIC}' carries {T.COMPRESSED_IMAGE} messages" in line), line  # fmt: skip
    assert not (tmp_path / "c.json").exists()


def _caminfo_on_tf(msg):
    if msg.topic == T.TF_TOPIC:
        return []
    topic = T.TF_TOPIC if msg.topic == INFO_TOPIC else msg.topic
    return [(topic, msg.datatype, msg.message, msg.log_time_ns)]


@pytest.mark.parametrize("case, says", [
    (("--topics", SWAPPED), "--topics CAM_FRONT"),
    (("--topics", f"lidar={IMAGE_TOPIC}"), f"the LiDAR topic '{IMAGE_TOPIC}' carries {T.COMPRESSED_IMAGE} messages, "
                                           f"not {T.POINTCLOUD2}"),  # read first to find the scan layout
    ("caminfo_on_tf", f"the TF topic '/tf' carries {T.CAMERA_INFO} messages, not {T.TF_MESSAGE}"),
], ids=["swapped", "lidar", "caminfo_on_tf"])  # fmt: skip
def test_run_names_a_topic_of_another_type(bag: Path, tiny_export: Path, tmp_path: Path, case, says):
    args: tuple = case
    if case == "caminfo_on_tf":
        bag, args = copy_bag(bag, tmp_path / "in.mcap", _caminfo_on_tf), ()
    result = invoke("run", "--bag", bag, "--export-dir", tiny_export, "--out", tmp_path / "det.mcap", *args)
    assert result.exit_code == 1
    one_line_error(result, says)
    assert not (tmp_path / "det.mcap").exists()


# ---- M2: repeated and out-of-order LiDAR stamps -------------------------------------------------------------------


def stamped_bag(path: Path, clouds: list[tuple[int, np.ndarray]]) -> Path:
    """One PointCloud2 per (header stamp, points), logged in this order 1 ms apart."""
    with BagWriter(path) as writer:
        for i, (stamp, points) in enumerate(clouds):
            writer.write(T.LIDAR_TOPIC, T.POINTCLOUD2, pointcloud2_message(points, stamp, "LIDAR_TOP"), STAMP_NS + i * 1_000_000)
    return path


def test_repeated_and_earlier_stamps_are_skipped_counted_and_warned_once(tmp_path: Path, caplog):
    order = [0, 1, 1, 1, 3, 2, 0, 4]  # in sweeps after STAMP_NS: two repeats of 1, then 2 and 0 after 3
    path = stamped_bag(tmp_path / "x.mcap", [(STAMP_NS + k * SWEEP_NS, sweep_points(500, i)) for i, k in enumerate(order)])
    source = BagSource(path, SourceConfig(**NO_TF))
    with caplog.at_level(logging.WARNING, logger="streamdet.bag.source"):
        pairs = list(source.events())
    assert len(pairs) == len(order)  # every message still yielded (run copies them all)
    assert [e.cloud.stamp_ns for _, e in pairs if e is not None] == [STAMP_NS + k * SWEEP_NS for k in (0, 1, 3, 4)]
    assert (source.num_clouds_repeated, source.num_clouds_behind) == (2, 2)
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 2, warned  # one per kind
    assert f"message at stamp {STAMP_NS + SWEEP_NS} ns" in warned[0] and "repeats the stamp of one already read" in warned[0]
    assert f"message at stamp {STAMP_NS + 2 * SWEEP_NS} ns" in warned[1] and "stamped 0.05 s before one already read" in warned[1]
    assert all("skipped, not detected" in w and "later ones are counted" in w for w in warned)


def test_a_slicing_driver_may_stamp_a_rotation_once_but_a_slice_sent_again_is_skipped(tmp_path: Path):
    n = 4
    points = sweep_points(4000)
    k_of = slice_index_of(points[:, 0], points[:, 1], n)
    slices = [points[k_of == k] for k in range(n)]
    first, second = STAMP_NS, STAMP_NS + SWEEP_NS
    clouds = [(first, slices[0]), (first, slices[1]), (first, slices[1]), (first, slices[2]), (first, slices[3]),
              (second, slices[0]), (first, slices[2]), (second, slices[1]), (second, slices[2]), (second, slices[3])]  # fmt: skip
    source = BagSource(stamped_bag(tmp_path / "x.mcap", clouds), SourceConfig(slice_per_message=True, num_slices=n, **NO_TF))
    taken = [(e.cloud.stamp_ns, e.slices[0].index) for e in source.sweeps()]
    assert taken == [(first, k) for k in range(n)] + [(second, k) for k in range(n)]
    assert (source.num_clouds_repeated, source.num_clouds_behind) == (1, 1)


def _duplicated(msg):
    """Every LiDAR message twice, the copy logged 1 ns later (a republished cloud)."""
    copies = 2 if msg.topic == T.LIDAR_TOPIC else 1
    return [(msg.topic, msg.datatype, msg.message, msg.log_time_ns + i) for i in range(copies)]


def test_run_detects_a_duplicated_cloud_once_and_says_so(bag: Path, tiny_export: Path, clean: dict, tmp_path: Path):
    dup = copy_bag(bag, tmp_path / "dup.mcap", _duplicated)
    out = tmp_path / "det.mcap"
    result = invoke("run", "--bag", dup, "--export-dir", tiny_export, "--out", out)
    assert result.exit_code == 0, result.output
    assert "2 sweeps, 16 slices, 2 image sets" in result.output  # the sweep count agrees with the results
    assert ("LiDAR messages not detected for their header stamp (copied to --out as recorded): 2 stamped as one "
            "already read (republished, recorded twice), 0 stamped before one already read") in result.output  # fmt: skip
    assert_same_results(json.loads(out.with_name("det.results_nusc.json").read_text())["results"], clean)
    copied = sum(1 for m in BagSource(out, SourceConfig()).messages() if m.topic == T.LIDAR_TOPIC)
    assert copied == 4  # the input's messages all copied, as recorded


def test_run_skips_a_cloud_stamped_before_the_previous_one(bag: Path, tiny_export: Path, clean: dict, tmp_path: Path):
    """The second cloud carries a stamp 1 ms before the first's: it is not detected, nothing replaces the first."""
    lidar = [m for m in BagSource(bag, SourceConfig()).messages() if m.topic == T.LIDAR_TOPIC]
    stamp = lidar[0].message.header.stamp
    sec, nanosec = divmod(stamp.sec * 1_000_000_000 + stamp.nanosec - 1_000_000, 1_000_000_000)

    def edit(msg):
        if msg.topic == T.LIDAR_TOPIC and msg.log_time_ns == lidar[1].log_time_ns:
            msg.message.header.stamp.sec, msg.message.header.stamp.nanosec = sec, nanosec  # decoded afresh: its own copy
        return [(msg.topic, msg.datatype, msg.message, msg.log_time_ns)]

    summary = run_bag(copy_bag(bag, tmp_path / "behind.mcap", edit), tiny_export, tmp_path / "det.mcap")
    assert summary.num_sweeps == 1  # the detector never ran back in time
    results = json.loads(summary.results_json.read_text())["results"]
    first_token = next(iter(clean))
    assert_same_results(results, {first_token: clean[first_token]})
    assert (summary.num_sweeps, summary.num_clouds_repeated, summary.num_clouds_behind) == (1, 0, 1)


def test_a_results_key_two_sweeps_share_keeps_the_first(bag: Path, tiny_export: Path, clean: dict, tmp_path: Path, caplog):
    """The bag's metadata gives both stamps the first sample token: the second sweep does not replace the first's."""

    def one_token(name, data):
        if name != T.METADATA_NAME:
            return data
        tokens = json.loads(data["sample_tokens"])
        first = tokens[min(tokens, key=int)]
        return {**data, "sample_tokens": json.dumps({stamp: first for stamp in tokens})}

    same = copy_bag(bag, tmp_path / "same.mcap", lambda m: [(m.topic, m.datatype, m.message, m.log_time_ns)], one_token)
    with caplog.at_level(logging.WARNING, logger="streamdet.bag.run"):
        summary = run_bag(same, tiny_export, tmp_path / "det.mcap")
    first_token = next(iter(clean))
    assert_same_results(json.loads(summary.results_json.read_text())["results"], {first_token: clean[first_token]})
    assert (summary.num_sweeps, summary.num_duplicate_keys) == (2, 1)
    assert f"has the results key {first_token} of an earlier sweep: left out of the results JSON" in caplog.text
