"""The embedded-runtime review's findings (H1, M1-M3, L1-L6): each case with the behaviour it must have, and the
malformed inputs beside it. Runs without ROS: the example node's callbacks run on stand-in rclpy modules."""

from __future__ import annotations

import importlib.util
import logging
import re
import struct
import sys
import tracemalloc
import types
import zlib
from pathlib import Path
from types import SimpleNamespace as ns

import cv2
import numpy as np
import pytest

from streamdet.calibration.camera import make_transform, matrix_to_quaternion, quaternion_to_matrix
from streamdet.runtime_ort import CloudClockError, DetectorClosed, RosMessageError, StreamingDetector, TfLookupError
from streamdet.runtime_ort.ros.camera_info import camera_info_intrinsics, camera_info_message, rig_from_ros
from streamdet.runtime_ort.ros.detections import detection3d_array_message
from streamdet.runtime_ort.ros.header import NS_PER_S, byte_view
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb, image_to_rgb, rgb_to_compressed_image_message
from streamdet.runtime_ort.ros.pointcloud2 import CloudFields, decode_pointcloud2, pointcloud2_message
from streamdet.runtime_ort.ros.tf import TfBuffer, transform_stamped_msg

from test_hardening_ros_adapters import as_msg  # noqa: E402 (a dict message as the readers' attribute object)

ROOT = Path(__file__).resolve().parents[1]
STAMP_NS = 1_700_000_000_000_000_000
IDENTITY = {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]}




def sweep(n: int = 2000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = np.zeros((n, 5), np.float32)
    points[:, :2] = rng.uniform(-40, 40, (n, 2))
    points[:, 2] = rng.uniform(-2, 2, n)
    points[:, 3] = rng.integers(0, 256, n)
    return points


def timed_cloud(times: np.ndarray, stamp_ns: int = STAMP_NS, dtype: str = "<f4", name: str = "time") -> dict:
    """A cloud of len(times) points whose time column ``name`` is ``times`` in ``dtype``."""
    points = sweep(len(times))
    dt = np.dtype({"names": ["x", "y", "z", "intensity", name], "formats": ["<f4"] * 4 + [dtype]})
    rec = np.zeros(len(times), dt)
    for j, field in enumerate(["x", "y", "z", "intensity"]):
        rec[field] = points[:, j]
    rec[name] = times
    codes = {"<f4": 7, "<f8": 8, "<u4": 6}
    msg = pointcloud2_message(points, stamp_ns, "lidar")
    msg.update(data=rec.tobytes(), point_step=dt.itemsize, row_step=dt.itemsize * len(times),
               fields=[{"name": f, "offset": dt.fields[f][1], "datatype": codes[dt.fields[f][0].str], "count": 1} for f in dt.names])  # fmt: skip
    return msg


def example():
    spec = importlib.util.spec_from_file_location("ros2_node_example_review", ROOT / "docs" / "ros2_node_example.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---- H1 / L1: per-point clocks ----------------------------------------------------------------------------------

SWEEP_S = np.linspace(-0.05, 0.0, 2000)


@pytest.mark.parametrize("offset_s, what", [(37.0, "TAI vs UTC"), (18.0, "GPS vs UTC"), (-37.0, "UTC vs TAI")])
def test_a_clock_offset_is_a_named_error_quoting_it(offset_s: float, what: str):
    msg = as_msg(timed_cloud(SWEEP_S + offset_s))
    with pytest.raises(CloudClockError) as info:
        decode_pointcloud2(msg)
    text = str(info.value)
    assert isinstance(info.value, RosMessageError) and isinstance(info.value, ValueError), what
    typical = float(re.search(r"typically ([-+][\d.]+) s", text).group(1))
    assert typical == pytest.approx(offset_s - 0.025, abs=1e-3)  # the sweep's median time, 37 s (or 18 s) away
    assert "2000 of 2000 timed points" in text and "'time'" in text
    assert "CloudFields(time=None)" in text and "clock" in text and "\n" not in text
    untimed = decode_pointcloud2(msg, CloudFields(time=None))  # the fix the message names: every point kept
    assert len(untimed.points) == 2000 and untimed.time_s is None


def test_a_header_stamp_of_zero_under_a_running_clock_is_refused():
    sim_clock = 1234.5 + SWEEP_S  # a simulator's clock in its per-point times, its header stamp left 0
    with pytest.raises(CloudClockError, match=r"stamp 0 ns .* typically \+1234"):
        decode_pointcloud2(as_msg(timed_cloud(sim_clock, stamp_ns=0)))


@pytest.mark.parametrize("bad, raises", [(0, False), (1, False), (999, False), (1000, False), (1001, True), (2000, True)])
def test_more_than_half_off_raises_fewer_are_dropped_and_counted(bad: int, raises: bool):
    times = SWEEP_S.copy()
    times[:bad] += 37.0
    msg = as_msg(timed_cloud(times))
    if raises:
        with pytest.raises(CloudClockError, match=f"{bad} of 2000 timed points"):
            decode_pointcloud2(msg)
        return
    cloud = decode_pointcloud2(msg)
    assert cloud.num_time_dropped == bad and len(cloud.points) == 2000 - bad


def test_non_finite_times_count_apart_from_the_clock_rule():
    times = SWEEP_S.copy()
    times[:1500] = np.nan  # not a clock: dropped and counted as before, out of the majority rule
    times[1500:1700] += 37.0
    cloud = decode_pointcloud2(as_msg(timed_cloud(times)))
    assert cloud.num_time_dropped == 1700 and len(cloud.points) == 300


def test_float_milliseconds_read_as_seconds_name_the_unit():
    ms = (SWEEP_S + 0.05) * 1e3  # 0..50 ms
    with pytest.raises(CloudClockError, match=r"read as s \(time_unit 'auto'\).*time_unit="):
        decode_pointcloud2(as_msg(timed_cloud(ms)))
    cloud = decode_pointcloud2(as_msg(timed_cloud(ms)), CloudFields(time_unit="ms"))
    assert len(cloud.points) == 2000 and np.ptp(cloud.time_s) == pytest.approx(0.05, abs=1e-6)


def test_a_float32_absolute_clock_is_refused_float64_and_relative_are_read():
    absolute = STAMP_NS / NS_PER_S + SWEEP_S
    with pytest.raises(CloudClockError, match=r"field 'timestamp' is float32 holding an absolute clock .* resolves only 128 s"):
        decode_pointcloud2(as_msg(timed_cloud(absolute, dtype="<f4", name="timestamp")))
    hesai = decode_pointcloud2(as_msg(timed_cloud(absolute, dtype="<f8", name="timestamp")))
    np.testing.assert_allclose(hesai.time_s, SWEEP_S, atol=1e-6)
    velodyne = decode_pointcloud2(as_msg(timed_cloud(SWEEP_S, dtype="<f4")))
    np.testing.assert_allclose(velodyne.time_s, SWEEP_S, atol=1e-7)
    ouster = decode_pointcloud2(as_msg(timed_cloud(np.round((SWEEP_S + 0.05) * 1e9), dtype="<u4", name="t")))
    np.testing.assert_allclose(ouster.time_s, SWEEP_S + 0.05, atol=1e-9)


def test_a_bag_on_another_clock_is_read_without_times_and_warned_once(tmp_path: Path, caplog):
    pytest.importorskip("mcap_ros2.writer")
    from streamdet.bag.source import BagSource, SourceConfig
    from streamdet.bag.writer import BagWriter

    path = tmp_path / "tai.mcap"
    with BagWriter(path) as writer:
        for i in range(3):
            stamp = STAMP_NS + i * 50_000_000
            writer.write("/LIDAR_TOP", "sensor_msgs/msg/PointCloud2", timed_cloud(SWEEP_S + 37.0, stamp), stamp)
        writer.metadata("streamdet", {"scene": "s", "sample_tokens": "{}"})
    config = SourceConfig(global_frame=None, ego_frame="lidar")
    source = BagSource(path, config)
    with caplog.at_level(logging.WARNING, logger="streamdet.bag.source"):
        events = list(source.sweeps())
    assert len(events) == 3 and source.num_clouds_untimed == 3 and source.num_time_dropped == 0
    for event in events:  # every point detected, each slice at its cloud's stamp
        assert len(event.cloud.points) == 2000 and event.cloud.time_s is None
        assert {s.scan_time_ns for s in event.slices} == {event.cloud.stamp_ns}
    warned = [r.getMessage() for r in caplog.records if "per-point" in r.getMessage()]
    assert len(warned) == 1 and "typically +36.97" in warned[0] and "read without per-point times" in warned[0]
    # a caller that asked for per-point times gets the refusal, naming the bag and the message
    strict = BagSource(path, SourceConfig(global_frame=None, ego_frame="lidar", cloud_fields=CloudFields()))
    with pytest.raises(ValueError, match=rf"{path}: /LIDAR_TOP message at stamp .* typically \+36.97"):
        list(strict.sweeps())


# ---- L4: header and flag fields are not coerced ------------------------------------------------------------------


@pytest.mark.parametrize("value", ["false", "true", 0, 1, None, 0.0])
def test_is_bigendian_must_be_a_bool(value):
    msg = as_msg({**timed_cloud(SWEEP_S), "is_bigendian": value})
    with pytest.raises(RosMessageError, match=r"PointCloud2.is_bigendian must be a bool, got"):
        decode_pointcloud2(msg)


def test_numpy_bool_is_bigendian_is_read():
    cloud = decode_pointcloud2(as_msg({**timed_cloud(SWEEP_S), "is_bigendian": np.bool_(False)}))
    np.testing.assert_array_equal(cloud.points[:, :3], sweep(2000)[:, :3])


@pytest.mark.parametrize("frame", [None, "", 5, b"lidar"])
@pytest.mark.parametrize("empty", [False, True])
def test_frame_id_must_be_a_non_empty_str(frame, empty: bool):
    msg = timed_cloud(SWEEP_S)
    msg["header"]["frame_id"] = frame
    if empty:
        msg.update(width=0, row_step=0, data=b"")
    with pytest.raises(RosMessageError, match=r"PointCloud2 header.frame_id must be a non-empty string"):
        decode_pointcloud2(as_msg(msg))


# ---- M1: one error class for every refused message -------------------------------------------------------------


@pytest.mark.parametrize("call", [
    lambda: byte_view(None),
    lambda: decode_pointcloud2(as_msg({**pointcloud2_message(sweep(10), STAMP_NS, "l"), "data": b"\0" * 7})),
    lambda: image_to_rgb(ns(encoding="mono8", height=1, width=1, step=1, data=b"\0")),
    lambda: compressed_image_to_rgb(ns(format="jpeg", data=b"not a jpeg")),
    lambda: camera_info_intrinsics(as_msg({**camera_info_message(np.diag([500.0, 500, 1]), 64, 48, 0, "c"), "d": [0.1]})),
    lambda: TfBuffer().add(as_msg({"transforms": [transform_stamped_msg("a", "b", {**IDENTITY, "rotation": [0.0] * 4}, 0)]})),
    lambda: TfBuffer().lookup("a", "b", 0),
    lambda: detection3d_array_message(np.full((1, 9), np.nan), np.ones(1), np.zeros(1, int), 0, "l"),
])  # fmt: skip
def test_every_adapter_refuses_a_message_with_ros_message_error(call):
    with pytest.raises(RosMessageError):
        call()


@pytest.mark.parametrize("call", [lambda: CloudFields(time_unit="minutes"), lambda: TfBuffer(max_extrapolation_ns=-1),
                                  lambda: TfBuffer(cache_s=0)])  # fmt: skip
def test_a_wrong_argument_stays_a_plain_value_error(call):
    with pytest.raises(ValueError) as info:
        call()
    assert not isinstance(info.value, RosMessageError)  # a caller's mistake, not a bad message


def test_no_tf_path_is_both_a_key_error_and_a_value_error():
    tf = TfBuffer()
    tf.add(as_msg({"transforms": [transform_stamped_msg("base_link", "lidar", IDENTITY, 0)]}), static=True)
    with pytest.raises(TfLookupError) as info:
        tf.lookup("map", "lidar", 0)
    assert isinstance(info.value, KeyError) and isinstance(info.value, ValueError)
    assert str(info.value).startswith("no TF path from 'map' to 'lidar'")  # a sentence, not a quoted key
    cam_info = as_msg(camera_info_message(np.diag([500.0, 500, 1]), 64, 48, 0, "cam"))
    with pytest.raises(ValueError, match="no TF path from 'base_link' to 'cam'"):  # a node catching ValueError meets it
        rig_from_ros({"cam": cam_info}, tf, "lidar", 0, global_frame=None)


# ---- M2: a bounded TF buffer -------------------------------------------------------------------------------------


def _tf_at(i: int, hz: int = 100) -> types.SimpleNamespace:
    stamp = STAMP_NS + i * NS_PER_S // hz
    pose = {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [i * 0.01, 0.0, 0.0]}
    return as_msg({"transforms": [transform_stamped_msg("map", "odom", IDENTITY, stamp),
                                  transform_stamped_msg("odom", "base_link", pose, stamp)]})  # fmt: skip


def test_the_tf_buffer_keeps_ten_seconds_and_lookups_within_them_work():
    tf = TfBuffer()
    assert tf.cache_s == 10.0
    tf.add(as_msg({"transforms": [transform_stamped_msg("base_link", "lidar", IDENTITY, 0)]}), static=True)
    tracemalloc.start()
    try:
        for i in range(3_000):  # 30 s at 100 Hz: the window is full
            tf.add(_tf_at(i))
        full, _ = tracemalloc.get_traced_memory()
        for i in range(3_000, 12_000):  # 90 s more: nothing may grow
            tf.add(_tf_at(i))
        later, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert all(len(e.stamps) == len(e.records) == 1_001 for k, e in tf._edges.items() if k != ("base_link", "lidar"))
    assert later - full < 100_000, (full, later)  # bytes: 9000 more messages kept nothing
    newest = STAMP_NS + 11_999 * NS_PER_S // 100
    # within the window: exact stamps, interpolation and chains through the static edge still answer
    assert tf.lookup("map", "lidar", newest)["translation"] == pytest.approx([119.99, 0.0, 0.0])
    assert tf.lookup("map", "base_link", newest - 5 * NS_PER_S - 5_000_000)["translation"] == pytest.approx([114.985, 0, 0])
    assert tf.lookup("map", "base_link", newest - 10 * NS_PER_S)["translation"] == pytest.approx([109.99, 0, 0])
    with pytest.raises(TfLookupError, match=r"outside its 1001 stamps .* keeps the last 10 s of each edge \(cache_s\)"):
        tf.lookup("map", "base_link", newest - 11 * NS_PER_S)
    assert tf.lookup("base_link", "lidar", 0) == IDENTITY  # static: kept whatever its stamp


def test_an_old_transform_arriving_late_is_pruned_and_cache_none_keeps_all():
    tf = TfBuffer(cache_s=1.0)
    for i in range(300):
        tf.add(_tf_at(i))
    tf.add(_tf_at(0))  # 3 s behind the newest: outside the window as soon as it is stored
    assert len(tf._edges[("odom", "base_link")].stamps) == 101
    keep_all = TfBuffer(cache_s=None)
    for i in range(300):
        keep_all.add(_tf_at(i))
    assert len(keep_all._edges[("odom", "base_link")].stamps) == 300


@pytest.mark.parametrize("value", [0, -1.0, float("nan"), float("inf"), True, "10"])
def test_cache_s_must_be_positive_seconds(value):
    with pytest.raises(ValueError, match=r"TfBuffer.cache_s must be a number of seconds > 0 or None"):
        TfBuffer(cache_s=value)


# ---- M3: rectified CameraInfo ------------------------------------------------------------------------------------

K_RECT = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])


def _rotation(axis: list[float], deg: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.deg2rad(deg) / 2
    return quaternion_to_matrix([np.cos(half), *(np.sin(half) * axis)])


def _rectified_info(R: np.ndarray, column: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> ns:
    msg = camera_info_message(K_RECT, 640, 480, STAMP_NS, "cam_optical")
    msg.update(d=[-0.2, 0.05, 0.0, 0.0, 0.0], r=R.reshape(-1).tolist(), p=np.c_[K_RECT, column].reshape(-1).tolist())
    return as_msg(msg)


def _camera_tf() -> tuple[TfBuffer, np.ndarray, np.ndarray]:
    lidar2ego = make_transform(_rotation([0, 0, 1], 1.0), [0.9, 0.0, 1.8])
    optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # z ahead (ego x), x right, y down
    cam2ego = make_transform(optical @ _rotation([1, 0, 0], 3.0), [1.5, 0.1, 1.6])
    tf = TfBuffer()
    tf.add(as_msg({"transforms": [
        transform_stamped_msg("base_link", "lidar", {"rotation": matrix_to_quaternion(lidar2ego[:3, :3]).tolist(), "translation": lidar2ego[:3, 3].tolist()}, 0),
        transform_stamped_msg("base_link", "cam_optical", {"rotation": matrix_to_quaternion(cam2ego[:3, :3]).tolist(), "translation": cam2ego[:3, 3].tolist()}, 0),
    ]}), static=True)  # fmt: skip
    return tf, lidar2ego, cam2ego


@pytest.mark.parametrize("R", [_rotation([0, 1, 0], 2.3), _rotation([1, 2, 3], 4.0), np.eye(3)])
def test_the_rectification_rotation_is_folded_in_as_a_naive_projection_says(R: np.ndarray):
    tf, lidar2ego, cam2ego = _camera_tf()
    rig = rig_from_ros({"cam": _rectified_info(R)}, tf, "lidar", STAMP_NS, global_frame=None, intrinsics="p")
    rng = np.random.default_rng(0)
    ahead = np.c_[rng.uniform(5, 40, 200), rng.uniform(-10, 10, 200), rng.uniform(-1, 2, 200)]  # LiDAR frame, in view
    # CameraInfo's definition, point by point: x_cam from TF, x_rect = R x_cam, pixels = P [x_rect; 1]
    x_cam = (np.linalg.inv(cam2ego) @ lidar2ego @ np.c_[ahead, np.ones(200)].T)[:3]
    uvw = np.c_[K_RECT, np.zeros(3)] @ np.r_[R @ x_cam, np.ones((1, 200))]
    naive = (uvw[:2] / uvw[2]).T
    uv, depth = rig.cameras[0].project(ahead)
    assert np.all(depth > 0)
    np.testing.assert_allclose(uv, naive, atol=1e-6)
    unrectified = rig_from_ros({"cam": _rectified_info(np.eye(3))}, tf, "lidar", STAMP_NS, global_frame=None, intrinsics="p")
    moved = np.abs(unrectified.cameras[0].project(ahead)[0] - naive).max()
    assert moved > 10 if not np.array_equal(R, np.eye(3)) else moved < 1e-9  # R ignored: tens of pixels off


def test_raw_images_ignore_r():
    tf, _, _ = _camera_tf()
    info = _rectified_info(_rotation([0, 1, 0], 2.3))
    info.d = [0.0] * 5  # an undistorted raw image read with K: R describes the rectified image only
    with_r = rig_from_ros({"cam": info}, tf, "lidar", STAMP_NS, global_frame=None, intrinsics="k")
    info.r = np.eye(3).reshape(-1).tolist()
    assert with_r == rig_from_ros({"cam": info}, tf, "lidar", STAMP_NS, global_frame=None, intrinsics="k")


@pytest.mark.parametrize("column", [(-400.0, 0.0, 0.0), (0.0, 12.5, 0.0), (0.0, 0.0, 1e-3)])
def test_a_stereo_second_camera_projection_is_refused_by_name(column):
    with pytest.raises(RosMessageError, match=r"CameraInfo of 'cam_optical': p's 4th column \[Tx, Ty, Tz\] = .* stereo"):
        camera_info_intrinsics(_rectified_info(np.eye(3), column), intrinsics="p")


@pytest.mark.parametrize("r, said", [([0.0] * 9, "is not a rotation"), (np.diag([1.0, 1.0, -1.0]).reshape(-1).tolist(), "det must be"),
                                     ([1.0] * 8, "r must hold 9 values"), ([np.nan] + [0.0] * 8, "is not a rotation"),
                                     (None, "r must be a list of numbers"), ((np.eye(3) * 1.01).reshape(-1).tolist(), "is not a rotation")])  # fmt: skip
def test_a_malformed_rectification_is_refused_by_name(r, said):
    tf, _, _ = _camera_tf()
    info = _rectified_info(np.eye(3))
    info.r = r
    with pytest.raises(RosMessageError, match=f"CameraInfo of 'cam_optical'.*{said}"):
        rig_from_ros({"cam": info}, tf, "lidar", STAMP_NS, global_frame=None, intrinsics="p")


# ---- L3: colour only; rgba8 / bgra8 without alpha ----------------------------------------------------------------


def test_grey_alpha_png_is_refused_and_rgba_png_is_colour():
    rng = np.random.default_rng(1)
    grey_alpha = rng.integers(0, 256, (24, 32, 2), dtype=np.uint8)
    ok, png = cv2.imencode(".png", cv2.merge([grey_alpha[..., 0]] * 3 + [grey_alpha[..., 1]]))
    bgra = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(compressed_image_to_rgb(ns(format="png", data=png.tobytes())), bgra[..., 2::-1])
    # a true grey+alpha PNG (colour type 4), written by hand: OpenCV would read it as BGRA

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = b"".join(b"\0" + row.tobytes() for row in grey_alpha)
    la = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 32, 24, 8, 4, 0, 0, 0))
          + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))  # fmt: skip
    with pytest.raises(RosMessageError, match=r"\(png\) is a grey\+alpha 8-bit png image; streamdet takes 8-bit colour"):
        compressed_image_to_rgb(ns(format="png", data=la))


@pytest.mark.parametrize("encoding", ["rgba8", "bgra8", "RGBA8"])
@pytest.mark.parametrize("pad", [0, 3])
def test_raw_rgba_and_bgra_drop_alpha(encoding: str, pad: int):
    rgb = np.random.default_rng(2).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    alpha = np.full((5, 7, 1), 77, np.uint8)
    pixels = np.concatenate([rgb if encoding.lower() == "rgba8" else rgb[..., ::-1], alpha], axis=2).reshape(5, 28)
    rows = np.zeros((5, 28 + pad), np.uint8)
    rows[:, :28] = pixels
    msg = ns(encoding=encoding, height=5, width=7, step=28 + pad, data=rows.tobytes(), header=ns(stamp=ns(sec=1, nanosec=0)))
    out = image_to_rgb(msg)
    assert out.shape == (5, 7, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)
    msg.step = 27  # three bytes a pixel is not enough for four channels
    with pytest.raises(RosMessageError, match=f"step 27 < 4 x width 7 for {encoding}"):
        image_to_rgb(msg)


# ---- L5: a closed detector ---------------------------------------------------------------------------------------


def test_a_closed_detector_refuses_slices_without_pillars(tiny_export: Path):
    det = StreamingDetector(tiny_export)
    det.close()
    far = np.array([[500.0, 1.0, 0.0, 0.5, 0.0, 0.0]], np.float32)  # outside the grid: no pillar
    for points in (np.zeros((0, 6), np.float32), far, far.repeat(3, axis=0)):
        with pytest.raises(DetectorClosed, match="the detector was closed"):
            det.detect_slice(points, 0, 0.0)
    with pytest.raises(DetectorClosed):
        det.detect_slices([np.zeros((0, 6), np.float32)] * 2, [0, 1], [0.0, 0.0])


# ---- M1, L6, H1: the example node --------------------------------------------------------------------------------


class _Slices:
    """A stand-in detector for detect_cloud: slice k finds ``counts[k]`` boxes; ``fail_at`` raises at that slice."""

    def __init__(self, counts: list[int], fail_at: int | None = None) -> None:
        self.num_slices, self.config, self.counts, self.fail_at = len(counts), ns(start_deg=0.0, clockwise=False), counts, fail_at
        self.stamps: list[float] = []

    def detect_slice(self, points, index, timestamp):
        if index == self.fail_at:
            raise ValueError("a slice the detector refuses")
        self.stamps.append(timestamp)
        n = self.counts[index]
        boxes = np.tile([1.0, 2.0, 0.0, 2.0, 4.0, 1.5, 0.0, 0.0, 0.0], (n, 1))
        return ns(detections=ns(boxes=boxes, scores=np.full(n, 0.5), labels=np.zeros(n, int)))


def _deleted(markers: dict) -> list[int]:
    return sorted(m["id"] for m in markers["markers"] if m["action"] == 2 and not m["ns"].endswith("/labels"))


def test_fewer_boxes_delete_the_markers_left_and_a_failed_cloud_changes_nothing():
    node = example()
    cloud = as_msg(pointcloud2_message(sweep(), STAMP_NS, "lidar"))
    shown: dict[int, int] = {}
    first = node.detect_cloud(_Slices([3, 0, 5, 1]), cloud, shown)
    assert [_deleted(m) for _, m in first] == [[], [], [], []] and shown == {0: 3, 1: 0, 2: 5, 3: 1}
    with pytest.raises(ValueError, match="refuses"):
        node.detect_cloud(_Slices([0, 0, 0, 0], fail_at=3), cloud, shown)  # nothing published: nothing to delete
    assert shown == {0: 3, 1: 0, 2: 5, 3: 1}
    second = node.detect_cloud(_Slices([1, 2, 5, 0]), cloud, shown)
    assert [_deleted(m) for _, m in second] == [[1, 2], [], [], [0]]
    # without a record of its own, the caller gets one kept for its detector
    det = _Slices([4, 4, 4, 4])
    node.detect_cloud(det, cloud)
    det.counts = [0, 4, 2, 4]
    assert [_deleted(m) for _, m in node.detect_cloud(det, cloud)] == [[0, 1, 2, 3], [], [2, 3], []]


def test_a_cloud_on_another_clock_is_detected_without_times_and_logged(caplog):
    node = example()
    msg = timed_cloud(SWEEP_S + 37.0)
    errors = node.ErrorLog()
    det = _Slices([1, 1, 1, 1])
    with caplog.at_level(logging.WARNING, logger="streamdet_node"):
        out = node.detect_cloud(det, as_msg(msg), {}, errors)
    assert len(out) == 4 and det.stamps == [STAMP_NS * 1e-9] * 4  # every slice at the cloud's stamp
    assert errors.count == 1 and "typically +36.97" in caplog.text and "read without per-point times" in caplog.text


def test_error_log_is_rate_limited_per_source(caplog):
    node = example()
    now = [0.0]
    errors = node.ErrorLog(period_s=5.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="streamdet_node"):
        for t in (0.0, 1.0, 2.0, 5.5):
            now[0] = t
            errors.report("CAM_FRONT image", ValueError(f"bad at {t}"))
        errors.report("LiDAR cloud", ValueError("short"))
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["CAM_FRONT image: bad at 0.0", "CAM_FRONT image: bad at 5.5 (2 more since the last report)",
                     "LiDAR cloud: short"] and errors.count == 5  # fmt: skip


def _stand_in_ros(monkeypatch, export_dir: Path) -> dict:
    """rclpy and the message packages as far as ``main`` uses them; ``spin`` hands back the node."""
    spun: dict = {}

    class Node:
        def __init__(self, name: str) -> None:
            self.subscriptions, self.published = {}, {}

        def declare_parameter(self, name, default, descriptor=None):
            return ns(value=str(export_dir) if name == "export_dir" else default)

        def create_publisher(self, cls, topic, qos):
            self.published[topic] = []
            return ns(publish=self.published[topic].append)

        def create_subscription(self, cls, topic, callback, qos):
            assert qos == "sensor data", topic  # best effort: a reliable subscription misses sensor drivers
            self.subscriptions[topic] = callback

    def module(name: str, **attrs) -> None:
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
        for key, value in attrs.items():
            setattr(sys.modules[name], key, value)

    message = type("Message", (), {})
    module("rclpy", init=lambda: None, spin=lambda node: spun.update(node=node))
    module("rclpy.node", Node=Node)
    module("rclpy.qos", qos_profile_sensor_data="sensor data")
    module("rcl_interfaces")
    module("rcl_interfaces.msg", ParameterDescriptor=lambda **fields: ns(**fields))
    module("rosidl_runtime_py")
    module("rosidl_runtime_py.set_message_fields", set_message_fields=lambda msg, values: setattr(msg, "values", values))
    for package, names in (("sensor_msgs", ["CompressedImage", "PointCloud2"]), ("vision_msgs", ["Detection3DArray"]),
                           ("visualization_msgs", ["MarkerArray"])):  # fmt: skip
        module(package)
        module(f"{package}.msg", **{n: message for n in names})
    return spun


def test_the_node_skips_bad_messages_and_goes_on(tiny_export: Path, monkeypatch, caplog):
    node_module = example()
    spun = _stand_in_ros(monkeypatch, tiny_export)
    node_module.main()
    node = spun["node"]
    cam = node.detector.camera_names[0]
    on_image, on_cloud = node.subscriptions[f"/{cam}/image_rect_compressed"], node.subscriptions["/LIDAR_TOP"]
    rgb = np.random.default_rng(3).integers(0, 256, (node.detector.image.height, node.detector.image.width, 3), np.uint8)
    jpeg = rgb_to_compressed_image_message(rgb, STAMP_NS, cam)
    cloud = pointcloud2_message(sweep(20_000), STAMP_NS, "LIDAR_TOP")
    with caplog.at_level(logging.WARNING, logger="streamdet_node"):
        on_image(as_msg({**jpeg, "data": jpeg["data"][: len(jpeg["data"]) // 3]}))  # truncated on a lossy link
        on_cloud(as_msg({**cloud, "data": cloud["data"][:-7]}))  # short: a driver restarting
        on_cloud(as_msg({**cloud, "header": {"stamp": {"sec": None, "nanosec": 0}, "frame_id": "LIDAR_TOP"}}))
        assert node.published == {"/streamdet/detections": [], "/streamdet/markers": []}
        on_image(as_msg(jpeg))
        on_cloud(as_msg(cloud))  # the node is still there: the next good messages are detected
    assert len(node.published["/streamdet/detections"]) == node.detector.num_slices
    assert f"{cam} image" in caplog.text and "could not be decoded" in caplog.text
    assert "LiDAR cloud: PointCloud2 data holds" in caplog.text and node.errors.count == 3
