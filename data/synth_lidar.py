"""A rotating 32-beam LiDAR ray-cast into the synthetic world, with a rolling scan.

The sensor turns counter-clockwise (seen from above) once per sweep, starting at azimuth ``start_deg`` of the
LiDAR frame at ``t_end - sweep_duration`` and finishing at ``t_end``, the sweep's timestamp. Azimuth column a
fires its 32 beams together at ``(a + 0.5) / A`` of the sweep, from where the sensor is at that instant, and
sees every object where it is at that instant: a car at 15 m/s moves 0.75 m during one sweep, so its points
are smeared along its motion exactly as on a real rolling scan. Points are then expressed in the LiDAR frame at
``t_end`` (the ego motion within the sweep compensated, as nuScenes does), so static surfaces stay sharp while
moving objects keep their rolling-shutter displacement relative to their annotated pose at ``t_end``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.camera import invert_transform
from streamdet.core.boxes import box_corners_bev
from streamdet.data.synth_materials import ground, surface
from streamdet.data.synth_raycast import local_normals, ray_box_entry, ray_ground, world_to_local
from streamdet.data.synth_world import Scene

# Velodyne HDL-32E (nuScenes LIDAR_TOP): 32 beams evenly spaced from -30.67 to +10.67 deg.
HDL32E_ELEVATIONS_DEG: tuple[float, ...] = tuple(float(v) for v in np.linspace(-30.67, 10.67, 32))


@dataclass(frozen=True)
class LidarConfig:
    """The simulated sensor."""

    elevations_deg: tuple[float, ...] = HDL32E_ELEVATIONS_DEG  # beam elevations; ring index = position here
    azimuth_steps: int = 1080  # columns per rotation (0.33 deg, ~34.5 k rays)
    start_deg: float = 0.0  # azimuth (LiDAR frame) where each rotation starts
    min_range_m: float = 1.0  # returns nearer than this are dropped (the car's own body)
    max_range_m: float = 100.0
    range_noise_m: float = 0.015  # standard deviation along the ray
    dropout: float = 0.03  # fraction of returns lost at random
    intensity_noise: float = 2.0  # standard deviation, in 0..255 units

    def __post_init__(self) -> None:
        if len(self.elevations_deg) < 1 or not all(-90 < e < 90 for e in self.elevations_deg):
            raise ValueError(f"LidarConfig.elevations_deg must be angles in (-90, 90), got {self.elevations_deg!r}")
        if not (isinstance(self.azimuth_steps, int) and self.azimuth_steps >= 4):
            raise ValueError(f"LidarConfig.azimuth_steps must be an integer >= 4, got {self.azimuth_steps!r}")
        if not 0 < self.min_range_m < self.max_range_m:
            raise ValueError(f"LidarConfig needs 0 < min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"LidarConfig.dropout must be in [0, 1), got {self.dropout!r}")


@dataclass(frozen=True, eq=False)
class SimSweep:
    """One simulated sweep."""

    t_end_s: float  # scene time of the sweep's end (its timestamp)
    points: np.ndarray  # (N, 5) float32 x, y, z (LiDAR frame at t_end), intensity 0..255, ring
    time_s: np.ndarray  # (N,) float32 firing time after the sweep start, in [0, sweep_duration)
    hit: np.ndarray  # (N,) int64 index of the object hit in scene.objects, -1 for the ground


def simulate_sweep(
    scene: Scene,
    t_end_s: float,
    lidar2ego: np.ndarray,
    rng: np.random.Generator,
    config: LidarConfig = LidarConfig(),
) -> SimSweep:
    """Ray-cast one rotation ending at scene time ``t_end_s``; returns the points in firing order."""
    sweep_s = scene.config.sweep_duration_s
    n_az, n_el = config.azimuth_steps, len(config.elevations_deg)
    frac = (np.arange(n_az) + 0.5) / n_az  # (A,) position of each column within the sweep
    col_time = t_end_s - sweep_s + frac * sweep_s  # (A,) scene time of each column
    az = np.radians(config.start_deg + frac * 360.0)  # (A,)
    el = np.radians(np.asarray(config.elevations_deg))  # (E,)
    dirs_lidar = np.stack(
        [np.cos(el)[None, :] * np.cos(az)[:, None], np.cos(el)[None, :] * np.sin(az)[:, None], np.broadcast_to(np.sin(el), (n_az, n_el))],
        axis=-1,
    )  # (A, E, 3)
    # The ego only translates along the road, at constant speed: the LiDAR's rotation is the same all sweep
    # long and its position is linear in time.
    first, last = (scene.ego2global(t) @ lidar2ego for t in (col_time[0], col_time[-1]))
    rot = first[:3, :3]
    along = (col_time - col_time[0]) / max(col_time[-1] - col_time[0], 1e-12)  # (A,) 0 -> 1 over the sweep
    origins = first[:3, 3] + along[:, None] * (last[:3, 3] - first[:3, 3])  # (A, 3)
    dirs = dirs_lidar @ rot.T  # (A, E, 3) world

    n_rays = n_az * n_el
    t_best = ray_ground(np.broadcast_to(origins[:, None, :], dirs.shape), dirs).reshape(n_rays)  # (A * E,)
    best_obj = np.full(n_rays, -1, dtype=np.int64)
    best_refl = np.zeros(n_rays)
    best_cos = np.abs(dirs[..., 2]).reshape(n_rays)  # the ground normal is +z

    ai, ki = _candidate_columns(scene, col_time, origins, rot, config)
    if len(ai):
        a = np.repeat(ai, n_el)  # (P,) one pair per beam of each candidate column
        k = np.repeat(ki, n_el)
        e = np.tile(np.arange(n_el), len(ai))
        ray = a * n_el + e
        objs = scene.objects
        t_pair = col_time[a]
        centers = objs.center0[k] + np.concatenate([objs.velocity[k] * t_pair[:, None], np.zeros((len(k), 1))], axis=1)
        yaws = objs.yaw[k]
        half = objs.size_wlh[k][:, [1, 0, 2]] / 2  # (P, 3) along x (l), y (w), z (h)
        o_local = world_to_local(origins[a], centers, yaws)
        d_world = dirs[a, e]
        d_local = world_to_local(d_world, 0.0, yaws)
        hit, t_hit, axis, sign = ray_box_entry(o_local, d_local, half)
        keep = np.flatnonzero(hit & (t_hit < t_best[ray]))
        refl = np.zeros(len(keep))
        alpha = np.zeros(len(keep), dtype=bool)
        kinds = objs.kind[k[keep]]
        p_local = o_local[keep] + t_hit[keep, None] * d_local[keep]
        for kind in np.unique(kinds):
            m = kinds == kind
            sel = keep[m]
            kk = k[sel]
            _, alpha[m], refl[m] = surface(
                int(kind), axis[sel], sign[sel], p_local[m], half[sel], objs.color[kk], objs.color2[kk], objs.flag[kk]
            )
        keep, refl = keep[alpha], refl[alpha]
        # Nearest surface per ray: sort the surviving pairs by (ray, t) and take each ray's first.
        order = np.lexsort((t_hit[keep], ray[keep]))
        keep, refl = keep[order], refl[order]
        first = np.r_[True, ray[keep][1:] != ray[keep][:-1]]
        keep, refl = keep[first], refl[first]
        closer = t_hit[keep] < t_best[ray[keep]]
        keep, refl = keep[closer], refl[closer]
        r = ray[keep]
        t_best[r] = t_hit[keep]
        best_obj[r] = k[keep]
        best_refl[r] = refl
        normals = local_normals(axis[keep], sign[keep], yaws[keep])
        best_cos[r] = np.abs(np.sum(normals * d_world[keep], axis=1))

    valid = (t_best >= config.min_range_m) & (t_best <= config.max_range_m)
    valid &= rng.uniform(size=n_rays) >= config.dropout
    idx = np.flatnonzero(valid)  # firing order: column-major over (azimuth, beam)
    t = t_best[idx] + rng.normal(0.0, config.range_noise_m, size=len(idx))
    a_idx, e_idx = idx // n_el, idx % n_el
    world = origins[a_idx] + t[:, None] * dirs[a_idx, e_idx]  # (N, 3)
    obj = best_obj[idx]
    on_ground = obj < 0
    if np.any(on_ground):
        s_road, d_road = scene.to_road(world[on_ground, :2])
        _, best_refl_ground = ground(s_road, d_road)
        refl_all = best_refl[idx].copy()
        refl_all[on_ground] = best_refl_ground
    else:
        refl_all = best_refl[idx]
    intensity = 255.0 * refl_all * (0.3 + 0.7 * best_cos[idx]) + rng.normal(0.0, config.intensity_noise, size=len(idx))
    to_lidar = invert_transform(scene.ego2global(t_end_s) @ lidar2ego)
    xyz = world @ to_lidar[:3, :3].T + to_lidar[:3, 3]
    points = np.empty((len(idx), 5), dtype=np.float32)
    points[:, :3] = xyz
    points[:, 3] = np.clip(np.round(intensity), 0, 255)
    points[:, 4] = e_idx
    return SimSweep(t_end_s=float(t_end_s), points=points, time_s=(frac[a_idx] * sweep_s).astype(np.float32), hit=obj)


def _candidate_columns(
    scene: Scene, col_time: np.ndarray, origins: np.ndarray, rot: np.ndarray, config: LidarConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(column, object) pairs whose azimuth could meet: each object's azimuth span over the sweep, padded."""
    objs = scene.objects
    n_az = config.azimuth_steps
    t0, t1 = col_time[0], col_time[-1]
    boxes = np.concatenate([objs.boxes_at(t0), objs.boxes_at(t1)], axis=0)  # (2K, 9)
    corners = box_corners_bev(boxes).reshape(2, len(objs), 4, 2)  # (2 times, K, 4, 2)
    corners = corners.transpose(1, 0, 2, 3).reshape(len(objs), 8, 2)  # (K, 8, 2): both times' corners
    sensor = 0.5 * (origins[0, :2] + origins[-1, :2])
    rel = corners - sensor  # (K, 8, 2)
    # Azimuth in the LiDAR frame (its small tilt is covered by the padding).
    ax, ay = rot[:2, 0], rot[:2, 1]
    ang = np.degrees(np.arctan2(rel @ ay, rel @ ax))  # (K, 8)
    centre = ang[:, 0:1]
    delta = np.mod(ang - centre + 180.0, 360.0) - 180.0
    dist = np.linalg.norm(rel, axis=-1).min(axis=1)  # (K,)
    travel = np.linalg.norm(origins[-1] - origins[0]) + 0.5
    pad = np.degrees(np.arctan2(travel, np.maximum(dist, 1e-3))) + 360.0 / n_az
    lo = centre[:, 0] + delta.min(axis=1) - pad
    hi = centre[:, 0] + delta.max(axis=1) + pad
    step = 360.0 / n_az
    c_lo = np.floor((lo - config.start_deg) / step).astype(np.int64)
    width = np.ceil((hi - lo) / step).astype(np.int64) + 1
    local = world_to_local(np.r_[sensor, 0.0], boxes[: len(objs), :3], objs.yaw)  # (K, 3); motion within the slack
    slack = travel + np.linalg.norm(objs.velocity, axis=1) * (t1 - t0)
    inside = (np.abs(local[:, 0]) < objs.size_wlh[:, 1] / 2 + slack) & (np.abs(local[:, 1]) < objs.size_wlh[:, 0] / 2 + slack)
    everywhere = inside | (width >= n_az)
    far = dist > config.max_range_m
    cols = np.arange(n_az)[:, None]
    mask = (np.mod(cols - c_lo[None, :], n_az) <= width[None, :]) | everywhere[None, :]  # (A, K)
    mask &= ~far[None, :]
    ai, ki = np.nonzero(mask)
    return ai.astype(np.int64), ki.astype(np.int64)

