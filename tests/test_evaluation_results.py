"""streamdet boxes <-> nuScenes results entries and files, on the real sample's boxes and calibration."""

from __future__ import annotations

import importlib.resources
import json

import numpy as np
import pytest

from streamdet.core.boxes import YAW
from streamdet.core.classes import CLASS_NAMES
from streamdet.evaluation import (
    EvalBoxes,
    boxes_to_gt,
    boxes_to_results,
    global_to_lidar,
    lidar_to_global,
    load_gt_and_predictions,
    read_results_json,
    results_to_boxes,
    write_results_json,
)
from streamdet.core.rotations import quaternion_to_matrix
from streamdet.evaluation.results import default_attribute, load_eval_inputs

SAMPLE = importlib.resources.files("streamdet.data") / "nuscenes_sample"
CALIB = json.loads((SAMPLE / "calibration.json").read_text())
BOXES = json.loads((SAMPLE / "boxes.json").read_text())["boxes"]
L2E = np.array(CALIB["lidar"]["sensor2ego"]["matrix"])
E2G = np.array(CALIB["lidar"]["ego2global"]["matrix"])
TOKEN = CALIB["sample_token"]
META = {"use_camera": True, "use_lidar": True}


def _sample_boxes(with_nan_velocity: bool = False):
    rows = [b for b in BOXES if b["class_name"] is not None and (with_nan_velocity or b["velocity_xy"] is not None)]
    boxes = np.array(
        [b["center_xyz"] + b["size_wlh"] + [b["yaw"]] + (b["velocity_xy"] or [np.nan, np.nan]) for b in rows], dtype=float
    )  # (N, 9)
    labels = np.array([CLASS_NAMES.index(b["class_name"]) for b in rows], dtype=np.int64)
    return rows, boxes, labels


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_lidar_to_global_matches_center_global_and_round_trips():
    rows, boxes, _ = _sample_boxes()
    translation, size, rotation, velocity = lidar_to_global(boxes, L2E, E2G)
    np.testing.assert_allclose(translation, [b["center_global"] for b in rows], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(size, boxes[:, 3:6])
    np.testing.assert_allclose(np.linalg.norm(rotation, axis=1), 1.0, atol=1e-12)
    assert np.all(rotation[:, 0] >= 0)
    back = global_to_lidar(translation, size, rotation, velocity, L2E, E2G)
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], rtol=0, atol=1e-9)
    np.testing.assert_allclose(_wrap(back[:, YAW] - boxes[:, YAW]), 0.0, atol=1e-12)
    np.testing.assert_allclose(back[:, 7:], boxes[:, 7:], rtol=0, atol=1e-9)
    # The sample's first box is nuScenes annotation ef63a697...: global centre [373.256, 1130.419, 0.800].
    np.testing.assert_allclose(translation[0], [373.256, 1130.419, 0.800], atol=5e-4)


def test_global_yaw_is_lidar_yaw_plus_ego_heading():
    """A yaw-only lidar box seen in the global frame: heading = lidar yaw + the lidar's global heading."""
    _, boxes, _ = _sample_boxes()
    _, _, rotation, _ = lidar_to_global(boxes, L2E, E2G)
    r = quaternion_to_matrix(rotation)
    lidar_heading = np.arctan2((E2G @ L2E)[1, 0], (E2G @ L2E)[0, 0])
    np.testing.assert_allclose(_wrap(np.arctan2(r[:, 1, 0], r[:, 0, 0]) - boxes[:, YAW] - lidar_heading), 0, atol=2e-3)


def test_results_entries_round_trip_and_attributes():
    _, boxes, labels = _sample_boxes()
    scores = np.linspace(0.9, 0.1, len(boxes)).astype(np.float32)
    entries = boxes_to_results(TOKEN, boxes, scores, labels, L2E, E2G)
    assert {e["detection_name"] for e in entries} <= set(CLASS_NAMES)
    for e in entries:
        assert e["attribute_name"] == default_attribute(e["detection_name"], e["velocity"])
    b2, s2, l2 = results_to_boxes(entries, L2E, E2G)
    np.testing.assert_allclose(b2[:, :6], boxes[:, :6], atol=1e-9)
    np.testing.assert_array_equal(s2, scores)
    np.testing.assert_array_equal(l2, labels)
    assert default_attribute("car", [1.0, 0.0]) == "vehicle.moving" and default_attribute("bus", [0, 0]) == "vehicle.stopped"
    assert default_attribute("pedestrian", [0, 0]) == "pedestrian.standing" and default_attribute("barrier", [3, 0]) == ""


def test_gt_entries_carry_ego_translation_and_num_pts():
    rows, boxes, labels = _sample_boxes(with_nan_velocity=True)
    num_pts = np.array([b["num_lidar_pts"] + b["num_radar_pts"] for b in rows], dtype=np.int64)
    entries = boxes_to_gt(TOKEN, boxes, labels, num_pts, L2E, E2G)
    gt = EvalBoxes.from_results({TOKEN: entries})
    np.testing.assert_allclose(gt.ego_dist, [b["ego_dist_xy"] for b in rows], atol=1e-9)
    np.testing.assert_array_equal(gt.num_pts, num_pts)
    assert np.isnan(gt.velocity).any()  # unknown GT velocity survives as NaN


def test_files_round_trip_and_ego_positions(tmp_path):
    rows, boxes, labels = _sample_boxes(with_nan_velocity=True)
    num_pts = np.array([b["num_lidar_pts"] + b["num_radar_pts"] for b in rows], dtype=np.int64)
    gt_path, pred_path = tmp_path / "gt.json", tmp_path / "pred.json"
    write_results_json(gt_path, {TOKEN: boxes_to_gt(TOKEN, boxes, labels, num_pts, L2E, E2G), "empty": []}, META,
                       ego_positions={TOKEN: E2G[:3, 3].tolist(), "empty": [0.0, 0.0, 0.0]})  # fmt: skip
    pred_boxes = np.nan_to_num(boxes)
    write_results_json(pred_path, {TOKEN: boxes_to_results(TOKEN, pred_boxes, np.full(len(boxes), 0.5), labels, L2E, E2G),
                                   "empty": []}, META)  # fmt: skip
    doc = json.loads(pred_path.read_text())
    assert doc["meta"] == {"use_camera": True, "use_lidar": True, "use_radar": False, "use_map": False, "use_external": False}
    assert "null" in gt_path.read_text() and "NaN" not in gt_path.read_text()  # strict JSON
    f = read_results_json(gt_path)
    assert f.ego_positions["empty"] == [0.0, 0.0, 0.0] and set(f.results) == {TOKEN, "empty"}
    gt, pred = load_gt_and_predictions(gt_path, pred_path)
    np.testing.assert_allclose(pred.ego_translation, gt.ego_translation, atol=1e-9)  # same centres, same ego
    assert list(pred.sample_tokens) == [TOKEN, "empty"]


def test_predictions_need_an_ego_position(tmp_path):
    gt_path, pred_path = tmp_path / "gt.json", tmp_path / "pred.json"
    write_results_json(gt_path, {"a": []}, META)
    _, boxes, labels = _sample_boxes()
    write_results_json(pred_path, {"a": boxes_to_results("a", boxes[:1], [0.5], labels[:1], L2E, E2G)}, META)
    with pytest.raises(ValueError, match="no ego position for sample 'a'"):
        load_gt_and_predictions(gt_path, pred_path)


@pytest.mark.parametrize(
    "text, message",
    [
        ("{", "not valid JSON"),
        ("[]", "'results'"),
        ('{"meta": {}}', "'results'"),
        ('{"results": {"a": 3}}', "must be a list"),
        ('{"results": {}, "ego_positions": {"a": [1, 2]}}', "ego_positions"),
    ],
)
def test_malformed_files(tmp_path, text, message):
    p = tmp_path / "bad.json"
    p.write_text(text)
    good = tmp_path / "good.json"
    write_results_json(good, {}, META)
    with pytest.raises(ValueError, match=message):
        load_gt_and_predictions(p, good)


def test_bad_arguments():
    _, boxes, labels = _sample_boxes()
    with pytest.raises(ValueError, match="boxes must have shape"):
        boxes_to_results(TOKEN, boxes[:, :7], np.ones(len(boxes)), labels, L2E, E2G)
    with pytest.raises(ValueError, match="labels must index CLASS_NAMES"):
        boxes_to_results(TOKEN, boxes, np.ones(len(boxes)), labels + 10, L2E, E2G)
    with pytest.raises(ValueError, match="lidar2ego must be a rigid"):
        boxes_to_results(TOKEN, boxes, np.ones(len(boxes)), labels, 2 * L2E, E2G)
    with pytest.raises(ValueError, match="use_lidar"):
        write_results_json("unused.json", {}, {"use_camera": True})
    with pytest.raises(ValueError, match="one sample"):
        results_to_boxes([{"sample_token": "a"}, {"sample_token": "b"}], L2E, E2G)
    empty = boxes_to_results(TOKEN, np.zeros((0, 9)), np.zeros(0), np.zeros(0, np.int64), L2E, E2G)
    assert empty == [] and results_to_boxes([], L2E, E2G)[0].shape == (0, 9)


# ---- bike racks in a ground-truth file ---------------------------------------------------------------------------

RACK = [10.0, 5.0, 0.5, 1.0, 4.0, 1.2, 0.995, 0.0, 0.0, 0.0998]  # translation, size w l h, rotation w x y z


def test_bike_racks_round_trip_and_absent_is_not_empty(tmp_path):
    """A GT file's bike_racks come back as written (float64 through JSON exactly); a file without the key (written
    before racks were saved) reads as None, "racks unknown", and {} as "no rack anywhere"."""
    _, boxes, labels = _sample_boxes()
    num_pts = np.ones(len(boxes), dtype=np.int64)
    entries = {TOKEN: boxes_to_gt(TOKEN, boxes, labels, num_pts, L2E, E2G), "other": []}
    pred = tmp_path / "pred.json"
    write_results_json(pred, {TOKEN: [], "other": []}, META)
    racks = {TOKEN: np.array([RACK, [0.1 + 0.2, -3.0, 0.3, 0.7, 2.0, 1.0, 1.0, 0.0, 0.0, 0.0]])}
    cases = {"with": racks, "empty": {}, "none": None}
    for name, value in cases.items():
        write_results_json(tmp_path / f"{name}.json", entries, META, ego_positions={"other": [0.0, 0.0, 0.0]},
                           bike_racks=value)  # fmt: skip
    got = load_eval_inputs(tmp_path / "with.json", pred)
    assert set(got.bike_racks) == {TOKEN}
    np.testing.assert_array_equal(got.bike_racks[TOKEN], racks[TOKEN])  # bit for bit
    assert got.bike_racks[TOKEN].dtype == np.float64 and got.bike_racks[TOKEN].shape == (2, 10)
    assert load_eval_inputs(tmp_path / "empty.json", pred).bike_racks == {}
    assert load_eval_inputs(tmp_path / "none.json", pred).bike_racks is None
    assert "bike_racks" not in json.loads((tmp_path / "none.json").read_text())
    assert read_results_json(tmp_path / "with.json").bike_racks[TOKEN].shape == (2, 10)
    # a results file (no key) reads as it always did
    assert read_results_json(pred).bike_racks is None


@pytest.mark.parametrize(
    "racks, message",
    [
        ([RACK], "bike_racks must map sample tokens"),
        ({"a": RACK}, r"bike_racks\['a'\]\[0\] must be 10 finite numbers .* got 10.0"),
        ({"a": [RACK[:9]]}, r"must be 10 finite numbers .* got \[10.0, 5.0"),
        ({"a": [[*RACK[:9], "x"]]}, r"must be 10 finite numbers .*'x'"),
        ({"a": [[*RACK[:9], True]]}, r"must be 10 finite numbers .*True"),
        ({"a": [[float("nan"), *RACK[1:]]]}, r"must be 10 finite numbers .*nan"),
        ({"a": [[*RACK[:3], 0.0, *RACK[4:]]]}, r"sizes > 0 and a non-zero quaternion, got \[10.0, 5.0, 0.5, 0.0"),
        ({"a": [[*RACK[:6], 0, 0, 0, 0]]}, r"non-zero quaternion, got .*0, 0, 0, 0\]"),
        ({"a": 3}, r"bike_racks\['a'\] must be a list of rack boxes, got 3"),
    ],
)
def test_malformed_bike_racks_are_refused_quoting_the_value(tmp_path, racks, message):
    """Read (a file) or written: the rack, its sample and the bad value are named."""
    good = tmp_path / "good.json"
    write_results_json(good, {"a": []}, META)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"results": {"a": []}, "bike_racks": racks}, allow_nan=True))
    with pytest.raises(ValueError, match=message):
        load_eval_inputs(bad, good)
    with pytest.raises(ValueError, match=f"{bad}: bike_racks"):
        read_results_json(bad)
    with pytest.raises(ValueError, match=message):
        write_results_json(tmp_path / "never.json", {"a": []}, META, bike_racks=racks)
    assert not (tmp_path / "never.json").exists()


def test_bike_racks_of_a_sample_the_ground_truth_lacks_are_refused(tmp_path):
    gt, pred = tmp_path / "gt.json", tmp_path / "pred.json"
    write_results_json(gt, {"a": []}, META, ego_positions={"a": [0.0, 0.0, 0.0]}, bike_racks={"b": [RACK]})
    write_results_json(pred, {"a": []}, META)
    with pytest.raises(ValueError, match=r"bike_racks names sample 'b', which its results do not hold"):
        load_eval_inputs(gt, pred)
    write_results_json(gt, {"a": []}, META, ego_positions={"a": [0.0, 0.0, 0.0]}, bike_racks={"a": []})
    assert load_eval_inputs(gt, pred).bike_racks["a"].shape == (0, 10)  # a sample without racks
