"""World 6's sensor timing against naive references, through the written files and tables only where it can be:
the LiDAR turns clockwise from 180 deg (nuScenes' LIDAR_TOP), each camera fires as the LiDAR crosses its optical axis
with its own timestamp and ego pose, a moving object's box brought to a camera's time through the devkit chain covers
its rendered mask, and the reader's camera extrinsics (and so the LUT) carry the ego motion between the two times."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from streamdet.calibration.camera import Camera, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut_build import build_lut
from streamdet.core.scan_layout import ScanLayout, layout_from_times
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import bundled_sample_dir, load_point_times, load_points
from streamdet.data.synth_lidar import LidarConfig, scan_fraction
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import SynthConfig, camera_trigger_times_s, generate_dataset, real_rig_records

# seed 3 scene 0: the ego drives (10 m/s) among movers crossing the views; at 320x180 a mover's lag is pixels wide
CONFIG = SynthConfig(num_scenes=1, seed=3, resolution=(320, 180), sweeps_per_sample=2, world=WorldConfig(samples_per_scene=2))
SWEEP_US = round(CONFIG.world.sweep_duration_s * 1e6)
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_timing")
    generate_dataset(root, CONFIG)
    tables = {n: json.loads((root / CONFIG.version / f"{n}.json").read_text())
              for n in ("sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose", "sample_annotation")}  # fmt: skip
    by = {n: {r["token"]: r for r in rows} for n, rows in tables.items()}
    channel = {cs["token"]: by["sensor"][cs["sensor_token"]]["channel"] for cs in tables["calibrated_sensor"]}
    key = {}  # sample token -> channel -> key-frame sample_data
    for sd in tables["sample_data"]:
        if sd["is_key_frame"]:
            key.setdefault(sd["sample_token"], {})[channel[sd["calibrated_sensor_token"]]] = sd
    return root, tables, by, key


def _rot(q):
    """w, x, y, z unit quaternion -> 3x3 rotation, written out (independent of streamdet's)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip


def _mat(record):
    m = np.eye(4)
    m[:3, :3] = _rot(record["rotation"])
    m[:3, 3] = record["translation"]
    return m


def _axis_azimuth_deg(by, lidar_sd, cam_sd):
    """The camera's optical axis (+z) as an azimuth of the LiDAR frame, from the calibrated_sensor rows."""
    r_lidar = _rot(by["calibrated_sensor"][lidar_sd["calibrated_sensor_token"]]["rotation"])
    r_cam = _rot(by["calibrated_sensor"][cam_sd["calibrated_sensor_token"]]["rotation"])
    axis = r_lidar.T @ r_cam @ [0.0, 0.0, 1.0]
    return math.degrees(math.atan2(axis[1], axis[0]))


# ---- (c) the LiDAR turns clockwise from 180 deg -------------------------------------------------------------------

def test_the_written_sweeps_turn_clockwise_from_180(dataset):
    """core.scan_layout reads nuScenes' LIDAR_TOP layout from every written sweep's per-point times, key frame or
    not, and the sweep's first and last firings lie on either side of 180 deg."""
    root, tables, _, _ = dataset
    lidar = [sd for sd in tables["sample_data"] if sd["fileformat"] == "pcd"]
    assert len(lidar) == 4
    column_s = CONFIG.world.sweep_duration_s / LidarConfig().azimuth_steps
    for sd in lidar:
        path = root / sd["filename"]
        points = load_points(path)
        times = load_point_times(path, len(points))
        layout = layout_from_times(points, times)
        assert layout == ScanLayout(180.0, True, "from the per-point times"), (sd["filename"], layout)
        far = np.hypot(points[:, 0], points[:, 1]) > 15.0  # the ego-motion compensation turns these by < 2 deg
        az = np.degrees(np.arctan2(points[far, 1], points[far, 0])) % 360.0
        first, last = az[times[far] < 6 * column_s], az[times[far] > CONFIG.world.sweep_duration_s - 6 * column_s]
        assert len(first) and len(last)
        # both ends at 180 deg (the car's left), the first firings just clockwise of it, the last just before it
        assert np.abs(first - 180.0).max() < 4.5 and np.abs(last - 180.0).max() < 4.5, (first, last)
        assert first.mean() < last.mean()
    # the reader hands the same times to the replay, which infers its layout from them
    sample = NuScenesReader(root, CONFIG.version).get(0)
    assert layout_from_times(sample.points, sample.point_time_s).describe() == (
        "LiDAR scan layout: clockwise from 180 deg (from the per-point times)")


def test_scan_fraction_is_the_clockwise_turn_from_the_start():
    cw = LidarConfig()
    assert (cw.start_deg, cw.clockwise) == (180.0, True)
    # the start azimuth itself is reached at the sweep's end (core.sectors.scan_fraction: it lies in the last slice)
    for az, want in [(180.0, 1.0), (90.0, 0.25), (0.0, 0.5), (-90.0, 0.75), (270.0, 0.75), (179.0, 1.0 / 360.0), (181.0, 359.0 / 360.0)]:
        assert scan_fraction(az, cw) == pytest.approx(want, abs=1e-12), az
    ccw = LidarConfig(start_deg=0.0, clockwise=False)  # world 5's sensor
    assert scan_fraction(90.0, ccw) == pytest.approx(0.25) and scan_fraction(-90.0, ccw) == pytest.approx(0.75)
    with pytest.raises(ValueError, match="clockwise"):
        LidarConfig(clockwise=1)


# ---- (a) each camera fires as the LiDAR crosses its optical axis ------------------------------------------------

def test_each_camera_fires_when_the_lidar_crosses_its_axis(dataset):
    """Per camera: timestamp = sweep start + the clockwise-from-180 LiDAR's crossing time of the camera's axis (from
    the calibrated_sensor rows), to the microsecond; the LiDAR's own points along that axis were fired then (their
    .time); the camera's ego_pose is the ego's pose at that time; the sample stays at the sweep's end."""
    root, tables, by, key = dataset
    samples = sorted(tables["sample"], key=lambda s: s["timestamp"])
    poses = [by["ego_pose"][key[s["token"]]["LIDAR_TOP"]["ego_pose_token"]] for s in samples]
    ego_velocity = (np.array(poses[1]["translation"]) - poses[0]["translation"]) / (1e-6 * (poses[1]["timestamp"] - poses[0]["timestamp"]))
    assert np.linalg.norm(ego_velocity) > 1.0  # the ego drives: its pose at the camera's time differs
    for smp in samples:
        sds = key[smp["token"]]
        lidar = sds["LIDAR_TOP"]
        assert lidar["timestamp"] == smp["timestamp"]  # the sample is the sweep's end
        start_us = lidar["timestamp"] - SWEEP_US
        path = root / lidar["filename"]
        points = load_points(path)
        times = load_point_times(path, len(points)).astype(np.float64)
        az_points = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        lidar_pose = by["ego_pose"][lidar["ego_pose_token"]]
        offsets = {}
        for name in CAMERAS:
            sd = sds[name]
            axis = _axis_azimuth_deg(by, lidar, sd)
            crossing_us = (180.0 - axis) % 360.0 / 360.0 * SWEEP_US
            assert abs(sd["timestamp"] - (start_us + crossing_us)) <= 1, (name, sd["timestamp"] - start_us, crossing_us)
            # the data's own clock: the points within a degree of the axis were fired at the exposure (to a few
            # columns: the ego-motion compensation turns a point's azimuth a little)
            near = (np.abs((az_points - axis + 180.0) % 360.0 - 180.0) < 1.0) & (np.hypot(points[:, 0], points[:, 1]) > 5.0)
            assert near.sum() >= 5, name
            assert abs(np.median(times[near]) * 1e6 - (sd["timestamp"] - start_us)) < 300, name
            pose = by["ego_pose"][sd["ego_pose_token"]]
            assert pose["timestamp"] == sd["timestamp"]
            dt = 1e-6 * (sd["timestamp"] - lidar["timestamp"])
            np.testing.assert_allclose(pose["translation"], np.array(lidar_pose["translation"]) + ego_velocity * dt, atol=1e-6)
            assert sd["filename"].endswith(f"__{name}__{sd['timestamp']}.jpg")
            offsets[name] = 1e-3 * (sd["timestamp"] - lidar["timestamp"])
        assert all(-50.0 < v < 0.0 for v in offsets.values()), offsets
        # the real sample's cameras fire in the same order, each at the same phase up to one shared shift (the real
        # sensor starts a few degrees past 180 deg)
        calib = json.loads((bundled_sample_dir() / "calibration.json").read_text())
        real = {c["name"]: 1e-3 * (c["timestamp_us"] - calib["sample_timestamp_us"]) for c in calib["cameras"]}
        assert sorted(CAMERAS, key=offsets.get) == sorted(CAMERAS, key=real.get) == [
            "CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT"]
        shift = np.array([offsets[n] - real[n] for n in CAMERAS])
        assert np.ptp(shift) < 0.5 and abs(shift.mean()) < 3.0, shift


def test_trigger_times_follow_the_sensor_s_direction():
    """camera_trigger_times_s: the crossing of each axis by the configured sensor, for either direction."""
    rig = real_rig_records((64, 36))
    cw = camera_trigger_times_s(rig, 1.0, 0.05)
    ccw = camera_trigger_times_s(rig, 1.0, 0.05, LidarConfig(start_deg=0.0, clockwise=False))
    for name in CAMERAS:
        assert 0.95 < cw[name] < 1.0 and 0.95 < ccw[name] < 1.0
    # CAM_FRONT looks along the LiDAR's +y (90 deg): a quarter turn from 180 clockwise or from 0 counter-clockwise
    assert cw["CAM_FRONT"] == pytest.approx(0.95 + 0.0125, abs=2e-4) and ccw["CAM_FRONT"] == pytest.approx(0.95 + 0.0125, abs=2e-4)
    assert cw["CAM_BACK"] == pytest.approx(0.95 + 0.0375, abs=2e-4) and ccw["CAM_BACK"] == pytest.approx(0.95 + 0.0375, abs=2e-4)
    assert cw["CAM_FRONT_LEFT"] < cw["CAM_FRONT"] < cw["CAM_FRONT_RIGHT"]
    assert ccw["CAM_FRONT_RIGHT"] < ccw["CAM_FRONT"] < ccw["CAM_FRONT_LEFT"]


# ---- (b) a moving object's box through the devkit chain covers its mask -------------------------------------------

def _hull_outside_px(corners_lidar, lidar2cam, K, mask):
    """Largest distance (px) of a mask pixel centre outside the hull of the corners projected by ``lidar2cam``;
    None where a corner is behind the camera."""
    cam = corners_lidar @ lidar2cam[:3, :3].T + lidar2cam[:3, 3]
    if cam[:, 2].min() < 0.5:
        return None
    uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
    hull = cv2.convexHull(uv.astype(np.float32))
    rows, cols = np.nonzero(mask)
    return max(0.0, -min(cv2.pointPolygonTest(hull, (float(c) + 0.5, float(r) + 0.5), True) for r, c in zip(rows, cols)))


def test_a_moving_object_s_box_at_the_camera_s_time_covers_its_mask(dataset):
    """Through the tables only: a straight mover's annotated box (global) is moved on by its velocity (the difference
    of its annotations) over the camera's lag behind the sample, expressed in the LiDAR frame, and projected as the
    devkit does, lidar -> ego(t_lidar) -> global -> ego(t_cam) -> cam. Every pixel of its mask lies in that box.
    The annotated box itself (the sample's time) does not cover its mask, nor does the box at the camera's time
    through the LiDAR's ego pose: the times and the poses both matter."""
    root, tables, by, key = dataset
    anns = {a["token"]: a for a in tables["sample_annotation"]}
    checked, largest_lag_px, largest_wrong_px = 0, 0.0, 0.0
    for smp in tables["sample"]:
        sds = key[smp["token"]]
        lidar = sds["LIDAR_TOP"]
        lidar2ego = _mat(by["calibrated_sensor"][lidar["calibrated_sensor_token"]])
        ego2global_lidar = _mat(by["ego_pose"][lidar["ego_pose_token"]])
        global2lidar = np.linalg.inv(ego2global_lidar @ lidar2ego)
        for ann in (a for a in tables["sample_annotation"] if a["sample_token"] == smp["token"]):
            ends = [anns[t] for t in (ann["prev"], ann["next"]) if t]
            if not ends:
                continue
            other = ends[0]
            dt_ann = 1e-6 * (by["sample"][other["sample_token"]]["timestamp"] - smp["timestamp"])
            velocity = (np.array(other["translation"]) - ann["translation"]) / dt_ann
            yaw_change = abs(math.remainder(2 * math.atan2(other["rotation"][3], other["rotation"][0])
                                            - 2 * math.atan2(ann["rotation"][3], ann["rotation"][0]), 2 * math.pi))  # fmt: skip
            if np.linalg.norm(velocity) < 1.0 or yaw_change > 1e-9:  # straight movers: velocity * dt is exact
                continue
            w, l, h = ann["size"]
            local = np.array([[sx * l / 2, sy * w / 2, sz * h / 2] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            corners_global = local @ _rot(ann["rotation"]).T + ann["translation"]
            for name in CAMERAS:
                sd = sds[name]
                mz = np.load(root / (sd["filename"] + ".mask.npz"))
                ids = {t: int(i) for i, t in zip(mz["ids"], mz["tokens"])}
                if ann["instance_token"] not in ids:
                    continue
                mask = mz["instance"] == ids[ann["instance_token"]]
                if mask.sum() < 20:
                    continue
                cs = by["calibrated_sensor"][sd["calibrated_sensor_token"]]
                K = np.array(cs["camera_intrinsic"])
                ego2global_cam = _mat(by["ego_pose"][sd["ego_pose_token"]])
                lidar2cam = np.linalg.inv(_mat(cs)) @ np.linalg.inv(ego2global_cam) @ ego2global_lidar @ lidar2ego
                wrong = np.linalg.inv(_mat(cs)) @ lidar2ego  # the LiDAR's ego pose for the camera
                lag = 1e-6 * (sd["timestamp"] - smp["timestamp"])
                at_cam = corners_global + velocity * lag
                to_lidar = lambda p: p @ global2lidar[:3, :3].T + global2lidar[:3, 3]  # noqa: E731
                outside = _hull_outside_px(to_lidar(at_cam), lidar2cam, K, mask)
                if outside is None:
                    continue
                assert outside <= 0.05, (name, ann["token"], outside)
                checked += 1
                largest_lag_px = max(largest_lag_px, _hull_outside_px(to_lidar(corners_global), lidar2cam, K, mask))
                largest_wrong_px = max(largest_wrong_px, _hull_outside_px(to_lidar(at_cam), wrong, K, mask) or 0.0)
    assert checked >= 10
    assert largest_lag_px > 3.0  # the object moved on between the exposure and the sample
    assert largest_wrong_px > 1.0  # and so did the ego


# ---- the reader: each camera's extrinsic from its own ego pose, and the LUT built from it -----------------------

def test_the_reader_and_the_lut_take_each_camera_s_ego_pose(dataset):
    """NuScenesReader's lidar2cam per camera is the devkit chain through the camera's own ego pose (written out
    here from the tables); the LUT built from a synthetic sample's rig is the LUT of that chain, not of the LiDAR's
    pose for every camera."""
    root, tables, by, key = dataset
    sample = NuScenesReader(root, CONFIG.version).get(1)
    sds = key[sample.token]
    lidar = sds["LIDAR_TOP"]
    lidar2ego = _mat(by["calibrated_sensor"][lidar["calibrated_sensor_token"]])
    ego2global_lidar = _mat(by["ego_pose"][lidar["ego_pose_token"]])
    naive, static = [], []
    for cam in sample.rig.cameras:
        sd = sds[cam.name]
        cs = by["calibrated_sensor"][sd["calibrated_sensor_token"]]
        chain = np.linalg.inv(_mat(cs)) @ np.linalg.inv(_mat(by["ego_pose"][sd["ego_pose_token"]])) @ ego2global_lidar @ lidar2ego
        np.testing.assert_allclose(cam.lidar2cam, chain, atol=1e-9)
        assert cam.timestamp_us == sd["timestamp"] != sample.timestamp_us
        moved = np.linalg.norm(cam.lidar2cam[:3, 3] - (np.linalg.inv(_mat(cs)) @ lidar2ego)[:3, 3])
        assert moved > 0.01, cam.name  # centimetres of ego motion: the LiDAR's pose would put the camera elsewhere
        naive.append(Camera(cam.name, cam.K, chain, cam.width, cam.height))
        static.append(Camera(cam.name, cam.K, np.linalg.inv(_mat(cs)) @ lidar2ego, cam.width, cam.height))
    grid = GridSpec(voxel_xy_m=0.8, voxel_z_m=1.0)
    lut = build_lut(sample.rig, grid)
    same = build_lut(Rig(tuple(naive), sample.rig.lidar2ego, sample.rig.ego2global), grid)
    other = build_lut(Rig(tuple(static), sample.rig.lidar2ego, sample.rig.ego2global), grid)
    assert np.mean(lut.index != same.index) < 1e-3  # the same projection (a cell border may round either way)
    assert np.mean(lut.index != other.index) > 10 * max(np.mean(lut.index != same.index), 1e-4)
