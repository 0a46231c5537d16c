"""The nuScenes table reader (data/nuscenes.py) and the bundled-sample loader (data/sample.py), on real data.

The bundled sample ships as calibration.json + boxes.json, not as nuScenes tables, so the fixture writes a tiny
v1.0-mini-style table set from them (global boxes from the devkit's global centres, neighbouring annotations that
reproduce the stored velocities, a past sweep with a known ego motion) and the reader must give boxes.json back.
"""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from streamdet.calibration.camera import make_transform, matrix_to_quaternion, quaternion_to_matrix
from streamdet.core.classes import CLASS_NAMES
from streamdet.data.nuscenes import GLOBAL_ANNOTATIONS, NuScenesReader
from streamdet.data.sample import bundled_sample_dir, load_bundled_sample, load_image, load_points

SAMPLE_DIR = bundled_sample_dir()
CATEGORY = {
    "car": "vehicle.car", "truck": "vehicle.truck", "bus": "vehicle.bus.rigid", "bicycle": "vehicle.bicycle",
    "construction_vehicle": "vehicle.construction", "pedestrian": "human.pedestrian.adult",
    "traffic_cone": "movable_object.trafficcone", "barrier": "movable_object.barrier", None: "animal",
}
PAST_MOTION = make_transform(quaternion_to_matrix([math.cos(0.02), 0, 0, math.sin(0.02)]), [-0.9, 0.3, 0.0])  # ego(t-50ms) -> ego(t)


def _pose(entry) -> dict:
    return {"translation": entry["translation"], "rotation": entry["rotation_wxyz"]}


def _write_tables(root: Path) -> dict:
    calib = json.loads((SAMPLE_DIR / "calibration.json").read_text())
    boxes = json.loads((SAMPLE_DIR / "boxes.json").read_text())["boxes"]
    rows = {name: [] for name in ("category", "attribute", "instance", "sensor", "calibrated_sensor", "ego_pose", "scene",
                                  "sample", "sample_data", "sample_annotation", "log", "visibility", "map")}
    ts = calib["sample_timestamp_us"]
    sample = calib["sample_token"]
    rows["scene"].append({"token": "scene0", "name": "scene-0061", "log_token": "log0", "nbr_samples": 3,
                          "first_sample_token": "prev", "last_sample_token": "next", "description": ""})
    for token, t, prev, nxt in (("prev", ts - 500_000, "", sample), (sample, ts, "prev", "next"), ("next", ts + 500_000, sample, "")):
        rows["sample"].append({"token": token, "timestamp": t, "prev": prev, "next": nxt, "scene_token": "scene0"})

    def add_sensor(channel, modality, s2e, K, pose, filename, t, width, height, key=True, prev="", nxt="", token=None):
        if not any(r["channel"] == channel for r in rows["sensor"]):
            rows["sensor"].append({"token": f"sensor-{channel}", "channel": channel, "modality": modality})
            rows["calibrated_sensor"].append({"token": f"cs-{channel}", "sensor_token": f"sensor-{channel}",
                                              "camera_intrinsic": K, **_pose(s2e)})
        token = token or f"sd-{channel}"
        rows["ego_pose"].append({"token": f"ep-{token}", "timestamp": t, **pose})
        dst = root / ("samples" if key else "sweeps") / channel / Path(filename).name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if not dst.exists():  # a copy: a symlink out of the dataset root is refused (sample.dataset_file)
            shutil.copyfile(SAMPLE_DIR / filename, dst)
        rows["sample_data"].append({"token": token, "sample_token": sample, "ego_pose_token": f"ep-{token}",
                                    "calibrated_sensor_token": f"cs-{channel}", "timestamp": t, "fileformat": "jpg",
                                    "is_key_frame": key, "height": height, "width": width,
                                    "filename": str(dst.relative_to(root)), "prev": prev, "next": nxt})

    lidar = calib["lidar"]
    e2g = make_transform(quaternion_to_matrix(lidar["ego2global"]["rotation_wxyz"]), lidar["ego2global"]["translation"])
    past_e2g = e2g @ PAST_MOTION
    past_pose = {"translation": past_e2g[:3, 3].tolist(), "rotation": matrix_to_quaternion(past_e2g[:3, :3]).tolist()}
    add_sensor("LIDAR_TOP", "lidar", lidar["sensor2ego"], [], _pose(lidar["ego2global"]), lidar["file"], ts, 0, 0,
               prev="sd-LIDAR_TOP-past")
    add_sensor("LIDAR_TOP", "lidar", lidar["sensor2ego"], [], past_pose, lidar["file"], ts - 50_000, 0, 0, key=False,
               nxt="sd-LIDAR_TOP", token="sd-LIDAR_TOP-past")
    for cam in calib["cameras"]:
        add_sensor(cam["name"], "camera", cam["sensor2ego"], cam["K"], _pose(cam["ego2global"]), cam["file"],
                   cam["timestamp_us"], cam["width"], cam["height"])

    l2g = e2g @ make_transform(quaternion_to_matrix(lidar["sensor2ego"]["rotation_wxyz"]), lidar["sensor2ego"]["translation"])
    # Global velocity (vz = 0) whose lidar-frame xy is the stored velocity: solve the 2x2 block.
    block = l2g[:3, :3].T[:2, :2]
    for i, b in enumerate(boxes):
        rows["category"].append({"token": f"cat-{i}", "name": CATEGORY[b["class_name"]], "description": ""})
        rows["instance"].append({"token": f"inst-{i}", "category_token": f"cat-{i}", "nbr_annotations": 3,
                                 "first_annotation_token": f"ann-prev-{i}", "last_annotation_token": f"ann-next-{i}"})
        rot = l2g[:3, :3] @ quaternion_to_matrix([math.cos(b["yaw"] / 2), 0, 0, math.sin(b["yaw"] / 2)])
        q = matrix_to_quaternion(rot).tolist()
        centre = np.array(b["center_global"])
        v = np.zeros(3)
        known = None not in b["velocity_xy"]  # unknown velocity: a lone annotation, as in nuScenes
        if known:
            v[:2] = np.linalg.solve(block, np.array(b["velocity_xy"]))
        chain = (("prev", "prev", -0.5, "", f"ann-{i}"), ("", sample, 0.0, f"ann-prev-{i}", f"ann-next-{i}"), ("next", "next", 0.5, f"ann-{i}", ""))
        if not known:
            chain = (("", sample, 0.0, "", ""),)
            rows["instance"][-1].update(nbr_annotations=1, first_annotation_token=f"ann-{i}", last_annotation_token=f"ann-{i}")
        for tag, sample_token, offset, prev, nxt in chain:
            rows["sample_annotation"].append({
                "token": f"ann-{tag}-{i}" if tag else f"ann-{i}", "sample_token": sample_token, "instance_token": f"inst-{i}",
                "visibility_token": "4", "attribute_tokens": [], "translation": (centre + offset * v).tolist(),
                "size": b["size_wlh"], "rotation": q, "prev": prev, "next": nxt,
                "num_lidar_pts": b["num_lidar_pts"], "num_radar_pts": b["num_radar_pts"]})
    rows["log"].append({"token": "log0", "logfile": "n015-2018-07-24-11-22-45+0800", "vehicle": "n015",
                        "date_captured": "2018-07-24", "location": "singapore-onenorth"})
    rows["map"].append({"category": "semantic_prior", "token": "map0", "filename": "", "log_tokens": ["log0"]})
    table_dir = root / "v1.0-mini"
    table_dir.mkdir(parents=True, exist_ok=True)
    for name, r in rows.items():
        (table_dir / f"{name}.json").write_text(json.dumps(r))
    return {"calib": calib, "boxes": boxes, "l2g": l2g}


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc_bundled")
    info = _write_tables(root)
    return root, info


def test_reader_gives_back_the_bundled_boxes(tables):
    root, info = tables
    reader = NuScenesReader(root, "v1.0-mini")
    assert len(reader) == 3 and info["calib"]["sample_token"] in reader.sample_tokens
    s = reader.get(info["calib"]["sample_token"])
    ref = info["boxes"]
    assert s.points.shape == (34688, 5) and s.points.dtype == np.float32 and s.point_time_s is None
    assert s.gt_boxes.shape == (len(ref), 9)
    # boxes.json's global centres came through float32 matrices: ~1e-4 m
    np.testing.assert_allclose(s.gt_boxes[:, :3], [b["center_xyz"] for b in ref], atol=2e-3)
    np.testing.assert_allclose(s.gt_boxes[:, 3:6], [b["size_wlh"] for b in ref], atol=1e-9)
    yaw_err = np.mod(s.gt_boxes[:, 6] - [b["yaw"] for b in ref] + math.pi, 2 * math.pi) - math.pi
    assert np.abs(yaw_err).max() < 1e-6
    known = np.array([None not in b["velocity_xy"] for b in ref])
    assert (~known).sum() == 2
    np.testing.assert_allclose(s.gt_boxes[known, 7:9], [b["velocity_xy"] for b in ref if None not in b["velocity_xy"]], atol=1e-6)
    np.testing.assert_array_equal(s.velocity_valid, known)
    assert np.all(s.gt_boxes[~known, 7:9] == 0)
    np.testing.assert_array_equal(s.gt_labels, [b["label"] for b in ref])
    assert s.gt_names[0] == "pedestrian" and "animal" in s.gt_names
    np.testing.assert_array_equal(s.num_lidar_pts, [b["num_lidar_pts"] for b in ref])
    assert s.instance_tokens[0] == "inst-0" and s.annotation_tokens[0] == "ann-0"


def test_reader_builds_the_devkit_lidar2cam_chain(tables):
    root, info = tables
    s = NuScenesReader(root, "v1.0-mini").get(info["calib"]["sample_token"])
    assert s.rig.names == tuple(c["name"] for c in info["calib"]["cameras"])
    for cam in info["calib"]["cameras"]:
        got = s.rig.camera(cam["name"])
        np.testing.assert_allclose(got.K, cam["K"])
        # calibration.json stores lidar2cam from float32 matrices; the derived camera poses carry ~1e-4 m
        np.testing.assert_allclose(got.lidar2cam, cam["lidar2cam"]["matrix"], atol=5e-4)
        assert (got.width, got.height) == (cam["width"], cam["height"])
        assert s.image_paths[cam["name"]].name == cam["file"]
    images = s.load_images(size=(160, 90))
    assert images.shape == (6, 90, 160, 3) and images.dtype == np.uint8


def test_past_sweeps_move_into_the_key_frame(tables):
    root, info = tables
    reader = NuScenesReader(root, "v1.0-mini")
    token = info["calib"]["sample_token"]
    assert reader.get(token).sweeps == ()
    s = reader.get(token, num_past_sweeps=3)  # the chain holds one
    assert len(s.sweeps) == 1
    sweep = s.sweeps[0]
    assert sweep.time_lag_s == pytest.approx(0.05) and sweep.timestamp_us == s.timestamp_us - 50_000
    lidar = info["calib"]["lidar"]
    l2e = make_transform(quaternion_to_matrix(lidar["sensor2ego"]["rotation_wxyz"]), lidar["sensor2ego"]["translation"])
    expected = np.linalg.inv(l2e) @ PAST_MOTION @ l2e  # past LiDAR frame -> current LiDAR frame
    raw = load_points(SAMPLE_DIR / lidar["file"])
    ref = raw[:, :3].astype(np.float64) @ expected[:3, :3].T + expected[:3, 3]
    np.testing.assert_allclose(sweep.points[:, :3], ref, atol=1e-3)
    np.testing.assert_array_equal(sweep.points[:, 3:], raw[:, 3:])


def test_one_sided_and_missing_velocity(tmp_path):
    root = tmp_path / "nusc"
    _write_tables(root)
    path = root / "v1.0-mini" / "sample_annotation.json"
    anns = json.loads(path.read_text())
    for a in anns:  # cut every track after the key frame: one-sided difference; box 0 loses both neighbours
        if a["token"] == "ann-0":
            a["prev"] = a["next"] = ""
        elif not a["token"].startswith("ann-prev") and not a["token"].startswith("ann-next"):
            a["next"] = ""
    path.write_text(json.dumps(anns))
    s = NuScenesReader(root, "v1.0-mini").get(1)
    ref = json.loads((SAMPLE_DIR / "boxes.json").read_text())["boxes"]
    known = np.array([None not in b["velocity_xy"] for b in ref])
    known[0] = False
    assert not s.velocity_valid[0] and np.all(s.gt_boxes[0, 7:9] == 0)
    np.testing.assert_array_equal(s.velocity_valid, known)
    np.testing.assert_allclose(s.gt_boxes[known, 7:9], np.array([b["velocity_xy"] for b in ref], dtype=object)[known].tolist(), atol=1e-6)


def _devkit_box_velocity(first: dict, last: dict, t_first_us: int, t_last_us: int, centred: bool) -> np.ndarray:
    """nuscenes-devkit ``NuScenes.box_velocity`` (max_time_diff=1.5) written out: each timestamp in seconds, then the
    difference; NaN when it is over 1.5 s, or over twice that for a centred difference (one exactly at the limit is
    kept: the devkit's test is ``time_diff > max_time_diff``)."""
    time_diff = 1e-6 * t_last_us - 1e-6 * t_first_us
    if time_diff > 1.5 * (2 if centred else 1):
        return np.full(3, np.nan)
    return (np.asarray(last["translation"]) - np.asarray(first["translation"])) / time_diff


@pytest.mark.parametrize(
    ("prev_gap_us", "next_gap_us", "valid"),
    [(1_250_000, 1_250_000, True),  # centred over 2.5 s: over 1.5 s, but within the 3 s a centred difference has
     (500_000, 2_000_000, True),  # the limit is on the whole span, not on either side
     (1_500_000, 1_500_000, True),  # exactly 3 s (exact in float64 for this timestamp): kept
     (1_500_000, 1_500_001, False),  # 1 us over
     (1_750_000, 1_750_000, False),  # 3.5 s
     (1_000_000, None, True),  # one-sided (no next annotation): 1.5 s at most
     (1_500_000, None, True),  # exactly 1.5 s: kept
     (1_500_001, None, False),
     (1_600_000, None, False),
     (2_500_000, None, False)],  # what a centred difference may span, one-sided: not kept
)  # fmt: skip
def test_velocity_window_is_the_devkits(tmp_path, prev_gap_us, next_gap_us, valid):
    """The gap box_velocity accepts: 1.5 s for a one-sided difference, 3 s for a centred one, a gap exactly at the
    limit kept; the reader against the devkit's rule written out, on neighbours moved in time."""
    root = tmp_path / "nusc"
    info = _write_tables(root)
    table_dir = root / "v1.0-mini"
    ts = info["calib"]["sample_timestamp_us"]
    samples = json.loads((table_dir / "sample.json").read_text())
    stamps = {"prev": ts - prev_gap_us, "next": ts + (next_gap_us or 500_000)}
    for s in samples:
        s["timestamp"] = stamps.get(s["token"], s["timestamp"])
    (table_dir / "sample.json").write_text(json.dumps(samples))
    path = table_dir / "sample_annotation.json"
    anns = json.loads(path.read_text())
    if next_gap_us is None:  # cut every track after the key frame: a one-sided difference back to "prev"
        for a in anns:
            if a["sample_token"] == info["calib"]["sample_token"]:
                a["next"] = ""
        path.write_text(json.dumps(anns))
    by_token = {a["token"]: a for a in anns}
    sample_ts = {s["token"]: s["timestamp"] for s in samples}
    s = NuScenesReader(root, "v1.0-mini").get(info["calib"]["sample_token"])
    velocity = s.extras[GLOBAL_ANNOTATIONS]["velocity"]
    tracked = np.array([by_token[t]["prev"] != "" for t in s.annotation_tokens])  # the others are lone annotations
    assert tracked.sum() == len(tracked) - 2
    for i, token in enumerate(s.annotation_tokens):
        ann = by_token[token]
        if not tracked[i]:
            assert not s.velocity_valid[i] and np.isnan(velocity[i]).all()
            continue
        first = by_token[ann["prev"]]
        last = by_token[ann["next"]] if ann["next"] else ann
        want = _devkit_box_velocity(first, last, sample_ts[first["sample_token"]], sample_ts[last["sample_token"]],
                                    centred=ann["next"] != "")  # fmt: skip
        assert np.isfinite(want).all() == valid, (token, want)  # the case is the one named
        np.testing.assert_allclose(velocity[i], want, rtol=1e-12, atol=1e-12, err_msg=token)  # NaN where want is
        assert s.velocity_valid[i] == valid, (token, s.velocity_valid[i])
        if not valid:
            assert np.all(s.gt_boxes[i, 7:9] == 0), (token, s.gt_boxes[i, 7:9])


def test_reader_errors_name_what_is_missing(tmp_path):
    root = tmp_path / "nusc"
    _write_tables(root)
    with pytest.raises(FileNotFoundError, match="v1.0-trainval"):
        NuScenesReader(root, "v1.0-trainval")
    reader = NuScenesReader(root, "v1.0-mini")
    with pytest.raises(KeyError, match="nope"):
        reader.get("nope")
    with pytest.raises(IndexError):
        reader.get(7)
    with pytest.raises(ValueError, match="num_past_sweeps"):
        reader.get(1, num_past_sweeps=-1)
    lidar_file = next((root / "samples" / "LIDAR_TOP").iterdir())
    times = lidar_file.with_name(lidar_file.name + ".time")
    np.zeros(3, dtype=np.float32).tofile(times)
    with pytest.raises(ValueError, match="point-time"):
        reader.get(1)
    times.unlink()
    lidar_file.unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(lidar_file.name)):
        reader.get(1)
    (root / "v1.0-mini" / "sample_annotation.json").write_text("{not json")
    with pytest.raises(ValueError, match="sample_annotation"):
        NuScenesReader(root, "v1.0-mini")
    (root / "v1.0-mini" / "sample_annotation.json").write_text("{}")
    with pytest.raises(ValueError, match="list"):
        NuScenesReader(root, "v1.0-mini")
    (root / "v1.0-mini" / "sample_annotation.json").unlink()
    with pytest.raises(FileNotFoundError, match="sample_annotation"):
        NuScenesReader(root, "v1.0-mini")


def test_bundled_sample_matches_its_files():
    s = load_bundled_sample()
    ref = json.loads((SAMPLE_DIR / "boxes.json").read_text())["boxes"]
    calib = json.loads((SAMPLE_DIR / "calibration.json").read_text())
    assert s.token == calib["sample_token"] and s.timestamp_us == calib["sample_timestamp_us"]
    assert s.points.shape == (34688, 5) and s.points.dtype == np.float32
    assert set(np.unique(s.points[:, 4]).astype(int)) == set(range(32))
    for i, b in enumerate(ref):
        np.testing.assert_allclose(s.gt_boxes[i, :3], b["center_xyz"])
        np.testing.assert_allclose(s.gt_boxes[i, 3:6], b["size_wlh"])
        assert s.gt_boxes[i, 6] == b["yaw"]
        if None in b["velocity_xy"]:
            assert not s.velocity_valid[i] and np.all(s.gt_boxes[i, 7:9] == 0)
        else:
            np.testing.assert_allclose(s.gt_boxes[i, 7:9], b["velocity_xy"])
        assert s.gt_labels[i] == b["label"]
        assert s.gt_names[i] == (b["class_name"] or "other")
        assert s.num_lidar_pts[i] == b["num_lidar_pts"]
    assert np.sum(s.gt_labels == CLASS_NAMES.index("pedestrian")) == 30
    np.testing.assert_allclose(s.extras["center_global"][0], [373.256, 1130.419, 0.800], atol=1e-3)
    # the global centres are the LiDAR centres moved through lidar2ego and ego2global
    moved = s.gt_boxes[:, :3] @ s.lidar2global[:3, :3].T + s.lidar2global[:3, 3]
    np.testing.assert_allclose(moved, s.extras["center_global"], atol=1e-3)
    assert s.rig.names[0] == "CAM_FRONT" and len(s.rig.names) == 6
    front = load_image(s.image_paths["CAM_FRONT"])
    assert front.shape == (900, 1600, 3) and front.dtype == np.uint8
    assert load_image(s.image_paths["CAM_FRONT"], size=(400, 225)).shape == (225, 400, 3)


def test_load_image_and_points_errors(tmp_path, caplog):
    with pytest.raises(FileNotFoundError, match="missing.jpg"):
        load_image(tmp_path / "missing.jpg")
    (tmp_path / "bad.jpg").write_bytes(b"not an image")
    with pytest.raises(FileNotFoundError, match="bad.jpg"):
        load_image(tmp_path / "bad.jpg")
    with pytest.raises(ValueError, match="size"):
        load_image(SAMPLE_DIR / json.loads((SAMPLE_DIR / "calibration.json").read_text())["cameras"][0]["file"], size=(0, 10))
    np.zeros(7, dtype=np.float32).tofile(tmp_path / "odd.pcd.bin")
    with pytest.raises(ValueError, match="multiple of 5"):
        load_points(tmp_path / "odd.pcd.bin")
    with pytest.raises(FileNotFoundError, match="nothing.pcd.bin"):
        load_points(tmp_path / "nothing.pcd.bin")
    (tmp_path / "empty.pcd.bin").write_bytes(b"")
    with caplog.at_level(logging.WARNING, logger="streamdet.data.sample"):
        assert load_points(tmp_path / "empty.pcd.bin").shape == (0, 5)  # the devkit reads it so too
    assert "empty.pcd.bin holds no points" in caplog.text
    copy = tmp_path / "sample"
    shutil.copytree(SAMPLE_DIR, copy)
    (copy / "boxes.json").unlink()
    with pytest.raises(FileNotFoundError, match="boxes.json"):
        load_bundled_sample(copy)


def test_official_devkit_agrees_with_the_reader(tables):
    nuscenes = pytest.importorskip("nuscenes.nuscenes", reason="nuscenes-devkit not installed")
    root, info = tables
    nusc = nuscenes.NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    s = NuScenesReader(root, "v1.0-mini").get(info["calib"]["sample_token"])
    _, boxes, _ = nusc.get_sample_data(nusc.get("sample", s.token)["data"]["LIDAR_TOP"])
    by_token = {b.token: b for b in boxes}
    for i, token in enumerate(s.annotation_tokens):
        b = by_token[token]
        np.testing.assert_allclose(b.center, s.gt_boxes[i, :3], atol=1e-9)
        assert abs(np.mod(b.orientation.yaw_pitch_roll[0] - s.gt_boxes[i, 6] + math.pi, 2 * math.pi) - math.pi) < 1e-9
        v = nusc.box_velocity(token)  # global; the devkit's boxes carry none
        if s.velocity_valid[i]:
            np.testing.assert_allclose((v @ s.lidar2global[:3, :3])[:2], s.gt_boxes[i, 7:9], atol=1e-9)
        else:
            assert np.all(np.isnan(v))
