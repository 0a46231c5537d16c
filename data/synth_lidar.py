"""A rotating 32-beam LiDAR ray-cast into the synthetic world, with a rolling scan.

The sensor turns as nuScenes' LIDAR_TOP (a Velodyne HDL-32E) does: clockwise seen from above, once per sweep,
starting at azimuth ``start_deg`` (180 deg: the LiDAR frame's -x, the car's left; the real sensor starts a few
degrees past that, behind-left) at ``t_end - sweep_duration`` and finishing at ``t_end``, the sweep's timestamp.
``LidarConfig.clockwise`` and ``start_deg`` say so (``scan_fraction`` maps an azimuth to the share of the sweep at
which the sensor points there); until world 6 the sensor turned counter-clockwise from 0 deg. Azimuth column a
fires its 32 beams together at ``(a + 0.5) / A`` of the sweep, from where the sensor is at that instant, and
sees every object where it is at that instant: a car at 15 m/s moves 0.75 m during one sweep, so its points
are smeared along its motion exactly as on a real rolling scan. Points are then expressed in the LiDAR frame at
``t_end`` (the ego motion within the sweep compensated, as nuScenes does), so static surfaces stay sharp while
moving objects keep their rolling-shutter displacement relative to their annotated pose at ``t_end``. The cameras
fire as the sensor crosses their optical axes (``synth_writer.camera_trigger_times_s``), as nuScenes' do.

Each beam meets the nearest part of an object (``synth_shapes``) or the undulating ground. Glass lets most beams
through to whatever is behind. Whether the pulse then comes back is the return model (``detection_probability``):
more likely for bright surfaces, near ones and those hit head-on (steeply so for glossy paint and metal), so dark
cars, far pedestrians and grazing surfaces lose points as they do on a real HDL-32E; a part thinner than the
beam's footprint (a bicycle's tubes, a far limb) returns in proportion to the share of the footprint it covers. A point's intensity follows
its surface's reflectance and the incidence, not its class.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.camera import invert_transform
from streamdet.core.boxes import box_corners_bev
from streamdet.core import sectors
from streamdet.core.sectors import angle_diff_deg
from streamdet.data.synth_materials import ground_reflectance, shade
from streamdet.data.synth_raycast import ray_box_entry, ray_shape_entry, world_to_local
from streamdet.data.synth_road import ray_ground_height
from streamdet.data.synth_world import Scene

GROUND_GLOSS = 0.3  # asphalt and paving return diffusely, even at grazing incidence

# Velodyne HDL-32E (nuScenes LIDAR_TOP): 32 beams evenly spaced from -30.67 to +10.67 deg.
HDL32E_ELEVATIONS_DEG: tuple[float, ...] = tuple(float(v) for v in np.linspace(-30.67, 10.67, 32))


@dataclass(frozen=True)
class LidarConfig:
    """The simulated sensor."""

    elevations_deg: tuple[float, ...] = HDL32E_ELEVATIONS_DEG  # beam elevations; ring index = position here
    azimuth_steps: int = 1080  # columns per rotation (0.33 deg, ~34.5 k rays)
    start_deg: float = 180.0  # azimuth (LiDAR frame, from +x towards +y) where each rotation starts
    clockwise: bool = True  # seen from above, as nuScenes' LIDAR_TOP turns (world 5 and before: counter-clockwise from 0)
    min_range_m: float = 1.0  # returns nearer than this are dropped (the car's own body)
    max_range_m: float = 100.0
    range_noise_m: float = 0.015  # standard deviation along the ray
    dropout: float = 0.005  # fraction of returns lost at random, on top of the return model
    detect_reflectance: float = 0.025  # the return model's reference reflectance (see detection_probability)
    detect_range_m: float = 28.0  # ... and reference range
    beam_exit_m: float = 0.01  # beam diameter at the sensor; with the divergence, the footprint a thin part may not fill
    beam_divergence_rad: float = 0.003  # full angle: the footprint grows by this much per metre of range
    intensity_gain: float = 1.1  # intensity = gain * 255 * reflectance * (0.3 + 0.7 cos(incidence)), clipped to 255
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
        if not isinstance(self.clockwise, bool):
            raise ValueError(f"LidarConfig.clockwise must be True or False, got {self.clockwise!r}")
        if not np.isfinite(self.start_deg):
            raise ValueError(f"LidarConfig.start_deg must be a finite angle, got {self.start_deg!r}")

    @property
    def turn_sign(self) -> float:
        """+1 counter-clockwise, -1 clockwise: the azimuth at sweep fraction f is ``start_deg + turn_sign * 360 f``."""
        return -1.0 if self.clockwise else 1.0


def scan_fraction(azimuth_deg, config: LidarConfig = LidarConfig()) -> np.ndarray:
    """The share of the sweep after which the sensor points at ``azimuth_deg`` (LiDAR frame): the time since the
    sweep start at which it crosses that azimuth, over the sweep's duration (``core.sectors.scan_fraction`` of this
    sensor's layout)."""
    return np.asarray(sectors.scan_fraction(np.asarray(azimuth_deg, dtype=np.float64), config.start_deg, config.clockwise))


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
    az = np.radians(config.start_deg + config.turn_sign * frac * 360.0)  # (A,) in scan order
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
    t_best = ray_ground_height(np.broadcast_to(origins[:, None, :], dirs.shape), dirs, scene.ground_phase).reshape(n_rays)  # (A * E,)
    best_obj = np.full(n_rays, -1, dtype=np.int64)
    best_refl = np.zeros(n_rays)
    best_cos = np.abs(dirs[..., 2]).reshape(n_rays)  # the ground's normal is nearly +z
    best_gloss = np.full(n_rays, GROUND_GLOSS)
    best_width = np.full(n_rays, np.inf)  # width of the surface hit across the beam (the ground: unbounded)

    ai, ki, beam_ok = _candidate_columns(scene, col_time, origins, rot, config)
    if len(ai):
        hits = _object_hits(scene, ai, ki, beam_ok, col_time, origins, dirs, t_best, rng)
        if hits is not None:
            r, t_hit, obj, refl, cos, gloss, width = hits
            t_best[r] = t_hit
            best_obj[r] = obj
            best_refl[r] = refl
            best_cos[r] = cos
            best_gloss[r] = gloss
            best_width[r] = width

    valid = (t_best >= config.min_range_m) & (t_best <= config.max_range_m)
    valid &= rng.uniform(size=n_rays) >= config.dropout
    idx = np.flatnonzero(valid)  # firing order: column-major over (azimuth, beam)
    t = t_best[idx] + rng.normal(0.0, config.range_noise_m, size=len(idx))
    a_idx, e_idx = idx // n_el, idx % n_el
    world = origins[a_idx] + t[:, None] * dirs[a_idx, e_idx]  # (N, 3)
    obj = best_obj[idx]
    on_ground = obj < 0
    refl_all = best_refl[idx].copy()
    if np.any(on_ground):
        s_road, d_road = scene.to_road(world[on_ground, :2])
        refl_all[on_ground] = ground_reflectance(s_road, d_road, scene.cross_s_m)
    cos = best_cos[idx]
    # The return model: whether a pulse comes back falls with range and incidence and rises with reflectance.
    fill = footprint_fill(best_width[idx], t_best[idx], config)
    p_return = detection_probability(refl_all * fill, cos, t_best[idx], best_gloss[idx], config)
    returned = rng.uniform(size=len(idx)) < p_return
    idx, t, a_idx, e_idx, world, obj, refl_all, cos = (v[returned] for v in (idx, t, a_idx, e_idx, world, obj, refl_all, cos))
    intensity = config.intensity_gain * 255.0 * refl_all * (0.3 + 0.7 * cos) + rng.normal(0.0, config.intensity_noise, size=len(idx))
    to_lidar = invert_transform(scene.ego2global(t_end_s) @ lidar2ego)
    xyz = world @ to_lidar[:3, :3].T + to_lidar[:3, 3]
    points = np.empty((len(idx), 5), dtype=np.float32)
    points[:, :3] = xyz
    points[:, 3] = np.clip(np.round(intensity), 0, 255)
    points[:, 4] = e_idx
    return SimSweep(t_end_s=float(t_end_s), points=points, time_s=(frac[a_idx] * sweep_s).astype(np.float32), hit=obj)


def detection_probability(reflectance: np.ndarray, cos_incidence: np.ndarray, range_m: np.ndarray,
                          gloss: np.ndarray | float = 0.5, config: LidarConfig = LidarConfig()) -> np.ndarray:
    """(N,) chance that a pulse returns: ``1 - exp(-signal)``, the signal proportional to the reflectance and to
    ``0.1 + 0.9 cos(incidence) ** gloss`` (glossy paint and metal send the pulse away unless hit head-on) and
    falling with the square of the range."""
    lobe = 0.1 + 0.9 * np.abs(np.asarray(cos_incidence)) ** np.asarray(gloss)
    signal = (np.asarray(reflectance) / config.detect_reflectance) * lobe
    signal = signal * (config.detect_range_m / np.maximum(np.asarray(range_m), 1e-3)) ** 2
    return 1.0 - np.exp(-signal)


def footprint_fill(width_m: np.ndarray, range_m: np.ndarray, config: LidarConfig = LidarConfig()) -> np.ndarray:
    """(N,) share of the beam's footprint a surface ``width_m`` across covers at ``range_m``: a part thinner than
    the footprint (a frame tube, a limb far away) sends back only that share of the pulse."""
    footprint = config.beam_exit_m + config.beam_divergence_rad * np.asarray(range_m)
    return np.minimum(np.asarray(width_m) / footprint, 1.0)


def _object_hits(scene: Scene, ai: np.ndarray, ki: np.ndarray, beam_ok: np.ndarray, col_time: np.ndarray, origins: np.ndarray,
                 dirs: np.ndarray, t_best: np.ndarray, rng: np.random.Generator):
    """Nearest part surface per ray over the candidate (column, object) pairs, nearer than the ground.

    Returns (rays, distance, object, reflectance, cos incidence, gloss, part width) or None. Each pair's rays are first tested
    against the object's box; only rays entering it are tested against its parts. A glass part lets a beam
    through (to whatever is behind) with the chance its material gives.
    """
    n_el = dirs.shape[1]
    objs = scene.objects
    pair_centres, pair_yaws, _ = objs.poses_at(col_time[ai], ki)  # (C, 3), (C,) per (column, object) pair
    o_pair = world_to_local(origins[ai], pair_centres, pair_yaws)  # (C, 3)
    pair, e = np.nonzero(beam_ok[ki])  # (Q,) one (pair, beam) per beam that may meet the pair's object
    a, k = ai[pair], ki[pair]
    ray = a * n_el + e
    yaws = pair_yaws[pair]
    half = objs.size_wlh[k][:, [1, 0, 2]] / 2  # (Q, 3) along x (l), y (w), z (h)
    o_local = o_pair[pair]
    d_local = world_to_local(dirs[a, e], 0.0, yaws)
    hit, t_box, _, _ = ray_box_entry(o_local, d_local, half)
    keep = np.flatnonzero(hit & (t_box < t_best[ray]))
    if not len(keep):
        return None
    parts = objs.parts
    pair, part = parts.expand(k[keep])
    q = keep[pair]  # (R,) the (ray, object) pair of each (ray, part) test
    rot_t = np.transpose(parts.rot[part], (0, 2, 1))  # (R, 3, 3) box -> part
    o_part = np.einsum("rij,rj->ri", rot_t, o_local[q] - parts.center[part])
    d_part = np.einsum("rij,rj->ri", rot_t, d_local[q])
    t_part, n_part = ray_shape_entry(o_part, d_part, parts.half[part], parts.shape[part])
    ok = np.flatnonzero(np.isfinite(t_part) & (t_part < t_best[ray[q]]))
    if not len(ok):
        return None
    part, q, t_part, n_part = part[ok], q[ok], t_part[ok], n_part[ok]
    p_part = o_part[ok] + t_part[:, None] * d_part[ok]
    _, alpha, refl, scale, gloss = shade(parts.mat[part], parts.albedo[part], parts.refl[part], p_part, parts.half[part], n_part)
    alpha &= rng.uniform(size=len(part)) < scale  # glass: most beams pass through
    part, q, t_part, n_part, refl, gloss = part[alpha], q[alpha], t_part[alpha], n_part[alpha], refl[alpha], gloss[alpha]
    r = ray[q]
    order = np.lexsort((t_part, r))  # nearest surface per ray
    order = order[np.r_[True, r[order][1:] != r[order][:-1]]] if len(order) else order
    part, q, t_part, n_part, refl, gloss, r = (v[order] for v in (part, q, t_part, n_part, refl, gloss, r))
    n_box = np.einsum("rij,rj->ri", parts.rot[part], n_part)  # (R, 3) normal in the box frame
    c, s = np.cos(yaws[q]), np.sin(yaws[q])
    n_world = np.stack([c * n_box[:, 0] - s * n_box[:, 1], s * n_box[:, 0] + c * n_box[:, 1], n_box[:, 2]], axis=1)
    cos = np.abs(np.sum(n_world * dirs[a[q], e[q]], axis=1))
    width = 2.0 * np.median(parts.half[part], axis=1)  # a tube's or limb's diameter, a panel's smaller side
    return r, t_part, k[q], refl, cos, gloss, width


def _candidate_columns(
    scene: Scene, col_time: np.ndarray, origins: np.ndarray, rot: np.ndarray, config: LidarConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column, object) pairs whose azimuth could meet (each object's azimuth span over the sweep, padded) and
    (K, E) bool: the beams whose elevation could meet each object."""
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
    delta = angle_diff_deg(ang, centre)
    dist = np.linalg.norm(rel, axis=-1).min(axis=1)  # (K,)
    travel = np.linalg.norm(origins[-1] - origins[0]) + 0.5
    pad = np.degrees(np.arctan2(travel, np.maximum(dist, 1e-3))) + 360.0 / n_az
    lo = centre[:, 0] + delta.min(axis=1) - pad
    hi = centre[:, 0] + delta.max(axis=1) + pad
    step = 360.0 / n_az
    # the first column of the span [lo, hi]: column a points at start + turn_sign * (a + 0.5) * step
    first_edge = lo if not config.clockwise else -hi
    c_lo = np.floor((first_edge - config.turn_sign * config.start_deg) / step).astype(np.int64)
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
    # Beams whose elevation could meet each object: from its box's bottom and top at its nearest and farthest
    # BEV distance, padded by a beam spacing and the sensor's tilt.
    rel_c = boxes[: len(objs), :2] - sensor
    reach = 0.5 * np.hypot(objs.size_wlh[:, 0], objs.size_wlh[:, 1]) + slack
    d_near = np.maximum(np.linalg.norm(rel_c, axis=1) - reach, 0.05)
    d_far = np.linalg.norm(rel_c, axis=1) + reach
    z_bottom = boxes[: len(objs), 2] - objs.size_wlh[:, 2] / 2 - origins[:, 2].mean()
    z_top = z_bottom + objs.size_wlh[:, 2]
    el_lo = np.degrees(np.arctan2(z_bottom, np.where(z_bottom < 0, d_near, d_far)))
    el_hi = np.degrees(np.arctan2(z_top, np.where(z_top > 0, d_near, d_far)))
    elev = np.asarray(config.elevations_deg)
    tilt = np.degrees(np.arccos(np.clip(rot[2, 2], -1.0, 1.0)))
    pad_el = float(np.max(np.abs(np.diff(np.sort(elev))), initial=1.0)) + tilt + 0.1
    beam_ok = (elev[None, :] >= el_lo[:, None] - pad_el) & (elev[None, :] <= el_hi[:, None] + pad_el)  # (K, E)
    beam_ok |= inside[:, None]
    return ai.astype(np.int64), ki.astype(np.int64), beam_ok

