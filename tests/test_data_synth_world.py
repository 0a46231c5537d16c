"""The synthetic world's parts, return model, layout and camera extras against naive references."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from streamdet.core.classes import CLASS_NAMES
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.synth_kinds import DISTRACTOR_KINDS, KIND_SPECS, Kind
from streamdet.data.synth_lidar import LidarConfig, detection_probability, footprint_fill
from streamdet.data.synth_materials import MATERIALS, SPOKED_RETURN, SPOKED_RIM, SPOKED_TYRE, Mat, shade
from streamdet.data.synth_raycast import SHAPE_BOX, SHAPE_CYLINDER, SHAPE_ELLIPSOID, ray_shape_entry
from streamdet.data.synth_render import Exposure
from streamdet.data.synth_shapes import part_extents, rotation
from streamdet.data.synth_stats import _angle_off_axes_deg, road_axes_at
from streamdet.data.synth_road import (
    BUILDING_LINE_M, CROSS_HALF_WIDTH_M, GROUND_AMPLITUDE_M, ground_height, ray_ground_height,
)  # fmt: skip
from streamdet.data.synth_world import WORLD_FILE, WORLD_VERSION, WorldConfig, make_scene
from streamdet.data.synth_writer import MASK_SUFFIX, SynthConfig, generate_dataset


def _inside(p, half, shape):
    r = p / half
    if shape == SHAPE_BOX:
        return np.abs(r).max(axis=-1) <= 1
    if shape == SHAPE_ELLIPSOID:
        return np.linalg.norm(r, axis=-1) <= 1
    return (np.linalg.norm(r[..., :2], axis=-1) <= 1) & (np.abs(r[..., 2]) <= 1)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", [SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_CYLINDER])
def test_ray_shape_entry_matches_marching(seed, shape):
    """The entry distance equals the first inside sample of a fine march along the ray."""
    rng = np.random.default_rng(seed)
    n = 200
    half = rng.uniform(0.2, 1.5, size=(n, 3))
    o = rng.uniform(-4, 4, size=(n, 3))
    o[np.all(np.abs(o) < half, axis=1)] += 5.0  # start outside
    target = rng.uniform(-1, 1, size=(n, 3)) * half * 0.9
    d = target - o
    d[: n // 4] = rng.normal(size=(n // 4, 3))  # some rays miss
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, normal = ray_shape_entry(o, d, half, np.full(n, shape))
    steps = np.arange(0.0, 12.0, 0.002)  # (S,)
    for i in range(n):
        pts = o[i] + steps[:, None] * d[i]
        inside = _inside(pts, half[i], shape)
        if _inside(o[i], half[i], shape):
            continue
        if not inside.any():
            assert t[i] == math.inf, i
            continue
        assert t[i] == pytest.approx(steps[np.argmax(inside)], abs=0.003), i
        assert abs(np.linalg.norm(normal[i]) - 1) < 1e-9
        assert normal[i] @ d[i] <= 1e-9  # the normal faces the ray


@pytest.mark.parametrize("shape", [SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_CYLINDER])
def test_part_extents_bound_the_rotated_shape(shape):
    rng = np.random.default_rng(3)
    for _ in range(20):
        half = rng.uniform(0.1, 1.0, size=3)
        rot = rotation(*rng.uniform(-math.pi, math.pi, size=3))
        ext = part_extents(half[None], rot[None], np.array([shape]))[0]
        pts = rng.uniform(-1, 1, size=(40000, 3)) * half
        pts = pts[_inside(pts, half, shape)] @ rot.T
        assert np.all(np.abs(pts) <= ext + 1e-9)
        assert np.all(np.abs(pts).max(axis=0) > ext - 0.1 * half.max())  # and is tight


def test_turning_poses_are_arcs_with_their_velocity():
    for index in range(12):
        scene = make_scene(5, index)
        objs = scene.objects
        turning = np.flatnonzero(objs.yaw_rate != 0)
        if not len(turning):
            continue
        k = turning[0]
        t = np.array([0.0, 1.0, 2.5])
        c, yaw, v = objs.poses_at(t, np.full(3, k))
        eps = 1e-5
        c2, _, _ = objs.poses_at(t + eps, np.full(3, k))
        np.testing.assert_allclose((c2[:, :2] - c[:, :2]) / eps, v, atol=1e-4)
        np.testing.assert_allclose(yaw, objs.yaw[k] + objs.yaw_rate[k] * t)
        np.testing.assert_allclose(np.arctan2(v[:, 1], v[:, 0]) - yaw, 0.0, atol=1e-9)  # heads where it goes
        boxes = objs.boxes_at(t)  # (3, K, 9)
        np.testing.assert_allclose(boxes[:, k, :3], c)
        return
    pytest.fail("no turning vehicle in 12 scenes")



def test_ray_ground_height_accuracy():
    """What ray_ground_height's docstring says of its three default steps, against 400 steps: steep rays land on the
    ground to well below the range noise; every ray's point keeps within the undulation's band, so its height error
    is bounded even where the range is not (grazing rays far away)."""
    rng = np.random.default_rng(0)
    n = 4000
    for elevation_deg, range_tol_m in ((-30.0, 1e-4), (-10.0, 1e-3), (-5.0, 0.01), (-2.0, None), (-1.33, None)):
        az = rng.uniform(0, 2 * math.pi, n)
        e = math.radians(elevation_deg)
        o = np.stack([rng.uniform(0, 2000, n), rng.uniform(0, 2000, n), np.full(n, 1.84)], axis=1)  # the LiDAR's height
        d = np.stack([math.cos(e) * np.cos(az), math.cos(e) * np.sin(az), np.full(n, math.sin(e))], axis=1)
        t = ray_ground_height(o, d, 1.3)
        assert np.isfinite(t).all()
        p = o + t[:, None] * d
        assert np.abs(p[:, 2]).max() <= GROUND_AMPLITUDE_M + 1e-12
        assert np.abs(p[:, 2] - ground_height(p[:, 0], p[:, 1], 1.3)).max() <= 2 * GROUND_AMPLITUDE_M
        if range_tol_m is not None:
            assert np.abs(t - ray_ground_height(o, d, 1.3, iterations=400)).max() < range_tol_m, elevation_deg

def test_detection_probability_follows_the_physics():
    cfg = LidarConfig()
    r = np.array([5.0, 20.0, 40.0, 80.0])
    p = detection_probability(np.full(4, 0.1), np.full(4, 0.7), r, 2.0, cfg)
    assert np.all(np.diff(p) < 0) and np.all((p >= 0) & (p <= 1))  # falls with range
    assert detection_probability(0.3, 0.7, 40.0, 2.0, cfg) > detection_probability(0.03, 0.7, 40.0, 2.0, cfg)
    assert detection_probability(0.1, 0.95, 40.0, 6.0, cfg) > detection_probability(0.1, 0.3, 40.0, 6.0, cfg)
    assert detection_probability(0.0, 1.0, 10.0, 1.0, cfg) == 0.0


@pytest.mark.parametrize("seed", [0, 1])
def test_thin_parts_and_spoked_wheels_return_less(seed):
    rng = np.random.default_rng(seed)
    cfg = LidarConfig()
    width, rng_m = rng.uniform(0.0, 0.3, 50), rng.uniform(1.0, 80.0, 50)
    naive = [min(w / (cfg.beam_exit_m + cfg.beam_divergence_rad * r), 1.0) for w, r in zip(width, rng_m)]
    np.testing.assert_allclose(footprint_fill(width, rng_m, cfg), naive)
    # A spoked wheel (a cylinder along its z): its rim returns like a tyre, its open disc rarely.
    half = np.tile([0.34, 0.34, 0.025], (50, 1))
    p = np.c_[rng.uniform(-0.34, 0.34, (50, 2)), np.full(50, 0.025)]
    _, alpha, _, scale, _ = shade(np.full(50, int(Mat.SPOKED)), np.full((50, 3), 0.05), np.full(50, 0.07), p, half, np.tile([0.0, 0.0, 1.0], (50, 1)))
    inner = [math.hypot(x / 0.34, y / 0.34) < SPOKED_RIM for x, y in p[:, :2]]
    np.testing.assert_array_equal(scale, np.where(inner, SPOKED_RETURN, 1.0))
    assert alpha.all()
    # ... and between the spokes and the tyre sits a metal rim
    radial = np.hypot(p[:, 0] / 0.34, p[:, 1] / 0.34)
    _, _, refl, _, _ = shade(np.full(50, int(Mat.SPOKED)), np.full((50, 3), 0.05), np.full(50, 0.07), p, half, np.tile([0.0, 0.0, 1.0], (50, 1)))
    expected = np.where(radial >= SPOKED_TYRE, 0.07, MATERIALS[Mat.METAL].reflectance[1])
    np.testing.assert_allclose(refl, expected)


def test_bicycle_racks_and_cross_street_people():
    """Parked bicycles stand in racks (side by side, one heading, a stand apart) and people walk the cross street's
    sidewalks beyond the corner blocks."""
    racks, cross_people = 0, 0
    for index in range(6):
        scene = make_scene(5, index)
        objs = scene.objects
        parked = np.flatnonzero((objs.kind == Kind.BICYCLE) & (np.linalg.norm(objs.velocity, axis=1) == 0))
        s, d = scene.to_road(objs.center0[parked, :2])
        for i in range(len(parked)):
            for j in range(i + 1, len(parked)):
                side_by_side = 0.8 < abs(s[i] - s[j]) < 1.05 and abs(d[i] - d[j]) < 1e-6
                racks += side_by_side and abs(objs.yaw[parked[i]] - objs.yaw[parked[j]]) < 0.1
        if scene.cross_s_m is not None:
            people = objs.kind == Kind.PEDESTRIAN
            s, d = scene.to_road(objs.center0[people, :2])
            cross_people += int(np.sum((np.abs(s - scene.cross_s_m) > CROSS_HALF_WIDTH_M) & (np.abs(d) > BUILDING_LINE_M)))
    assert racks >= 1
    assert cross_people >= 5


def test_layout_varies_and_keeps_the_tail_classes():
    """Over some scenes: tail classes >= 5 % of the road users, vehicles off the road axis, distractors."""
    counts = np.zeros(len(Kind), dtype=np.int64)
    off, vehicles = 0, 0
    for index in range(8):
        scene = make_scene(9, index)
        objs = scene.objects
        counts += np.bincount(objs.kind, minlength=len(Kind))
        roads = [{"origin_xy": r.origin_xy, "yaw": r.yaw, "half_width_m": r.half_width_m} for r in scene.roads]
        for k in np.flatnonzero(np.isin(objs.kind, [Kind.CAR, Kind.TRUCK, Kind.BUS])):
            off += _angle_off_axes_deg(objs.yaw[k], road_axes_at(roads, objs.center0[k, :2])) > 10
            vehicles += 1
    annotated = counts[: len([s for s in KIND_SPECS if s.detection_class])].sum()
    for kind in (Kind.BUS, Kind.BICYCLE, Kind.MOTORCYCLE):
        assert counts[kind] / annotated >= 0.05, (kind.name, counts[kind] / annotated)
    assert off / vehicles >= 0.25
    small = counts[Kind.PEDESTRIAN] + counts[Kind.TRAFFIC_CONE] + counts[Kind.BICYCLE]
    assert counts[list(DISTRACTOR_KINDS)].sum() >= small


def test_exposure_differs_per_draw():
    rng = np.random.default_rng(0)
    a, b = Exposure.draw(rng), Exposure.draw(rng)
    assert a.gain != b.gain and a.white_balance != b.white_balance
    assert 0.5 < a.gain < 2.0 and all(0.8 < v < 1.25 for v in a.white_balance)


@pytest.fixture(scope="module", params=[2, 43])  # 43: a car beyond annotation_range_m shows in CAM_FRONT
def swept(tmp_path_factory, request):
    root = tmp_path_factory.mktemp(f"swept{request.param}")
    cfg = SynthConfig(num_scenes=1, seed=request.param, resolution=(64, 36), sweeps_per_sample=10,
                      world=WorldConfig(samples_per_scene=2))
    generate_dataset(root, cfg)
    return root, cfg


def test_intermediate_sweeps_are_written_as_nuscenes(swept):
    root, cfg = swept
    sd = json.loads((root / cfg.version / "sample_data.json").read_text())
    lidar = sorted((r for r in sd if "LIDAR_TOP" in r["filename"]), key=lambda r: r["timestamp"])
    assert len(lidar) == 20 and sum(r["is_key_frame"] for r in lidar) == 2
    assert all(r["filename"].startswith("sweeps/") for r in lidar if not r["is_key_frame"])
    for a, b in zip(lidar, lidar[1:]):
        assert a["next"] == b["token"] and b["prev"] == a["token"]
        assert b["timestamp"] - a["timestamp"] == 50_000  # 20 Hz
    s = NuScenesReader(root, cfg.version).get(1, num_past_sweeps=9)
    assert len(s.sweeps) == 9
    np.testing.assert_allclose([w.time_lag_s for w in s.sweeps], 0.05 * np.arange(1, 10), atol=1e-6)


def test_masks_beside_each_image(swept):
    root, cfg = swept
    tables = root / cfg.version
    instances = {r["token"] for r in json.loads((tables / "instance.json").read_text())}
    sample_of = {r["filename"]: r["sample_token"] for r in json.loads((tables / "sample_data.json").read_text())}
    boxed: dict[str, set[str]] = {}  # sample token -> instance tokens of its boxes
    for ann in json.loads((tables / "sample_annotation.json").read_text()):
        boxed.setdefault(ann["sample_token"], set()).add(ann["instance_token"])
    images = sorted(root.glob("samples/CAM_*/*.jpg"))
    assert len(images) == 12
    seen_classes = set()
    for image in images:
        with np.load(image.with_name(image.name + MASK_SUFFIX)) as m:
            class_id, instance, ids, tokens = m["class_id"], m["instance"], m["ids"], m["tokens"]
        assert class_id.shape == (36, 64) and class_id.dtype == np.uint8 and instance.dtype == np.uint16
        assert np.all((class_id == 255) == (instance == 0))
        assert set(np.unique(instance[instance > 0]).tolist()) == set(ids.tolist())
        assert set(tokens.tolist()) <= instances  # every token names a row of the instance table
        # and a box of this very sample: an object of an annotated kind beyond annotation_range_m is no mask object
        assert set(tokens.tolist()) <= boxed.get(sample_of[image.relative_to(root).as_posix()], set())
        for i in ids:  # one object, one class
            assert len(np.unique(class_id[instance == i])) == 1
        seen_classes |= set(np.unique(class_id[class_id < 255]).tolist())
    assert seen_classes and max(seen_classes) < len(CLASS_NAMES)


def test_world_sidecar_names_the_version(swept):
    root, _ = swept
    doc = json.loads((root / WORLD_FILE).read_text())
    assert doc["world_version"] == WORLD_VERSION
    (scene,) = doc["scenes"].values()
    assert scene["roads"] and len(scene["distractors_xy"]) == len(scene["distractor_kinds"]) > 0
