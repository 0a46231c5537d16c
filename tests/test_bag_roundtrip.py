"""A synthetic scene exported to MCAP and read back with rosbags, a reader independent of the library that wrote
it (mcap-ros2-support): the same points, images, calibration (LUT) and poses as the nuScenes tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.bag import msgdefs
from streamdet.bag.cli import main as bag_main
from streamdet.bag.export import cloud_time_s
from streamdet.calibration.camera import make_transform, quaternion_to_matrix
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut_build import build_lut
from streamdet.core.points import SWEEP_DURATION_S
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import load_bundled_sample, load_image
from streamdet.runtime_ort.ros.camera_info import rig_from_ros
from streamdet.runtime_ort.ros.header import header_stamp_ns
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb
from streamdet.runtime_ort.ros.pointcloud2 import decode_pointcloud2
from streamdet.runtime_ort.ros.tf import TfBuffer

rosbags_highlevel = pytest.importorskip("rosbags.highlevel")
rosbags_typesys = pytest.importorskip("rosbags.typesys")

GRID = GridSpec(x_range_m=(-16.0, 16.0), y_range_m=(-16.0, 16.0), z_range_m=(-3.0, 5.0), voxel_xy_m=1.0, voxel_z_m=1.0)


def read_with_rosbags(path: Path) -> list[tuple[str, str, int, object]]:
    """(topic, type, log time, message) of every message, decoded by rosbags."""
    typestore = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_HUMBLE)
    with rosbags_highlevel.AnyReader([path], default_typestore=typestore) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


@pytest.fixture(scope="module")
def exported(tiny_synth_data: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "drive.mcap"
    result = CliRunner().invoke(bag_main, ["export", "--data", str(tiny_synth_data), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "2 sweeps (2 key frames), 12 images" in result.output
    return out


@pytest.fixture(scope="module")
def messages(exported: Path):
    return read_with_rosbags(exported)


@pytest.fixture(scope="module")
def samples(tiny_synth_data: Path):
    reader = NuScenesReader(tiny_synth_data, "v1.0-synth")
    return [reader.get(t) for t in reader.sample_tokens]


def test_topics_types_and_order(messages):
    types = {topic: msgtype for topic, msgtype, _, _ in messages}
    assert types["/LIDAR_TOP"] == "sensor_msgs/msg/PointCloud2"
    assert types["/tf"] == types["/tf_static"] == "tf2_msgs/msg/TFMessage"
    assert types["/markers/annotations"] == "visualization_msgs/msg/MarkerArray"
    for cam in ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"):
        assert types[f"/{cam}/image_rect_compressed"] == "sensor_msgs/msg/CompressedImage"
        assert types[f"/{cam}/camera_info"] == "sensor_msgs/msg/CameraInfo"
    times = [t for _, _, t, _ in messages]
    assert times == sorted(times)
    assert messages[0][0] == "/tf_static"
    for topic, _, t, msg in messages:  # every message is logged at its own stamp
        if hasattr(msg, "header"):
            assert header_stamp_ns(msg) == t


def test_points_are_bit_identical_with_their_times(messages, samples):
    clouds = [m for topic, _, _, m in messages if topic == "/LIDAR_TOP"]
    assert len(clouds) == len(samples) == 2
    for msg, sample in zip(clouds, samples):
        assert header_stamp_ns(msg) == sample.timestamp_us * 1000 and msg.header.frame_id == "LIDAR_TOP"
        assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "ring", "time"]
        cloud = decode_pointcloud2(msg)
        assert cloud.points.tobytes() == np.ascontiguousarray(sample.points, dtype=np.float32).tobytes()
        expected = cloud_time_s(sample.points, sample.point_time_s)  # after the sweep start -> relative to the stamp
        assert cloud.time_s.astype(np.float32).tobytes() == expected.tobytes()
        assert np.all(cloud.time_s <= 0) and np.all(cloud.time_s >= -SWEEP_DURATION_S - 1e-6)


def test_images_decode_as_the_dataset_files(messages, samples):
    images = [(topic.split("/")[1], m) for topic, _, _, m in messages if topic.endswith("/image_rect_compressed")]
    assert len(images) == 12
    by_stamp = {(s.rig.camera(n).timestamp_us * 1000, n): s.image_paths[n] for s in samples for n in s.rig.names}
    worst = 0
    for cam, msg in images:
        path = by_stamp[(header_stamp_ns(msg), cam)]
        assert bytes(msg.data) == path.read_bytes()  # the dataset's JPEG, byte for byte
        diff = np.abs(compressed_image_to_rgb(msg).astype(int) - load_image(path).astype(int))
        worst = max(worst, int(diff.max()))
    assert worst == 0  # the same bytes decode to the same pixels: no JPEG error at all


def _tf_and_infos(messages):
    tf = TfBuffer()
    infos_by_stamp: dict[int, dict] = {}
    for topic, _, _, msg in messages:
        if topic == "/tf_static":
            tf.add(msg, static=True)
        elif topic == "/tf":
            tf.add(msg)
        elif topic.endswith("/camera_info"):
            infos_by_stamp.setdefault(header_stamp_ns(msg), {})[topic.split("/")[1]] = msg
    return tf, infos_by_stamp


def test_calibration_and_lut_are_identical(messages, samples):
    tf, infos_by_stamp = _tf_and_infos(messages)
    for sample in samples:
        cams = sample.rig.names
        stamps = {n: sample.rig.camera(n).timestamp_us * 1000 for n in cams}
        infos = {n: infos_by_stamp[stamps[n]][n] for n in cams}
        rig = rig_from_ros(infos, tf, "LIDAR_TOP", sample.timestamp_us * 1000, stamps, order=cams)
        assert rig == sample.rig  # K, lidar2cam (with the ego motion), sizes, lidar2ego, ego2global: bit for bit
        ours = build_lut(rig, GRID, 4)
        theirs = build_lut(sample.rig, GRID, 4)
        assert np.array_equal(ours.index, theirs.index) and np.array_equal(ours.weight, theirs.weight)
        assert ours.calibration_sha256 == theirs.calibration_sha256


def test_poses_are_identical(messages, samples):
    tf, _ = _tf_and_infos(messages)
    for sample in samples:
        stamp = sample.timestamp_us * 1000
        pose = tf.lookup("map", "base_link", stamp)
        mount = tf.lookup("base_link", "LIDAR_TOP", stamp)
        assert np.array_equal(make_transform(quaternion_to_matrix(pose["rotation"]), pose["translation"]), sample.ego2global)
        assert np.array_equal(make_transform(quaternion_to_matrix(mount["rotation"]), mount["translation"]), sample.lidar2ego)


def test_ground_truth_markers(messages, samples):
    arrays = [m for topic, _, _, m in messages if topic == "/markers/annotations"]
    for msg, sample in zip(arrays, samples):
        assert msg.markers[0].action == 3  # DELETEALL: the previous key frame's boxes go
        cubes = [m for m in msg.markers if m.type == 1 and m.action == 0]
        assert len(cubes) == len(sample.gt_boxes)
        centres = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in cubes])
        np.testing.assert_allclose(centres, sample.gt_boxes[:, :3])


def test_bundled_real_sample_round_trip(tmp_path):
    out = tmp_path / "real.mcap"
    result = CliRunner().invoke(bag_main, ["export", "--out", str(out)])
    assert result.exit_code == 0, result.output
    sample = load_bundled_sample()
    messages = read_with_rosbags(out)
    (cloud_msg,) = [m for topic, _, _, m in messages if topic == "/LIDAR_TOP"]
    cloud = decode_pointcloud2(cloud_msg)
    assert cloud.points.tobytes() == sample.points.tobytes()
    tf, infos_by_stamp = _tf_and_infos(messages)
    cams = sample.rig.names
    stamps = {n: sample.rig.camera(n).timestamp_us * 1000 for n in cams}
    rig = rig_from_ros({n: infos_by_stamp[stamps[n]][n] for n in cams}, tf, "LIDAR_TOP", sample.timestamp_us * 1000, stamps, order=cams)
    # calibration.json stores lidar2cam as a float32-derived matrix; the bag rebuilds it from the mountings and poses
    for ours, theirs in zip(rig.cameras, sample.rig.cameras):
        assert np.array_equal(ours.K, theirs.K)
        assert np.abs(ours.lidar2cam - theirs.lidar2cam).max() < 1e-3


def test_export_errors_are_one_line(tiny_synth_data: Path, tmp_path):
    result = CliRunner().invoke(bag_main, ["export", "--data", str(tiny_synth_data), "--scene", "nope", "--out", str(tmp_path / "x.mcap")])
    assert result.exit_code != 0 and "scene 'nope' not found" in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(bag_main, ["export", "--data", str(tmp_path), "--out", str(tmp_path / "x.mcap")])
    assert result.exit_code != 0 and "nuScenes table folder not found" in result.output


def test_missing_extra_is_a_one_line_hint(tiny_synth_data: Path, tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_mcap(name, *args, **kwargs):
        if name.split(".")[0] in ("mcap", "mcap_ros2"):
            raise ImportError(f"No module named {name!r}", name=name.split(".")[0])
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mcap)
    monkeypatch.setattr("importlib.import_module", lambda name: no_mcap(name))
    result = CliRunner().invoke(bag_main, ["export", "--data", str(tiny_synth_data), "--out", str(tmp_path / "x.mcap")])
    assert result.exit_code != 0
    assert "streamdet-bag needs mcap (pip install 'streamdet[ros]'; from a checkout: pip install '.[ros]')" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_message_definitions_match_the_ros2_humble_ones():
    """Every definition rosbags also ships has the same fields and constants, in the same order."""
    typestore = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_HUMBLE)
    checked = 0
    for name in msgdefs.MSGDEFS:
        full = msgdefs.full_name(name)
        if full not in typestore.fielddefs:
            continue  # vision_msgs: not in rosbags' store; its bag round trip is tested in test_bag_run
        ours = rosbags_typesys.get_types_from_msg(msgdefs.definition(name), full)[full]
        consts, fields = typestore.fielddefs[full]
        assert [f[0] for f in ours[1]] == [f[0] for f in fields], name
        assert [(c[0], c[2]) for c in ours[0]] == [(c[0], c[2]) for c in consts], name
        checked += 1
    assert checked >= 20
    text = msgdefs.schema_text("sensor_msgs/msg/PointCloud2")
    assert text.count("MSG: ") == 3 and "MSG: sensor_msgs/PointField" in text and "MSG: builtin_interfaces/Time" in text
    with pytest.raises(KeyError, match="no message definition for 'nav_msgs/Odometry'"):
        msgdefs.schema_text("nav_msgs/msg/Odometry")


def test_adapters_and_bag_import_without_torch():
    """The vehicle side: runtime_ort.ros and streamdet.bag load and convert with PyTorch unimportable."""
    import subprocess
    import sys

    script = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'torchvision'):\n"
        "            raise ImportError(name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import streamdet.runtime_ort.ros.pointcloud2, streamdet.runtime_ort.ros.images, streamdet.runtime_ort.ros.tf\n"
        "import streamdet.runtime_ort.ros.camera_info, streamdet.runtime_ort.ros.detections\n"
        "import streamdet.bag.cli, streamdet.bag.export, streamdet.bag.run, streamdet.bag.source, streamdet.bag.recording\n"
        "assert not [m for m in sys.modules if m.split('.')[0] in ('torch', 'torchvision')]\n"
        "assert not [m for m in sys.modules if m.split('.')[:2] in (['streamdet', 'models'], ['streamdet', 'export'], "
        "['streamdet', 'training'], ['streamdet', 'benchmarks'])]\n"
        "print('ok')\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"


def test_calibration_json_of_the_bag_is_the_first_samples_rig(exported: Path, samples, tmp_path):
    from streamdet.calibration.camera import Rig

    out = tmp_path / "calibration.json"
    result = CliRunner().invoke(bag_main, ["calibration", "--bag", str(exported), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"at LiDAR stamp {samples[0].timestamp_us * 1000} ns" in result.output
    assert Rig.from_calibration_json(out) == samples[0].rig  # the first complete image set: the first key frame
    result = CliRunner().invoke(bag_main, ["calibration", "--bag", str(exported), "--out", str(out), "--cameras", "CAM_BACK,CAM_FRONT"])
    assert result.exit_code == 0, result.output
    assert Rig.from_calibration_json(out).names == ("CAM_BACK", "CAM_FRONT")
    result = CliRunner().invoke(bag_main, ["calibration", "--bag", str(exported), "--out", str(out), "--cameras", "CAM_LEFT"])
    assert result.exit_code != 0 and "no LiDAR message comes after an image and a CameraInfo of every camera ['CAM_LEFT']" in result.output


def test_a_rosbag2_folder_holding_one_mcap(exported: Path, tmp_path):
    import shutil

    from streamdet.bag.source import BagSource, SourceConfig

    folder = tmp_path / "rosbag2_drive"
    folder.mkdir()
    shutil.copy(exported, folder / "drive_0.mcap")
    assert BagSource(folder, SourceConfig()).path == folder / "drive_0.mcap"
    shutil.copy(exported, folder / "drive_1.mcap")
    with pytest.raises(ValueError, match="is a folder holding 2 .mcap files; name the bag file"):
        BagSource(folder, SourceConfig())
    with pytest.raises(FileNotFoundError, match="bag not found"):
        BagSource(tmp_path / "nope.mcap", SourceConfig())


def test_an_exported_image_is_read_bounded_and_labelled_by_its_header(tmp_path):
    """A FIFO named like a camera image fails at once (it used to block the export for ever); a PNG is labelled png."""
    import os
    from types import SimpleNamespace

    import cv2

    from streamdet.bag.export import _image

    fifo = tmp_path / "cam.jpg"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        _image(SimpleNamespace(path=fifo, name="CAM_FRONT"), 0)()
    png = tmp_path / "cam.png"
    cv2.imwrite(str(png), np.zeros((4, 6, 3), np.uint8))
    msg = _image(SimpleNamespace(path=png, name="CAM_FRONT"), 0)()
    assert msg["format"] == "png" and msg["data"] == png.read_bytes()
    (tmp_path / "x.jpg").write_bytes(b"GIF89a....")
    with pytest.raises(ValueError, match="x.jpg"):
        _image(SimpleNamespace(path=tmp_path / "x.jpg", name="CAM_FRONT"), 0)()
