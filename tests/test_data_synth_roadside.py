"""Road works and the furniture that looks like cones and barriers (world 4) against naive references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.data.synth_kinds import BARRIER_LOOKALIKE_KINDS, CONE_LOOKALIKE_KINDS, KIND_SPECS, Kind
from streamdet.data.synth_road import LANE_WIDTH_M, ROAD_HALF_WIDTH_M
from streamdet.data.synth_world import make_scene

FIXED = (Kind.DELINEATOR,) + BARRIER_LOOKALIKE_KINDS
ANNOTATED = tuple(Kind(k) for k, spec in enumerate(KIND_SPECS) if spec.detection_class is not None)


def _footprint_points(centre_xy: np.ndarray, yaw: float, size_wlh: np.ndarray, step_m: float = 0.05) -> np.ndarray:
    """(P, 2) world points on a grid covering a box's footprint (the naive reference for rectangle overlap)."""
    w, l = float(size_wlh[0]), float(size_wlh[1])
    xs = np.linspace(-l / 2, l / 2, max(2, int(l / step_m) + 1))
    ys = np.linspace(-w / 2, w / 2, max(2, int(w / step_m) + 1))
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    c, s = math.cos(yaw), math.sin(yaw)
    return centre_xy + np.stack([gx.ravel() * c - gy.ravel() * s, gx.ravel() * s + gy.ravel() * c], axis=1)


def _inside_box(pts: np.ndarray, centre_xy: np.ndarray, yaw: float, size_wlh: np.ndarray) -> np.ndarray:
    rel = pts - centre_xy
    c, s = math.cos(yaw), math.sin(yaw)
    lx = rel[:, 0] * c + rel[:, 1] * s
    ly = -rel[:, 0] * s + rel[:, 1] * c
    return (np.abs(lx) < size_wlh[1] / 2) & (np.abs(ly) < size_wlh[0] / 2)


@pytest.mark.parametrize("seed", [3, 4])
def test_fixed_furniture_never_overlaps_annotated_objects(seed):
    """Every rail, divider, planter and post stays outside every annotated box at every 50 ms of the scene (a dense
    grid over the furniture's footprint, tested point by point)."""
    scene = make_scene(seed, 0)
    objs = scene.objects
    fixed = np.flatnonzero(np.isin(objs.kind, FIXED))
    users = np.flatnonzero(np.isin(objs.kind, ANNOTATED))
    assert len(fixed) > 0
    times = np.arange(0.0, float(scene.sample_times_s[-1]) + 1e-9, 0.05)
    centres, yaws, _ = objs.poses_at(times[:, None], users)  # (T, U, 3), (T, U)
    for k in fixed:
        pts = _footprint_points(objs.center0[k, :2], float(objs.yaw[k]), objs.size_wlh[k])
        for j, u in enumerate(users):
            near = np.linalg.norm(centres[:, j, :2] - objs.center0[k, :2], axis=1) < 0.5 * (
                np.hypot(*objs.size_wlh[k, :2]) + np.hypot(*objs.size_wlh[u, :2]))
            for t in np.flatnonzero(near):
                assert not np.any(_inside_box(pts, centres[t, j, :2], float(yaws[t, j]), objs.size_wlh[u])), (
                    Kind(int(objs.kind[k])).name, Kind(int(objs.kind[u])).name, times[t])


def test_lookalikes_outnumber_cones_and_barriers_near_the_ego():
    """Within 30 m of the ego (nuScenes' range for cones and barriers), per key frame over some scenes: at least as
    many cone-sized look-alikes as annotated cones, and at least as many barrier-sized look-alike segments (per
    2.5 m of rail, a barrier's length) as annotated barriers."""
    cones = barriers = cone_like = 0
    barrier_like = 0.0
    for index in range(6):
        scene = make_scene(11, index)
        objs = scene.objects
        for t in scene.sample_times_s:
            centres, _, _ = objs.poses_at(t)
            near = np.linalg.norm(centres[:, :2] - scene.ego_xy(t), axis=1) <= 30.0
            cones += int(np.sum(near & (objs.kind == Kind.TRAFFIC_CONE)))
            barriers += int(np.sum(near & (objs.kind == Kind.BARRIER)))
            cone_like += int(np.sum(near & np.isin(objs.kind, CONE_LOOKALIKE_KINDS)))
            rails = near & np.isin(objs.kind, BARRIER_LOOKALIKE_KINDS)
            barrier_like += float(np.sum(np.maximum(objs.size_wlh[rails, 1] / KIND_SPECS[Kind.BARRIER].size_wlh_m[0], 1.0)))
    assert cones > 0 and barriers > 0
    assert cone_like >= cones, (cone_like, cones)
    assert barrier_like >= barriers, (barrier_like, barriers)


def test_cones_stand_where_real_ones_do():
    """Cones are not only in tidy rows on the road: some close a traffic lane, some stand on sidewalks, some next to
    a barrier (a work zone mixes them)."""
    in_lane = on_sidewalk = beside_barrier = 0
    for index in range(10):
        scene = make_scene(13, index)
        objs = scene.objects
        cone = np.flatnonzero(objs.kind == Kind.TRAFFIC_CONE)
        barrier = np.flatnonzero(objs.kind == Kind.BARRIER)
        _, d = scene.to_road(objs.center0[cone, :2])
        in_lane += int(np.sum(np.abs(d) < 2 * LANE_WIDTH_M - 0.3))
        on_sidewalk += int(np.sum(np.abs(d) > ROAD_HALF_WIDTH_M))
        if len(barrier):
            gap = np.linalg.norm(objs.center0[cone, None, :2] - objs.center0[None, barrier, :2], axis=-1).min(axis=1)
            beside_barrier += int(np.sum(gap < 2.0))
    assert in_lane >= 3 and on_sidewalk >= 3 and beside_barrier >= 2, (in_lane, on_sidewalk, beside_barrier)
