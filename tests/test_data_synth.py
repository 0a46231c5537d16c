"""The synthetic world: LiDAR on part surfaces, rolling scan, renders under their boxes, the written dataset read back."""

from __future__ import annotations

import hashlib
import json
import math

import cv2
import numpy as np
import pytest

from streamdet.calibration.camera import quaternion_to_matrix
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.sectors import sector_bounds_deg
from streamdet.core.slicing import relative_time_s, split_sweep
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.synth_lidar import LidarConfig, simulate_sweep
from streamdet.data.synth_kinds import DISTRACTOR_KINDS
from streamdet.data.synth_materials import MATERIALS, Mat, ground, shade
from streamdet.data.synth_raycast import ray_box_entry, ray_ground, world_to_local
from streamdet.data.synth_shapes import build_shape
from streamdet.data.synth_world import KIND_SPECS, Kind, WorldConfig, make_scene
from streamdet.data.synth_writer import SynthConfig, generate_dataset, real_rig_records, simulate_frame

CONFIG = SynthConfig(num_scenes=1, seed=7, resolution=(192, 108), sweeps_per_sample=2, world=WorldConfig(samples_per_scene=3))
SWEEP_S = CONFIG.world.sweep_duration_s


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    summary = generate_dataset(root, CONFIG)
    return root, summary


@pytest.fixture(scope="module")
def frame():
    scene = make_scene(CONFIG.seed, 0, CONFIG.world)
    rig = real_rig_records(CONFIG.resolution)
    return scene, rig, simulate_frame(scene, 1, rig, CONFIG)


def _world_points(scene, sweep, lidar2ego):
    l2g = scene.ego2global(sweep.t_end_s) @ lidar2ego
    return sweep.points[:, :3].astype(np.float64) @ l2g[:3, :3].T + l2g[:3, 3]


def _pose_at_point_times(scene, times_abs, k):
    """(N, 3) centres and (N,) yaws of object k at each point's time."""
    centres, yaws, _ = scene.objects.poses_at(times_abs, np.full(len(times_abs), k))
    return centres, yaws


# ---- ray casting against naive references ---------------------------------------------------------

def _naive_slab(o, d, half):
    t_near, t_far, axis = -math.inf, math.inf, -1
    for a in range(3):
        if abs(d[a]) < 1e-12:
            if abs(o[a]) > half[a]:
                return math.inf, -1
            continue
        t1, t2 = (-half[a] - o[a]) / d[a], (half[a] - o[a]) / d[a]
        lo, hi = min(t1, t2), max(t1, t2)
        if lo > t_near:
            t_near, axis = lo, a
        t_far = min(t_far, hi)
    if t_near <= t_far and t_near > 0:
        return t_near, axis
    return math.inf, -1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ray_box_entry_matches_naive(seed):
    rng = np.random.default_rng(seed)
    n = 400
    o = rng.uniform(-6, 6, size=(n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:20, 0] = 0.0  # rays parallel to a slab
    half = rng.uniform(0.3, 3.0, size=(n, 3))
    hit, t, axis, sign = ray_box_entry(o, d, half)
    for i in range(n):
        t_ref, a_ref = _naive_slab(o[i], d[i], half[i])
        assert hit[i] == math.isfinite(t_ref), i
        if hit[i]:
            assert t[i] == pytest.approx(t_ref, rel=1e-9, abs=1e-9)
            assert axis[i] == a_ref
            p = o[i] + t[i] * d[i]
            assert p[axis[i]] == pytest.approx(sign[i] * half[i, axis[i]], abs=1e-9)
        else:
            assert t[i] == math.inf


@pytest.mark.parametrize("seed", [0, 1])
def test_ray_ground_and_frames_match_naive(seed):
    rng = np.random.default_rng(seed)
    o = rng.uniform(-5, 5, size=(200, 3)) + [0, 0, 2]
    d = rng.normal(size=(200, 3))
    t = ray_ground(o, d)
    for i in range(200):
        ref = -o[i, 2] / d[i, 2] if d[i, 2] < 0 and -o[i, 2] / d[i, 2] > 0 else math.inf
        assert t[i] == pytest.approx(ref) if math.isfinite(ref) else t[i] == math.inf
    yaw = rng.uniform(-3, 3, size=200)
    c = rng.normal(size=(200, 3))
    local = world_to_local(o, c, yaw)
    for i in range(5):
        R = np.array([[math.cos(yaw[i]), -math.sin(yaw[i]), 0], [math.sin(yaw[i]), math.cos(yaw[i]), 0], [0, 0, 1]])
        np.testing.assert_allclose(local[i], R.T @ (o[i] - c[i]))


def test_materials_and_shapes_stay_in_range():
    rng = np.random.default_rng(0)
    for kind in Kind:
        for flag in (False, True):
            shape = build_shape(kind, KIND_SPECS[kind].size_wlh_m, rng, [0.8, 0.1, 0.1], [0.1, 0.1, 0.3], flag)
            n = len(shape.mat)
            assert n >= 1 and shape.albedo.shape == (n, 3) and np.all(shape.half > 0), kind
            assert np.all((shape.refl >= 0) & (shape.refl <= 1)), kind
            # the box is tight (up to the annotator's margin): every part lies inside it
            from streamdet.data.synth_shapes import part_extents
            ext = part_extents(shape.half, shape.rot, shape.shape)
            half_box = np.array([shape.size_wlh[1], shape.size_wlh[0], shape.size_wlh[2]]) / 2
            assert np.all(np.abs(shape.center) + ext <= half_box + 1e-9), kind
            assert np.all((shape.size_wlh / np.asarray(KIND_SPECS[kind].size_wlh_m) > 0.3)), kind
            m = 300
            part = rng.integers(0, n, size=m)
            p = rng.uniform(-1, 1, size=(m, 3)) * shape.half[part]
            normal = rng.normal(size=(m, 3))
            albedo, alpha, refl, scale, gloss = shade(shape.mat[part], shape.albedo[part], shape.refl[part], p, shape.half[part], normal)
            assert albedo.shape == (m, 3) and albedo.dtype == np.float32 and alpha.dtype == bool
            assert albedo.min() >= 0 and albedo.max() <= 1 and refl.min() >= 0 and refl.max() <= 1
            assert np.all((scale > 0) & (scale <= 1)) and np.all(gloss > 0)
    albedo, refl = ground(rng.uniform(-100, 100, 1000), rng.uniform(-30, 30, 1000), 10.0)
    assert albedo.shape == (1000, 3) and 0 <= refl.min() and refl.max() <= 1
    # no material names a class: every class's parts draw from ranges shared with another class
    assert MATERIALS[Mat.PAINT].reflectance[0] < MATERIALS[Mat.CLOTH].reflectance[1]


# ---- the world ------------------------------------------------------------------------------------

def test_world_is_plausible_and_deterministic():
    scenes = [make_scene(3, i) for i in range(3)]
    kinds = set()
    for scene in scenes:
        objs = scene.objects
        kinds |= set(objs.kind[objs.annotated].tolist())
        speed = np.linalg.norm(objs.velocity, axis=1)
        for kind, top in ((Kind.CAR, 15.0), (Kind.PEDESTRIAN, 2.0), (Kind.BICYCLE, 7.0)):
            m = objs.kind == kind
            assert np.all(speed[m] <= top)
            mean = np.asarray(KIND_SPECS[kind].size_wlh_m)
            ratio = objs.size_wlh[m] / mean
            assert np.all((ratio > 0.35) & (ratio < 1.8)), (kind, ratio.min(), ratio.max())  # a tall walker's stride: ~1.76 l
            if kind == Kind.CAR:
                assert ratio[:, 1].std() > 0.04  # sizes spread (nuScenes cars: about 9 %)
        assert np.any(np.isin(objs.kind, [int(k) for k in DISTRACTOR_KINDS]))
        assert objs.parts.count.sum() == len(objs.parts.mat) and np.all(objs.parts.count >= 1)
        # moving road users head where they go
        moving = objs.annotated & (speed > 0.1)
        heading = np.stack([np.cos(objs.yaw), np.sin(objs.yaw)], axis=1)[moving]
        np.testing.assert_allclose(np.sum(heading * objs.velocity[moving], axis=1), speed[moving], rtol=1e-6)
        # annotated footprints never overlap at the key frames (exact rotated rectangles)
        for t in scene.sample_times_s:
            boxes = objs.boxes_at(t)[objs.annotated]
            rects = [((b[0], b[1]), (b[4], b[3]), math.degrees(b[6])) for b in boxes]
            for i in range(len(rects)):
                for j in range(i + 1, len(rects)):
                    if np.linalg.norm(boxes[i, :2] - boxes[j, :2]) > 20:
                        continue
                    kind_ij, pts = cv2.rotatedRectangleIntersection(rects[i], rects[j])
                    area = cv2.contourArea(pts) if pts is not None and len(pts) > 2 else 0.0
                    assert area < 1e-3, (t, i, j)
    assert {Kind.CAR, Kind.PEDESTRIAN, Kind.BICYCLE} <= kinds
    again = make_scene(3, 1)
    np.testing.assert_array_equal(again.objects.center0, scenes[1].objects.center0)
    assert make_scene(4, 1).objects.center0.shape != scenes[1].objects.center0.shape or not np.array_equal(
        make_scene(4, 1).objects.center0, scenes[1].objects.center0
    )


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="resolution"):
        SynthConfig(resolution=(8, 8))
    with pytest.raises(ValueError, match="num_scenes"):
        SynthConfig(num_scenes=0)
    with pytest.raises(ValueError, match="sweeps_per_sample"):
        SynthConfig(sweeps_per_sample=11)
    with pytest.raises(ValueError, match="samples_per_scene"):
        WorldConfig(samples_per_scene=0)
    with pytest.raises(ValueError, match="pedestrians"):
        WorldConfig(pedestrians=(5, 2))
    with pytest.raises(ValueError, match="azimuth_steps"):
        LidarConfig(azimuth_steps=2)


# ---- LiDAR ----------------------------------------------------------------------------------------

def test_lidar_points_fall_on_parts_and_ground(frame):
    scene, rig, f = frame
    sweep = f.sweep
    assert 25_000 < len(sweep.points) < 36_000
    assert set(np.unique(sweep.points[:, 4]).astype(int)) == set(range(32))
    assert sweep.points[:, 3].min() >= 0 and sweep.points[:, 3].max() <= 255
    assert np.all(sweep.points[:, 3] == np.round(sweep.points[:, 3]))
    world = _world_points(scene, sweep, rig.lidar2ego)
    ground = sweep.hit < 0
    # ground points lie on the undulating ground (range noise only)
    np.testing.assert_allclose(world[ground, 2], scene.ground_z(world[ground, :2]), atol=0.08)
    assert np.abs(scene.ground_z(world[ground, :2])).max() > 0.01  # and the ground is not a plane
    objs, parts = scene.objects, scene.objects.parts
    t_abs = sweep.t_end_s - SWEEP_S + sweep.time_s.astype(np.float64)
    checked, all_best = 0, []
    for k in np.unique(sweep.hit[~ground]):
        mine = np.flatnonzero(sweep.hit == k)
        centres, yaws = _pose_at_point_times(scene, t_abs[mine], k)
        local = world_to_local(world[mine], centres, yaws)  # (P, 3) box frame at each point's time
        half = objs.size_wlh[k, [1, 0, 2]] / 2
        assert np.all(np.abs(local) <= half + 0.08), k  # inside the object's box
        # on the surface of one of the object's parts: just outside or inside it within the range noise
        lo, hi = parts.start[k], parts.start[k] + parts.count[k]
        best = np.full(len(mine), np.inf)
        for j in range(lo, hi):
            q = (local - parts.center[j]) @ parts.rot[j]  # (P, 3) part frame
            r = q / parts.half[j]
            if parts.shape[j] == 0:
                d = np.abs(np.abs(r).max(axis=1) - 1) * parts.half[j].min()
            elif parts.shape[j] == 1:
                d = np.abs(np.linalg.norm(r, axis=1) - 1) * parts.half[j].min()
            else:
                d = np.abs(np.maximum(np.linalg.norm(r[:, :2], axis=1), np.abs(r[:, 2])) - 1) * parts.half[j].min()
            best = np.minimum(best, d)
        if len(mine) >= 10:
            assert np.mean(best < 0.1) > 0.9, (k, Kind(objs.kind[k]).name)
        all_best.append(best)
        checked += 1
    assert checked > 10
    all_best = np.concatenate(all_best)
    assert np.median(all_best) < 0.02 and np.quantile(all_best, 0.95) < 0.08
    assert 0.05 < np.mean(~ground) < 0.9
    # the return model: retroreflective plates come back bright, intensities do not name the class
    ann = np.isin(sweep.hit, np.flatnonzero(objs.annotated))
    assert np.median(sweep.points[ann, 3]) < 60


def test_moving_objects_are_displaced_within_the_sweep(frame):
    """Points of a moving object sit where the object was when the beam fired, not at its annotated pose."""
    scene, rig, f = frame
    sweep = f.sweep
    objs = scene.objects
    world = _world_points(scene, sweep, rig.lidar2ego)
    speed = np.linalg.norm(objs.velocity, axis=1)
    found, largest = 0, 0.0
    for k in np.flatnonzero((speed > 3.0) & objs.annotated):
        mine = np.flatnonzero(sweep.hit == k)
        if len(mine) < 5:
            continue
        t_abs = sweep.t_end_s - SWEEP_S + sweep.time_s[mine].astype(np.float64)
        centres, yaws = _pose_at_point_times(scene, t_abs, k)
        at_own_time = world_to_local(world[mine], centres, yaws)
        at_end = world_to_local(world[mine], objs.boxes_at(sweep.t_end_s)[k, :3], objs.boxes_at(sweep.t_end_s)[k, 6])
        half_l = objs.size_wlh[k, 1] / 2
        assert np.all(np.abs(at_own_time[:, 0]) <= half_l + 0.08)
        lag = speed[k] * (sweep.t_end_s - t_abs)  # metres moved since the point was taken
        # against the annotated pose (the sweep's end) every point lies behind by the distance travelled since
        if objs.yaw_rate[k] == 0.0:
            np.testing.assert_allclose(at_end[:, 0] - at_own_time[:, 0], -lag, atol=1e-6)
        largest = max(largest, lag.max())
        found += 1
    assert found, "no fast object in this sweep"
    assert largest > 0.1  # well above the range noise


def test_point_timestamps_rise_with_azimuth():
    world = WorldConfig(samples_per_scene=1, ego_stopped_prob=1.0)
    scene = make_scene(1, 0, world)
    assert scene.ego_speed_mps == 0.0
    rig = real_rig_records((64, 36))
    sweep = simulate_sweep(scene, scene.sample_times_s[0], rig.lidar2ego, np.random.default_rng(0))
    assert np.all(np.diff(sweep.time_s) >= 0)  # firing order
    az = np.degrees(np.arctan2(sweep.points[:, 1], sweep.points[:, 0])) % 360.0
    # world 6: clockwise seen from above from 180 deg, as nuScenes' LIDAR_TOP (world 5: counter-clockwise from 0)
    from_azimuth = np.mod(180.0 - az, 360.0) / 360.0 * SWEEP_S
    column = SWEEP_S / LidarConfig().azimuth_steps
    assert np.abs(from_azimuth - sweep.time_s).max() <= column / 2 + 1e-6
    assert az[sweep.time_s < column].min() > 179.0 and az[sweep.time_s > SWEEP_S - column].max() < 181.0  # the seam
    # the project's clock of that layout (core.scan_layout.NUSCENES_LIDAR_TOP, which bag export writes for real
    # sweeps) is the same clock
    np.testing.assert_allclose(relative_time_s(sweep.points, 180.0, SWEEP_S, clockwise=True), sweep.time_s, atol=column / 2 + 1e-6)


def test_moving_ego_keeps_time_close_to_azimuth(frame):
    scene, rig, f = frame
    sweep = f.sweep
    rng_m = np.linalg.norm(sweep.points[:, :2], axis=1)
    far = rng_m > 5.0
    az = np.degrees(np.arctan2(sweep.points[far, 1], sweep.points[far, 0])) % 360.0
    err = np.abs(np.mod(180.0 - az, 360.0) / 360.0 * SWEEP_S - sweep.time_s[far])  # clockwise from 180 deg
    err = np.minimum(err, SWEEP_S - err)
    # ego motion compensation moves a point at range r by at most v * T: an angle of atan(v T / r)
    bound = np.degrees(np.arctan2(scene.ego_speed_mps * SWEEP_S, rng_m[far])) / 360.0 * SWEEP_S + SWEEP_S / 1080
    assert np.all(err <= bound + 1e-6)


# ---- cameras --------------------------------------------------------------------------------------

def test_projected_boxes_cover_rendered_object_pixels(dataset, frame):
    """Every pixel of an annotated object lies inside its annotated 3D box projected through the written rig.

    The box is taken as written (global pose, quaternion) and moved through the reader's LiDAR pose and
    lidar2cam: the yaw-only LiDAR-frame box would be off by the LiDAR's 1.4 deg tilt, as on real nuScenes.
    Each camera exposes before the sample time (world 6: when the LiDAR crosses its axis), so a straight mover's box
    is moved on by its velocity over the camera's lag behind the sample, read from the written timestamps; a turning
    one is left out here (tests/test_data_synth_timing.py takes its pose at the camera's time).
    """
    root, _ = dataset
    scene, rig, f = frame
    sample = NuScenesReader(root, CONFIG.version).get(1)
    anns = {a["token"]: a for a in json.loads((root / CONFIG.version / "sample_annotation.json").read_text())}
    world_corners = []
    for token in sample.annotation_tokens:
        a = anns[token]
        w, l, h = a["size"]
        local = np.array([[sx * l / 2, sy * w / 2, sz * h / 2] for sz in (-1, 1) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
        world_corners.append(local @ quaternion_to_matrix(a["rotation"]).T + a["translation"])
    world_corners = np.array(world_corners)  # (M, 8, 3)
    g2l = np.linalg.inv(sample.lidar2global)
    lidar_corners = world_corners @ g2l[:3, :3].T + g2l[:3, 3]
    wb = scene.objects.boxes_at(f.t_s)
    row_of = {int(k): int(np.linalg.norm(world_corners.mean(axis=1) - wb[k, :3], axis=1).argmin()) for k in f.annotated}
    checked = 0
    best_fill = 0.0
    for name, render in f.renders.items():
        cam = sample.rig.camera(name)
        assert render.image.shape == (cam.height, cam.width, 3)
        lag_s = 1e-6 * (cam.timestamp_us - sample.timestamp_us)
        assert -SWEEP_S < lag_s < 0
        for obj, row in row_of.items():
            rows, cols = np.nonzero(render.object_id == obj)
            if not len(rows) or scene.objects.yaw_rate[obj] != 0.0:
                continue
            moved = np.r_[scene.objects.velocity[obj] * lag_s, 0.0] @ g2l[:3, :3].T  # global displacement in the LiDAR frame
            uv, depth = cam.project(lidar_corners[row] + moved)
            if depth.min() < 0.2:
                continue
            hull = cv2.convexHull(uv.astype(np.float32))
            dist = np.array([cv2.pointPolygonTest(hull, (float(c) + 0.5, float(r) + 0.5), True) for r, c in zip(rows, cols)])
            assert np.all(dist >= -0.05), (name, obj, dist.min())
            checked += 1
            if render.own_pixels[obj] == len(rows) and scene.objects.kind[obj] == Kind.CAR:
                best_fill = max(best_fill, len(rows) / max(cv2.contourArea(hull), 1.0))
    assert checked >= 5
    assert best_fill > 0.4  # an unoccluded car fills much of its projected box (its shape is not the box)


def test_renders_hide_the_ground_and_each_other(frame):
    scene, rig, f = frame
    ids = np.concatenate([r.object_id.ravel() for r in f.renders.values()])
    seen = np.bincount(ids[ids >= 0], minlength=len(scene.objects))
    own = sum(r.own_pixels for r in f.renders.values())
    ann = scene.objects.annotated
    assert np.all(seen[ann] <= own[ann])
    assert np.any((seen[ann] < 0.8 * own[ann]) & (own[ann] > 0)), "no annotated object is partly hidden"
    assert np.mean(ids >= 0) > 0.1 and np.mean(ids < 0) > 0.2  # objects and ground / sky both show
    front = f.renders["CAM_FRONT"].image.astype(np.float32)
    assert front[: front.shape[0] // 4].mean(axis=(0, 1))[2] > front[-front.shape[0] // 4 :].mean(axis=(0, 1))[2]  # sky above road


# ---- the written dataset --------------------------------------------------------------------------

def test_reader_returns_what_the_generator_wrote(dataset, frame):
    root, summary = dataset
    scene, rig, f = frame
    reader = NuScenesReader(root, CONFIG.version)
    assert len(reader) == 3 and summary.num_samples == 3 and summary.num_sweeps == 6
    s = reader.get(1, num_past_sweeps=1)
    np.testing.assert_array_equal(s.points, f.sweep.points)
    np.testing.assert_array_equal(s.point_time_s, f.sweep.time_s)
    assert s.scene_name == scene.name and s.timestamp_us == f.timestamp_us
    # the past sweep, moved into this key frame's LiDAR frame
    assert len(s.sweeps) == 1 and s.sweeps[0].time_lag_s == pytest.approx(CONFIG.world.sample_interval_s / 2)
    past = f.past_sweeps[0]
    to_now = np.linalg.inv(scene.ego2global(f.t_s) @ rig.lidar2ego) @ scene.ego2global(past.t_end_s) @ rig.lidar2ego
    np.testing.assert_allclose(s.sweeps[0].points[:, :3], past.points[:, :3] @ to_now[:3, :3].T + to_now[:3, 3], atol=1e-4)
    # boxes: world poses at the key frame, through the LiDAR pose, in the annotated order of the objects
    objs = scene.objects
    l2g = scene.ego2global(f.t_s) @ rig.lidar2ego
    wb = objs.boxes_at(f.t_s)[f.annotated]
    assert len(s.gt_boxes) == len(wb)
    order = np.linalg.norm(s.gt_boxes[None, :, :3] - ((wb[:, :3] - l2g[:3, 3]) @ l2g[:3, :3])[:, None], axis=2).argmin(axis=1)
    assert len(set(order.tolist())) == len(order)
    got = s.gt_boxes[order]
    np.testing.assert_allclose(got[:, :3], (wb[:, :3] - l2g[:3, 3]) @ l2g[:3, :3], atol=1e-6)
    np.testing.assert_allclose(got[:, 3:6], wb[:, 3:6])
    heading = np.stack([np.cos(wb[:, 6]), np.sin(wb[:, 6]), np.zeros(len(wb))], axis=1) @ l2g[:3, :3]
    yaw_err = np.mod(got[:, 6] - np.arctan2(heading[:, 1], heading[:, 0]) + math.pi, 2 * math.pi) - math.pi
    assert np.abs(yaw_err).max() < 1e-6
    v_lidar = np.concatenate([wb[:, 7:9], np.zeros((len(wb), 1))], axis=1) @ l2g[:3, :3]
    valid = s.velocity_valid[order]
    assert valid.mean() > 0.8
    straight = objs.yaw_rate[f.annotated] == 0.0
    np.testing.assert_allclose(got[valid & straight, 7:9], v_lidar[valid & straight, :2], atol=1e-6)
    # a turning vehicle's centred-difference velocity is the chord's, a little shorter than the tangent
    np.testing.assert_allclose(got[valid & ~straight, 7:9], v_lidar[valid & ~straight, :2], atol=0.2)
    np.testing.assert_array_equal(s.gt_labels[order], [CLASS_NAMES.index(KIND_SPECS[k].detection_class) for k in objs.kind[f.annotated]])
    np.testing.assert_array_equal(s.num_lidar_pts[order], f.num_lidar_pts)
    # rig: the real mounting, intrinsics scaled to the resolution, each camera at its own exposure's ego pose (world
    # 6: when the LiDAR crossed its axis; until then all at the key frame's), chained as the devkit does
    assert s.rig.names == tuple(m.name for m in rig.models)
    np.testing.assert_allclose(s.rig.lidar2ego, rig.lidar2ego, atol=1e-12)
    assert scene.ego_speed_mps > 1.0
    for m in rig.models:
        cam = s.rig.camera(m.name)
        np.testing.assert_allclose(cam.K, m.K)
        t_cam = f.camera_times_s[m.name]
        assert cam.timestamp_us == scene.timestamp_us(t_cam) and f.t_s - SWEEP_S < t_cam < f.t_s
        want = np.linalg.inv(m.cam2ego) @ np.linalg.inv(scene.ego2global(t_cam)) @ scene.ego2global(f.t_s) @ rig.lidar2ego
        np.testing.assert_allclose(cam.lidar2cam, want, atol=1e-6)
        # the ego moved on between the exposure and the sweep's end: the LiDAR's pose for the camera is off by that
        assert np.abs(cam.lidar2cam[:3, 3] - (np.linalg.inv(m.cam2ego) @ rig.lidar2ego)[:3, 3]).max() > 0.5 * scene.ego_speed_mps * (f.t_s - t_cam)
    images = s.load_images()
    assert images.shape == (6, 108, 192, 3)
    for j, name in enumerate(s.rig.names):
        assert np.abs(images[j].astype(float) - f.renders[name].image).mean() < 6.0  # JPEG



def _naive_in_box_count(points, box):
    """Points (N, 3) inside one box (x, y, z, w, l, h, yaw), boundary included: one point at a time."""
    c, s = math.cos(box[6]), math.sin(box[6])
    n = 0
    for p in points:
        dx, dy, dz = p[0] - box[0], p[1] - box[1], p[2] - box[2]
        n += abs(c * dx + s * dy) <= box[4] / 2 and abs(-s * dx + c * dy) <= box[3] / 2 and abs(dz) <= box[5] / 2
    return n


@pytest.mark.parametrize("seed", [0, 1])
def test_count_points_in_boxes_matches_naive(seed, monkeypatch):
    import streamdet.data.synth_writer as writer

    rng = np.random.default_rng(seed)
    pts = rng.uniform([-20, -60, -1], [20, 60, 3], size=(3000, 3))  # a street along y: sorting along x pairs all
    boxes = np.concatenate([rng.uniform([-15, -55, 0], [15, 55, 2], size=(40, 3)), rng.uniform(0.4, 6.0, size=(40, 3)),
                            rng.uniform(-math.pi, math.pi, size=(40, 1))], axis=1)  # fmt: skip
    boxes[:5, :3] = pts[:5]  # some points on a box's centre; one on a corner (the boundary is inside)
    corner = boxes[5, :3] + [math.cos(boxes[5, 6]) * boxes[5, 4] / 2, math.sin(boxes[5, 6]) * boxes[5, 4] / 2, boxes[5, 5] / 2]
    pts[5] = corner + 1e-12 * np.sign(boxes[5, :3] - corner)
    want = [_naive_in_box_count(pts, b) for b in boxes]
    np.testing.assert_array_equal(writer.count_points_in_boxes(pts, boxes), want)
    monkeypatch.setattr(writer, "_PAIR_CHUNK", 50)  # many chunks, some of one box only
    np.testing.assert_array_equal(writer.count_points_in_boxes(pts, boxes), want)
    assert writer.count_points_in_boxes(pts, boxes[:0]).shape == (0,)
    np.testing.assert_array_equal(writer.count_points_in_boxes(pts[:0], boxes), np.zeros(len(boxes)))


def test_num_lidar_pts_counts_the_points_in_the_annotated_box(dataset):
    """Through the written files and tables only, as the devkit's points_in_box counts (its port in
    evaluation.detection_eval): each annotation's num_lidar_pts is the number of its key frame's points in its box."""
    from streamdet.evaluation.detection_eval import points_in_boxes

    root, _ = dataset
    tables = {n: json.loads((root / CONFIG.version / f"{n}.json").read_text())
              for n in ("sample_data", "ego_pose", "calibrated_sensor", "sample_annotation")}  # fmt: skip
    by_token = {n: {r["token"]: r for r in rows} for n, rows in tables.items()}
    anns_of: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"]:
        anns_of.setdefault(ann["sample_token"], []).append(ann)
    checked = nonzero = 0
    for sd in tables["sample_data"]:
        if not (sd["is_key_frame"] and sd["fileformat"] == "pcd"):
            continue
        pts = np.fromfile(root / sd["filename"], dtype="<f4").reshape(-1, 5)[:, :3].astype(np.float64)
        cs, pose = by_token["calibrated_sensor"][sd["calibrated_sensor_token"]], by_token["ego_pose"][sd["ego_pose_token"]]
        for rec in (cs, pose):  # sensor -> ego -> global
            pts = pts @ quaternion_to_matrix(rec["rotation"]).T + np.asarray(rec["translation"])
        anns = anns_of[sd["sample_token"]]
        rows = np.array([a["translation"] + a["size"] + a["rotation"] for a in anns], dtype=np.float64)
        want = points_in_boxes(pts, rows).sum(axis=0)
        got = np.array([a["num_lidar_pts"] for a in anns])
        np.testing.assert_array_equal(got, want)
        checked += len(anns)
        nonzero += int((got > 0).sum())
    assert checked > 50 and 0 < nonzero < checked

def test_tables_follow_the_nuscenes_schema(dataset):
    root, _ = dataset
    schema = {
        "category": {"token", "name", "description"},
        "attribute": {"token", "name", "description"},
        "visibility": {"token", "level", "description"},
        "instance": {"token", "category_token", "nbr_annotations", "first_annotation_token", "last_annotation_token"},
        "sensor": {"token", "channel", "modality"},
        "calibrated_sensor": {"token", "sensor_token", "translation", "rotation", "camera_intrinsic"},
        "ego_pose": {"token", "timestamp", "rotation", "translation"},
        "log": {"token", "logfile", "vehicle", "date_captured", "location"},
        "scene": {"token", "log_token", "nbr_samples", "first_sample_token", "last_sample_token", "name", "description"},
        "sample": {"token", "timestamp", "prev", "next", "scene_token"},
        "sample_data": {"token", "sample_token", "ego_pose_token", "calibrated_sensor_token", "timestamp", "fileformat",
                        "is_key_frame", "height", "width", "filename", "prev", "next"},
        "sample_annotation": {"token", "sample_token", "instance_token", "visibility_token", "attribute_tokens", "translation",
                              "size", "rotation", "prev", "next", "num_lidar_pts", "num_radar_pts"},
        "map": {"category", "token", "filename", "log_tokens"},
    }
    tables = {name: json.loads((root / CONFIG.version / f"{name}.json").read_text()) for name in schema}
    for name, fields in schema.items():
        assert tables[name], name
        for row in tables[name]:
            assert set(row) == fields, (name, set(row) ^ fields)
    tokens = {name: {r["token"] for r in rows} for name, rows in tables.items()}
    for sd in tables["sample_data"]:
        assert (root / sd["filename"]).is_file()
        assert sd["ego_pose_token"] in tokens["ego_pose"] and sd["calibrated_sensor_token"] in tokens["calibrated_sensor"]
    lidar = [sd for sd in tables["sample_data"] if "LIDAR_TOP" in sd["filename"]]
    assert len(lidar) == 6 and sum(sd["is_key_frame"] for sd in lidar) == 3
    by_token = {sd["token"]: sd for sd in lidar}
    chain = [next(sd for sd in lidar if sd["prev"] == "")]
    while chain[-1]["next"]:
        chain.append(by_token[chain[-1]["next"]])
    assert len(chain) == 6 and all(a["timestamp"] < b["timestamp"] for a, b in zip(chain, chain[1:]))
    for inst in tables["instance"]:
        anns = [a for a in tables["sample_annotation"] if a["instance_token"] == inst["token"]]
        assert len(anns) == inst["nbr_annotations"] and inst["category_token"] in tokens["category"]
    for ann in tables["sample_annotation"]:
        assert ann["visibility_token"] in tokens["visibility"] and set(ann["attribute_tokens"]) <= tokens["attribute"]
        assert abs(np.linalg.norm(ann["rotation"]) - 1) < 1e-9 and ann["num_lidar_pts"] >= 0
    assert len({a["visibility_token"] for a in tables["sample_annotation"]}) >= 2
    assert tables["scene"][0]["nbr_samples"] == 3
    assert set(tables["map"][0]["log_tokens"]) == tokens["log"]
    splits = json.loads((root / "splits.json").read_text())
    assert splits == {"train": [tables["scene"][0]["name"]], "val": []}


def test_slices_of_a_synthetic_sample_lie_in_their_sectors(dataset):
    root, _ = dataset
    s = NuScenesReader(root, CONFIG.version).get(0)
    for k, pts in enumerate(split_sweep(s.points, 16)):
        lo, hi = sector_bounds_deg(k, 16)
        az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360.0
        assert len(pts) and np.all((az >= lo - 1e-4) & (az < hi + 1e-4))


def _tree_digest(root):
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_deterministic_for_a_seed(tmp_path):
    cfg = SynthConfig(num_scenes=1, seed=11, resolution=(64, 36), world=WorldConfig(samples_per_scene=1))
    generate_dataset(tmp_path / "a", cfg)
    generate_dataset(tmp_path / "b", cfg)
    assert _tree_digest(tmp_path / "a") == _tree_digest(tmp_path / "b")
    generate_dataset(tmp_path / "c", SynthConfig(num_scenes=1, seed=12, resolution=(64, 36), world=WorldConfig(samples_per_scene=1)))
    assert _tree_digest(tmp_path / "a") != _tree_digest(tmp_path / "c")


def test_parallel_workers_write_the_same_dataset(tmp_path):
    cfg = SynthConfig(num_scenes=2, seed=5, resolution=(48, 27), world=WorldConfig(samples_per_scene=1))
    done = []
    generate_dataset(tmp_path / "serial", cfg, progress=done.append)
    assert done == [1, 1]
    summary = generate_dataset(tmp_path / "parallel", cfg, workers=2)
    assert summary.num_samples == 2 and summary.scenes == ("synth-5-0000", "synth-5-0001")
    assert _tree_digest(tmp_path / "serial") == _tree_digest(tmp_path / "parallel")
    with pytest.raises(ValueError, match="workers"):
        generate_dataset(tmp_path / "x", cfg, workers=0)


def test_official_devkit_loads_the_tables(dataset):
    nuscenes = pytest.importorskip("nuscenes.nuscenes", reason="nuscenes-devkit not installed")
    root, _ = dataset
    nusc = nuscenes.NuScenes(version=CONFIG.version, dataroot=str(root), verbose=False)
    assert len(nusc.sample) == 3
    reader = NuScenesReader(root, CONFIG.version)
    s = reader.get(1)
    ann = nusc.get("sample_annotation", s.annotation_tokens[0])
    v = nusc.box_velocity(ann["token"])
    l2g = s.lidar2global
    np.testing.assert_allclose((np.array([v[0], v[1], 0.0]) @ l2g[:3, :3])[:2], s.gt_boxes[0, 7:9], atol=1e-6)
    _, boxes, _ = nusc.get_sample_data(nusc.get("sample", s.token)["data"]["LIDAR_TOP"])
    by_token = {b.token: b for b in boxes}
    for i, token in enumerate(s.annotation_tokens):
        np.testing.assert_allclose(by_token[token].center, s.gt_boxes[i, :3], atol=1e-6)
