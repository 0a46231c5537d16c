"""Detections -> vision_msgs/Detection3DArray and visualization_msgs/MarkerArray, read back field by field."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.core.boxes import box_corners_3d
from streamdet.core.classes import CLASS_COLORS_RGB, CLASS_NAMES, OTHER_COLOR_RGB
from streamdet.runtime_ort.ros.detections import (
    CUBE,
    DELETE,
    DELETEALL,
    TEXT_VIEW_FACING,
    detection3d_array_message,
    marker_array_message,
)

STAMP = 1_600_000_000_250_000_000


def _boxes(seed: int, n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    boxes = np.c_[rng.uniform(-40, 40, (n, 3)), rng.uniform(0.5, 5, (n, 3)), rng.uniform(-np.pi, np.pi, n), rng.normal(size=(n, 2))]
    return boxes.astype(np.float32), rng.uniform(0, 1, n).astype(np.float32), rng.integers(0, len(CLASS_NAMES), n)


def _corners_from_pose(pose: dict, size: dict) -> np.ndarray:
    """A box pose + size read the ROS way (size along the pose's own axes) -> (8, 3) corners, in our corner order."""
    q = pose["orientation"]
    yaw = 2 * np.arctan2(q["z"], q["w"])
    assert q["x"] == 0 and q["y"] == 0
    box = np.array([[pose["position"]["x"], pose["position"]["y"], pose["position"]["z"], size["y"], size["x"], size["z"], yaw, 0, 0]])
    return box_corners_3d(box)[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_detection3d_array_carries_class_score_and_the_same_box(seed: int):
    boxes, scores, labels = _boxes(seed)
    msg = detection3d_array_message(boxes, scores, labels, STAMP, "LIDAR_TOP")
    assert msg["header"] == {"stamp": {"sec": 1_600_000_000, "nanosec": 250_000_000}, "frame_id": "LIDAR_TOP"}
    assert len(msg["detections"]) == len(boxes)
    for i, d in enumerate(msg["detections"]):
        (hyp,) = d["results"]
        assert hyp["hypothesis"]["class_id"] == CLASS_NAMES[labels[i]]
        assert hyp["hypothesis"]["score"] == float(scores[i])
        assert d["header"]["frame_id"] == "LIDAR_TOP" and d["id"] == ""
        assert d["bbox"]["size"] == {"x": float(boxes[i, 4]), "y": float(boxes[i, 3]), "z": float(boxes[i, 5])}  # l, w, h
        np.testing.assert_allclose(_corners_from_pose(d["bbox"]["center"], d["bbox"]["size"]), box_corners_3d(boxes[i : i + 1].astype(np.float64))[0], atol=1e-5)
        assert hyp["pose"]["pose"] == d["bbox"]["center"] and len(hyp["pose"]["covariance"]) == 36
        q = d["bbox"]["center"]["orientation"]
        assert np.isclose(q["x"] ** 2 + q["y"] ** 2 + q["z"] ** 2 + q["w"] ** 2, 1.0)


def test_empty_detections():
    msg = detection3d_array_message(np.zeros((0, 9)), np.zeros(0), np.zeros(0, np.int64), STAMP, "l")
    assert msg["detections"] == []
    assert marker_array_message(np.zeros((0, 9)), np.zeros(0, np.int64), STAMP, "l")["markers"] == []


def test_markers_coloured_by_class_with_text_labels():
    boxes, scores, labels = _boxes(3, 4)
    labels = np.array([0, 7, -1, 9])
    msg = marker_array_message(boxes, labels, STAMP, "LIDAR_TOP", scores=scores, ns="det", lifetime_s=0.25, replace=True,
                               stale_ids=[4, 5])  # fmt: skip
    markers = msg["markers"]
    assert markers[0]["action"] == DELETEALL
    cubes = [m for m in markers if m["type"] == CUBE and m["action"] == 0 and m["ns"] == "det"]
    texts = [m for m in markers if m["type"] == TEXT_VIEW_FACING]
    assert [m["id"] for m in cubes] == [0, 1, 2, 3] and [m["ns"] for m in texts] == ["det/labels"] * 4
    # the same colours as the preview pictures (core.classes), as ColorRGBA's 0..1
    expected_colours = [tuple(v / 255 for v in c) for c in (CLASS_COLORS_RGB[0], CLASS_COLORS_RGB[7], OTHER_COLOR_RGB, CLASS_COLORS_RGB[9])]
    for cube, text, colour, i in zip(cubes, texts, expected_colours, range(4)):
        assert (cube["color"]["r"], cube["color"]["g"], cube["color"]["b"]) == colour and cube["color"]["a"] == 0.5
        assert cube["scale"] == {"x": float(boxes[i, 4]), "y": float(boxes[i, 3]), "z": float(boxes[i, 5])}
        assert cube["lifetime"] == {"sec": 0, "nanosec": 250_000_000}
        assert text["pose"]["position"]["z"] > cube["pose"]["position"]["z"] + float(boxes[i, 5]) / 2
    assert [t["text"] for t in texts] == [f"car {scores[0]:.2f}", f"pedestrian {scores[1]:.2f}", f"other {scores[2]:.2f}",
                                          f"barrier {scores[3]:.2f}"]  # fmt: skip
    deletes = [(m["ns"], m["id"]) for m in markers if m["action"] == DELETE]
    assert deletes == [("det", 4), ("det/labels", 4), ("det", 5), ("det/labels", 5)]
    named = marker_array_message(boxes, labels, STAMP, "l", names=["a", "b", "c", "d"])
    assert [m["text"] for m in named["markers"] if m["type"] == TEXT_VIEW_FACING] == ["a", "b", "c", "d"]


def test_refusals():
    boxes, scores, labels = _boxes(0, 3)
    with pytest.raises(ValueError, match=r"boxes must be \(N, 9\)"):
        detection3d_array_message(boxes[:, :7], scores, labels, STAMP, "l")
    with pytest.raises(ValueError, match=r"scores and labels must be \(3,\)"):
        detection3d_array_message(boxes, scores[:2], labels, STAMP, "l")
    with pytest.raises(ValueError, match=r"labels \[-1\] are outside 0..9"):
        detection3d_array_message(boxes, scores, np.array([0, -1, 2]), STAMP, "l")
    with pytest.raises(ValueError, match=r"labels \[10\] are outside 0..9"):
        marker_array_message(boxes, np.array([0, 10, 2]), STAMP, "l")
    with pytest.raises(ValueError, match="labels must be integers"):
        marker_array_message(boxes, np.array([0.0, 1.0, 2.0]), STAMP, "l")
    bad = boxes.copy()
    bad[1, 6] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        detection3d_array_message(bad, scores, labels, STAMP, "l")
    with pytest.raises(ValueError, match="names must have 3 entries"):
        marker_array_message(boxes, labels, STAMP, "l", names=["a"])
    with pytest.raises(ValueError, match="a duration must be >= 0 s"):
        marker_array_message(boxes, labels, STAMP, "l", lifetime_s=-1)
