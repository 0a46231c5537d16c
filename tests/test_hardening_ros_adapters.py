"""Hostile ROS 2 messages and arguments (API audit M2, M3, M4, L4, L5, L6): every refusal is a one-line ValueError
naming the message type, the field and the bad value (never TypeError, OverflowError, IndexError or numpy's own
text), a refused transform leaves the TF buffer exactly as it was, and valid inputs give what they gave before."""

from __future__ import annotations

import array
import copy
import math
from types import SimpleNamespace as ns

import numpy as np
import pytest

from streamdet.core.classes import CLASS_NAMES
from streamdet.core.sectors import slice_index_of
from streamdet.core.slicing import relative_time_s
from streamdet.runtime_ort.ros.camera_info import camera_info_intrinsics, camera_info_message
from streamdet.runtime_ort.ros.detections import detection3d_array_message, marker_array_message
from streamdet.runtime_ort.ros.header import INT32_MAX, INT32_MIN, NS_PER_S, byte_view, stamp_ns
from streamdet.runtime_ort.ros.pointcloud2 import decode_pointcloud2, pointcloud2_message, slice_from_message
from streamdet.runtime_ort.ros.tf import TfBuffer, transform_stamped_msg

STAMP_NS = 1_700_000_000_123_456_789
NAN, INF = float("nan"), float("inf")


def as_msg(value):
    """A message dict (what the adapters write) as an object with ROS field attributes (what the readers give)."""
    if isinstance(value, dict):
        return ns(**{k: as_msg(v) for k, v in value.items()})
    if isinstance(value, list):
        return [as_msg(v) for v in value]
    return value


def refused(call, *needles: str) -> str:
    """Run ``call``; it must raise a ValueError whose message is one line holding every needle."""
    with pytest.raises(ValueError) as info:
        call()
    text = str(info.value)
    assert "\n" not in text, text
    for needle in needles:
        assert needle in text, f"{needle!r} not in {text!r}"
    return text


# ---- M3: sensor_msgs/PointCloud2 and builtin_interfaces/Time -----------------------------------------------------

POINTS = np.array([[1, 2, 0, 10, 3], [5, -5, 0.5, 200, 7], [-3, 4, 1, 0, 1]], np.float32)
TIMES = np.array([0.0, 0.01, -0.02], np.float32)


def _cloud_msg(**over) -> dict:
    return {**pointcloud2_message(POINTS, STAMP_NS, "lidar", TIMES), **over}


def _stamped(sec, nanosec=0) -> dict:
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "lidar"}


@pytest.mark.parametrize(
    "over, field, shown",
    [({"height": -1, "width": -1}, "height", "-1"), ({"width": -1}, "width", "-1"), ({"height": -2}, "height", "-2"),
     ({"height": 1.5}, "height", "1.5"), ({"width": None}, "width", "None"), ({"height": True}, "height", "True"),
     ({"width": "3"}, "width", "'3'"), ({"width": NAN}, "width", "nan"), ({"width": 2**32}, "width", "4294967296"),
     ({"point_step": -24}, "point_step", "-24"), ({"row_step": None}, "row_step", "None"),
     ({"data": None}, "data", "None"), ({"data": "abc"}, "data", "'abc'"), ({"data": [256] * 72}, "data", "256"),
     ({"data": [1.5] * 72}, "data", "1.5"), ({"data": np.array([None] * 72)}, "data", "None"),
     ({"fields": None}, "fields", "None"), ({"fields": "xyz"}, "fields", "'xyz'"),
     ({"header": _stamped(INF)}, "header.stamp.sec", "inf"), ({"header": _stamped(NAN)}, "header.stamp.sec", "nan"),
     ({"header": _stamped(None)}, "header.stamp.sec", "None"), ({"header": _stamped("1")}, "header.stamp.sec", "'1'"),
     ({"header": _stamped(2**80)}, "header.stamp.sec", str(2**80)), ({"header": _stamped(1.0)}, "header.stamp.sec", "1.0"),
     ({"header": _stamped(True)}, "header.stamp.sec", "True"), ({"header": _stamped(INT32_MAX + 1)}, "header.stamp.sec", "2147483648"),
     ({"header": _stamped(INT32_MIN - 1)}, "header.stamp.sec", "-2147483649"),
     ({"header": _stamped(1, -1)}, "header.stamp.nanosec", "-1"), ({"header": _stamped(1, NS_PER_S)}, "header.stamp.nanosec", "1000000000"),
     ({"header": _stamped(1, None)}, "header.stamp.nanosec", "None"), ({"header": _stamped(1, 0.5)}, "header.stamp.nanosec", "0.5")],
)  # fmt: skip
def test_malformed_pointcloud2_is_a_named_value_error(over, field, shown):
    refused(lambda: decode_pointcloud2(as_msg(_cloud_msg(**over))), "sensor_msgs/PointCloud2", field, shown)


@pytest.mark.parametrize("attr, value", [("datatype", None), ("datatype", 7.0), ("count", -1), ("offset", -4), ("offset", NAN)])
def test_malformed_point_field_is_a_named_value_error(attr, value):
    fields = [{**f, attr: value} if f["name"] == "x" else f for f in _cloud_msg()["fields"]]
    refused(lambda: decode_pointcloud2(as_msg(_cloud_msg(fields=fields))), "sensor_msgs/PointCloud2 field 'x'", attr, repr(value))


@pytest.mark.parametrize("sec, nanosec, field, shown", [(INF, 0, "sec", "inf"), (None, 0, "sec", "None"), ("1", 0, "sec", "'1'"),
                                                        (2**80, 0, "sec", str(2**80)), (0, 10**9, "nanosec", "1000000000")])  # fmt: skip
def test_stamp_ns_names_the_field(sec, nanosec, field, shown):
    refused(lambda: stamp_ns(ns(sec=sec, nanosec=nanosec)), f"builtin_interfaces/Time.{field}", shown)


@pytest.mark.parametrize("data", [None, "abc", 3, [256], [-1], [1.5], [True], [None], np.array([None]),
                                  np.array([1, 256]), np.array([-1, 2]), np.array([1.0, 2.0]), np.array([1, 2], np.uint16) * 300])  # fmt: skip
def test_byte_view_refuses_what_is_no_uint8_payload(data):
    refused(lambda: byte_view(data, "sensor_msgs/Image.data"), "sensor_msgs/Image.data", type(data).__name__)


def test_valid_pointclouds_decode_as_before():
    plain = decode_pointcloud2(as_msg(_cloud_msg()))
    assert plain.points.tobytes() == POINTS.tobytes() and plain.stamp_ns == STAMP_NS
    np.testing.assert_array_equal(plain.time_s.astype(np.float32), TIMES)
    # numpy integers, as rosbags hands them over, and every payload type the three libraries use
    msg = _cloud_msg()
    sec, nanosec = divmod(STAMP_NS, NS_PER_S)
    for data in (msg["data"], bytearray(msg["data"]), np.frombuffer(msg["data"], np.uint8), array.array("B", msg["data"]),
                 list(msg["data"]), memoryview(msg["data"])):  # fmt: skip
        numpy_ints = _cloud_msg(height=np.uint32(1), width=np.uint32(3), point_step=np.uint32(24), row_step=np.uint32(72),
                                header={"stamp": {"sec": np.int32(sec), "nanosec": np.uint32(nanosec)}, "frame_id": "lidar"},
                                data=data)  # fmt: skip
        cloud = decode_pointcloud2(as_msg(numpy_ints))
        assert cloud.points.tobytes() == plain.points.tobytes() and cloud.stamp_ns == STAMP_NS
    # the int32 ends of a stamp, and an empty cloud
    for sec, nanosec in ((INT32_MAX, NS_PER_S - 1), (INT32_MIN, 0), (0, 0)):
        got = decode_pointcloud2(as_msg(_cloud_msg(header=_stamped(sec, nanosec))))
        assert got.stamp_ns == sec * NS_PER_S + nanosec
    empty = decode_pointcloud2(as_msg(pointcloud2_message(POINTS[:0], STAMP_NS, "lidar", TIMES[:0])))
    assert empty.points.shape == (0, 5) and empty.stamp_ns == STAMP_NS
    assert stamp_ns(ns(sec=1, nanosec=2)) == NS_PER_S + 2


# ---- M4: slice_from_message ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("duration, shown", [(NAN, "nan"), (INF, "inf"), (-INF, "-inf"), (-1.0, "-1.0"), (0.0, "0.0"), (0, "0"),
                                             (None, "None"), ("0.05", "'0.05'"), (True, "True"), (10**400, "digits")])  # fmt: skip
def test_slice_from_message_refuses_a_bad_sweep_duration(duration, shown):
    cloud = decode_pointcloud2(as_msg(_cloud_msg()))
    refused(lambda: slice_from_message(cloud, 8, sweep_duration_s=duration), "slice_from_message", "sweep_duration_s", shown)


@pytest.mark.parametrize("index, shown", [(True, "True"), (False, "False"), (np.bool_(True), "True"), (1.0, "1.0"), ("1", "'1'"),
                                          (-1, "-1"), (8, "8"), (NAN, "nan")])  # fmt: skip
def test_slice_from_message_refuses_a_bad_index(index, shown):
    cloud = decode_pointcloud2(as_msg(_cloud_msg()))
    refused(lambda: slice_from_message(cloud, 8, index=index), "slice_from_message", "slice index", shown)


def test_slice_from_message_valid_path_is_unchanged():
    cloud = decode_pointcloud2(as_msg(_cloud_msg()))
    for index, duration in ((None, 0.05), (3, 0.05), (np.int64(3), np.float32(0.1)), (0, 1)):
        s = slice_from_message(cloud, 8, index=index, sweep_duration_s=duration)
        most = np.bincount(slice_index_of(cloud.points[:, 0], cloud.points[:, 1], 8, 0.0), minlength=8).argmax()
        expected_index = int(most) if index is None else int(index)
        assert s.index == expected_index and s.points.shape == (3, 6)
        np.testing.assert_array_equal(s.points[:, 5], expected_index)
        np.testing.assert_array_equal(s.points[:, 4], relative_time_s(cloud.points, 0.0, duration).astype(np.float32))
        assert s.scan_time_ns == STAMP_NS + round(float(cloud.time_s.max()) * NS_PER_S)


# ---- L4: Detection3DArray and MarkerArray --------------------------------------------------------------------------


def _boxes(n: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(4)
    boxes = np.c_[rng.uniform(-40, 40, (n, 3)), rng.uniform(0.5, 5, (n, 3)), rng.uniform(-3, 3, n), rng.normal(size=(n, 2))]
    return boxes.astype(np.float32), rng.uniform(0, 1, n).astype(np.float32), np.arange(n)


@pytest.mark.parametrize("score, shown", [(NAN, "nan"), (INF, "inf"), (-INF, "-inf")])
def test_non_finite_scores_are_refused(score, shown):
    boxes, scores, labels = _boxes()
    scores[1] = score
    refused(lambda: detection3d_array_message(boxes, scores, labels, STAMP_NS, "l"), "vision_msgs/Detection3DArray", "score of box 1", shown)
    refused(lambda: marker_array_message(boxes, labels, STAMP_NS, "l", scores=scores), "visualization_msgs/MarkerArray", "score of box 1", shown)


@pytest.mark.parametrize("column", [3, 4, 5])  # w, l, h
@pytest.mark.parametrize("size, needle", [(0.0, "size w, l, h"), (-1.0, "size w, l, h"), (NAN, "NaN or infinite"), (INF, "NaN or infinite")])
def test_zero_negative_and_non_finite_sizes_are_refused(column, size, needle):
    boxes, scores, labels = _boxes()
    boxes[2, column] = size
    text = refused(lambda: detection3d_array_message(boxes, scores, labels, STAMP_NS, "l"), "vision_msgs/Detection3DArray", needle, "box 2")
    assert str(size) in text
    refused(lambda: marker_array_message(boxes, labels, STAMP_NS, "l"), "visualization_msgs/MarkerArray", needle, "box 2")


@pytest.mark.parametrize("alpha, shown", [(NAN, "nan"), (INF, "inf"), (-0.1, "-0.1"), (1.5, "1.5"), (None, "None"), ("0.5", "'0.5'"), (True, "True")])
def test_marker_alpha_must_be_in_0_1(alpha, shown):
    boxes, scores, labels = _boxes()
    refused(lambda: marker_array_message(boxes, labels, STAMP_NS, "l", alpha=alpha), "visualization_msgs/MarkerArray", "alpha", shown)


@pytest.mark.parametrize("bad, shown", [("x", "'x'"), (1.5, "1.5"), (True, "True"), (2**31, "2147483648")])
def test_marker_stale_ids_must_be_int32(bad, shown):
    boxes, _, labels = _boxes()
    refused(lambda: marker_array_message(boxes, labels, STAMP_NS, "l", stale_ids=[4, bad]), "visualization_msgs/MarkerArray", "stale_ids", shown)


@pytest.mark.parametrize("field", ["boxes", "scores"])
@pytest.mark.parametrize("value", [None, "abc", [["a"] * 9]])
def test_detection_arrays_that_are_no_numbers_are_refused(field, value):
    boxes, scores, labels = _boxes()
    args = {"boxes": boxes, "scores": scores, **{field: value}}
    refused(lambda: detection3d_array_message(args["boxes"], args["scores"], labels, STAMP_NS, "l"), "vision_msgs/Detection3DArray", field)


def test_valid_detections_and_markers_are_unchanged():
    boxes, scores, labels = _boxes()
    msg = detection3d_array_message(boxes, scores, labels, STAMP_NS, "l")
    assert [d["results"][0]["hypothesis"]["score"] for d in msg["detections"]] == [float(s) for s in scores]
    assert [list(d["bbox"]["size"].values()) for d in msg["detections"]] == [[float(b[4]), float(b[3]), float(b[5])] for b in boxes]
    for alpha in (0, 0.5, 1, np.float32(0.25)):
        markers = marker_array_message(boxes, labels, STAMP_NS, "l", scores=scores, alpha=alpha, stale_ids=[np.int64(5)])["markers"]
        assert [m["color"]["a"] for m in markers if m["type"] == 1 and m["action"] == 0] == [float(alpha)] * 3
        assert [(m["ns"], m["id"]) for m in markers if m["action"] == 2] == [("streamdet", 5), ("streamdet/labels", 5)]
    no_scores = marker_array_message(boxes, labels, STAMP_NS, "l")["markers"]
    assert [m["text"] for m in no_scores if m["type"] == 9] == list(CLASS_NAMES[:3])
    assert detection3d_array_message(np.zeros((0, 9)), np.zeros(0), np.zeros(0, int), STAMP_NS, "l")["detections"] == []


# ---- L5: sensor_msgs/CameraInfo ------------------------------------------------------------------------------------

K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])


def _info(**over) -> dict:
    return {**camera_info_message(K, 640, 480, STAMP_NS, "cam"), **over}


def _k(index: int, value) -> list:
    k = K.reshape(-1).tolist()
    k[index] = value
    return k


@pytest.mark.parametrize(
    "over, field, shown",
    [({"k": [NAN] * 9}, "k holds non-finite", "nan"), ({"k": _k(2, INF)}, "k holds non-finite", "inf"),
     ({"k": _k(0, NAN)}, "k holds non-finite", "nan"), ({"k": _k(4, -INF)}, "k holds non-finite", "-inf"),
     ({"k": [0.0] * 9}, "k focal lengths", "fx=0.0"), ({"k": _k(0, -500.0)}, "k focal lengths", "fx=-500.0"),
     ({"k": _k(4, 0.0)}, "k focal lengths", "fy=0.0"), ({"k": ["a"] * 9}, "k must be a list of numbers", "'a'"),
     ({"k": None}, "k must be a list of numbers", "None"), ({"k": [1.0, None] + [0.0] * 7}, "k must be a list of numbers", "None"),
     ({"d": None}, "d must be a list of numbers", "None"), ({"d": "0"}, "d must be a list of numbers", "'0'"),
     ({"d": [NAN]}, "d=[nan] holds non-finite", "nan"),
     ({"binning_x": -1}, "binning_x", "-1"), ({"binning_y": None}, "binning_y", "None"), ({"binning_x": 1.5}, "binning_x", "1.5"),
     ({"width": NAN}, "width", "nan"), ({"height": None}, "height", "None"), ({"width": -640}, "width", "-640"),
     ({"roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": -1, "do_rectify": False}}, "roi.width", "-1")],
)  # fmt: skip
def test_malformed_camera_info_is_a_named_value_error(over, field, shown):
    refused(lambda: camera_info_intrinsics(as_msg(_info(**over))), "sensor_msgs/CameraInfo of 'cam'", field, shown)


@pytest.mark.parametrize("p, shown", [([NAN] * 12, "nan"), (_k(0, 500.0)[:3] + [INF] + _k(0, 500.0)[3:6] + [0.0] + K[2].tolist() + [0.0], "inf"),
                                      ([0.0] * 12, "fx=0.0")])  # fmt: skip
def test_malformed_projection_is_refused(p, shown):
    refused(lambda: camera_info_intrinsics(as_msg(_info(p=p)), intrinsics="p"), "sensor_msgs/CameraInfo of 'cam'", "p ", shown)


def test_valid_camera_info_is_unchanged():
    expected = {"camera_intrinsic": K.tolist(), "width": 640, "height": 480}
    assert camera_info_intrinsics(as_msg(_info())) == expected
    # rosbags gives numpy arrays and integers, rclpy array.array for d
    numpy_style = _info(k=K.reshape(-1), d=array.array("d", [0.0] * 5), width=np.uint32(640), height=np.uint32(480),
                        binning_x=np.uint32(1), binning_y=0)  # fmt: skip
    assert camera_info_intrinsics(as_msg(numpy_style)) == expected
    assert camera_info_intrinsics(as_msg(_info(d=[]))) == expected
    P = np.c_[K * [[0.9], [0.9], [1]], [0.0, 0, 0]]
    rectified = camera_info_intrinsics(as_msg(_info(d=[0.1, 0, 0, 0, 0], p=P.reshape(-1).tolist())), intrinsics="p")
    np.testing.assert_array_equal(rectified["camera_intrinsic"], P[:, :3])
    # a stereo pair's second camera (Tx = -fx' * baseline) is refused by name: which frame P's points are in, TF's
    # or the first camera's rectified one, the message cannot tell (tests/test_ros_embed_review.py)
    stereo = np.c_[P[:, :3], [10.0, 0, 0]]
    refused(lambda: camera_info_intrinsics(as_msg(_info(d=[0.1, 0, 0, 0, 0], p=stereo.reshape(-1).tolist())), intrinsics="p"),
            "sensor_msgs/CameraInfo of 'cam'", "p's 4th column [Tx, Ty, Tz] = [10.0, 0.0, 0.0]", "stereo")


# ---- M2 and L6: TfBuffer -------------------------------------------------------------------------------------------

IDENTITY = {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]}
POSE = {"rotation": [math.cos(0.1), 0.0, 0.0, math.sin(0.1)], "translation": [1.0, 2.0, 3.0]}


def _ts(parent="map", child="base_link", stamp=NS_PER_S, record=POSE, **edit) -> dict:
    msg = transform_stamped_msg(parent, child, record, stamp)
    for path, value in edit.items():  # "header__stamp__sec"=... sets msg["header"]["stamp"]["sec"]
        *outer, last = path.split("__")
        node = msg
        for key in outer:
            node = node[key]
        node[last] = value
    return msg


def _buffer() -> TfBuffer:
    tf = TfBuffer()
    tf.add(as_msg({"transforms": [_ts("base_link", "lidar", 0, IDENTITY)]}), static=True)
    tf.add(as_msg({"transforms": [_ts(stamp=NS_PER_S), _ts(stamp=2 * NS_PER_S)]}))
    return tf


def _state(tf: TfBuffer):
    return copy.deepcopy((tf._parent, {k: (e.stamps, e.records, e.static) for k, e in tf._edges.items()}))


BAD_TRANSFORMS = {
    # a corrupt message from a wrong parent: before the fix, its parent link stayed and refused every valid one after
    "zero quaternion, wrong parent": (_ts("odom_typo", "base_link", transform__rotation={"x": 0, "y": 0, "z": 0, "w": 0}),
                                      "rotation [0.0, 0.0, 0.0, 0.0] must be a unit quaternion"),
    "NaN quaternion, new child": (_ts("map", "radar", transform__rotation={"x": 0, "y": 0, "z": 0, "w": NAN}), "rotation [nan"),
    "inf translation, new child": (_ts("map", "radar", transform__translation={"x": INF, "y": 0, "z": 0}), "translation [inf"),
    # a bad stamp on a new edge: before the fix, it left an empty edge and lookup raised a bare IndexError
    "nanosec 2e9, new edge": (_ts("map", "radar", header__stamp__nanosec=2 * NS_PER_S), "header.stamp.nanosec"),
    "sec inf": (_ts("map", "radar", header__stamp__sec=INF), "header.stamp.sec must be an integer"),
    "sec None, existing edge": (_ts(header__stamp__sec=None), "header.stamp.sec must be an integer"),
    "sec string": (_ts("map", "radar", header__stamp__sec="1"), "header.stamp.sec must be an integer"),
    "sec 2**80": (_ts("map", "radar", header__stamp__sec=2**80), "header.stamp.sec must be an integer"),
    "rotation w None": (_ts("map", "radar", transform__rotation={"x": 0, "y": 0, "z": 0, "w": None}), "transform.rotation.w"),
    "translation x string": (_ts("map", "radar", transform__translation={"x": "1", "y": 0, "z": 0}), "transform.translation.x"),
    "translation x 10**400": (_ts("map", "radar", transform__translation={"x": 10**400, "y": 0, "z": 0}), "transform.translation.x"),
    "parent None": (_ts(header__frame_id=None), "header.frame_id must be a non-empty frame id"),
    "child None": (_ts(child_frame_id=None), "child_frame_id must be a non-empty frame id"),
    "parent int": (_ts(header__frame_id=5), "header.frame_id must be a non-empty frame id"),
    "parent bytes": (_ts(header__frame_id=b"map"), "header.frame_id must be a non-empty frame id"),
    "child empty": (_ts(child_frame_id=""), "child_frame_id must be a non-empty frame id"),
    "child slash": (_ts(child_frame_id="/"), "child_frame_id must be a non-empty frame id"),
    "same frames": (_ts(child_frame_id="/map"), "two different frame ids"),
    "second parent": (_ts("odom", "base_link"), "frame 'base_link' has two parents"),
}


@pytest.mark.parametrize("static", [False, True])
@pytest.mark.parametrize("name", list(BAD_TRANSFORMS))
def test_a_refused_transform_changes_nothing(name, static):
    msg, needle = BAD_TRANSFORMS[name]
    tf = _buffer()
    before = _state(tf)
    refused(lambda: tf.add_transform(as_msg(msg), static), "geometry_msgs/TransformStamped", needle)
    assert _state(tf) == before
    # and as part of a TFMessage: the valid transform before it is not stored either (all or nothing)
    refused(lambda: tf.add(as_msg({"transforms": [_ts("map", "gps", 3 * NS_PER_S), msg]}), static), "geometry_msgs/TransformStamped")
    assert _state(tf) == before
    # later valid transforms and lookups work: no stray parent, no empty edge (a bare IndexError before)
    tf.add_transform(as_msg(_ts(stamp=3 * NS_PER_S)))
    assert tf.lookup("map", "base_link", 3 * NS_PER_S) == POSE
    assert tf.lookup("map", "lidar", NS_PER_S)["translation"] == pytest.approx(POSE["translation"])
    with pytest.raises(KeyError, match="no TF path from 'map' to 'radar'"):
        tf.lookup("map", "radar", NS_PER_S)


def test_tf_message_without_a_transform_list_is_refused():
    tf = _buffer()
    before = _state(tf)
    refused(lambda: tf.add(ns(transforms=None)), "tf2_msgs/TFMessage.transforms", "None")
    assert _state(tf) == before


@pytest.mark.parametrize("value, shown", [(NAN, "nan"), (INF, "inf"), (-1, "-1"), (-1.0, "-1.0"), (0.5, "0.5"), (None, "None"),
                                          ("5", "'5'"), (True, "True"), (np.float64(NAN), "nan")])  # fmt: skip
def test_max_extrapolation_must_be_a_whole_non_negative_number(value, shown):
    refused(lambda: TfBuffer(max_extrapolation_ns=value), "TfBuffer.max_extrapolation_ns", shown)


@pytest.mark.parametrize("parent, child, shown", [(None, "base_link", "None"), ("map", None, "None"), ("", "base_link", "''"),
                                                  ("map", 3, "3")])  # fmt: skip
def test_lookup_refuses_a_frame_that_is_no_str(parent, child, shown):
    refused(lambda: _buffer().lookup(parent, child, NS_PER_S), "TfBuffer.lookup", "frame id", shown)


def test_valid_tf_is_unchanged():
    for value, expected in ((0, 0), (1_000, 1_000), (5e7, 50_000_000), (np.int64(10), 10), (10**30, 10**30)):
        tf = TfBuffer(max_extrapolation_ns=value)
        assert tf.max_extrapolation_ns == expected and type(tf.max_extrapolation_ns) is int
    tf = _buffer()
    assert tf.lookup("map", "base_link", NS_PER_S) == POSE  # the message's own numbers, untouched
    assert tf.lookup("/map", "/base_link", 2 * NS_PER_S) == POSE  # a leading slash names the same frame
    assert tf.frames == {"map", "base_link", "lidar"}
    # numpy stamps and integer components, as rosbags and hand-written messages give them
    tf.add_transform(as_msg(_ts("base_link", "cam", header__stamp__sec=np.int32(1), header__stamp__nanosec=np.uint32(0),
                                transform__rotation={"x": 0, "y": 0, "z": 0, "w": 1})))  # fmt: skip
    assert tf.lookup("base_link", "cam", NS_PER_S) == {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": POSE["translation"]}
    with pytest.raises(ValueError, match=r"at 3000000000 ns is outside its 2 stamps"):
        tf.lookup("map", "base_link", 3 * NS_PER_S)


# ---- what the helper left: raw image sizes, stamps and frame ids written out ----------------------------------------
@pytest.mark.parametrize("field, bad", [("width", float("nan")), ("height", None), ("step", "4800"), ("width", True)])
def test_raw_image_sizes_must_be_integers(field, bad):
    from types import SimpleNamespace as ns

    from streamdet.runtime_ort.ros.images import image_to_rgb

    msg = ns(encoding="rgb8", height=2, width=2, step=6, data=bytes(12), header=ns(stamp=ns(sec=1, nanosec=0), frame_id="c"))
    setattr(msg, field, bad)
    with pytest.raises(ValueError, match=rf"sensor_msgs/Image.{field} must be an integer"):
        image_to_rgb(msg)


@pytest.mark.parametrize("ns_, frame, said", [(1.5, "lidar", "whole nanoseconds"), (None, "lidar", "whole nanoseconds"),
                                             (10, None, "frame_id must be a non-empty string"), (10, "", "frame_id")])  # fmt: skip
def test_written_headers_refuse_what_ros_cannot_carry(ns_, frame, said):
    from streamdet.runtime_ort.ros.header import header_msg

    with pytest.raises(ValueError, match=said):
        header_msg(ns_, frame)
    assert header_msg(1_500_000_123, "lidar") == {"stamp": {"sec": 1, "nanosec": 500_000_123}, "frame_id": "lidar"}


@pytest.mark.parametrize("data", [
    np.array([1, 2, 255], np.int64),  # np.array(list(msg.data)): values, not eight raw bytes each
    np.array([1, 2, 255], np.uint16),
    array.array("q", [1, 2, 255]),
    memoryview(bytes([1, 0, 2, 0, 255]))[::2],  # a strided view: its elements
    [1, 2, 255],
    bytes([1, 2, 255]),
])  # fmt: skip
def test_byte_view_takes_payload_elements_by_value(data):
    from streamdet.runtime_ort.ros.header import byte_view

    np.testing.assert_array_equal(byte_view(data), np.array([1, 2, 255], np.uint8))
