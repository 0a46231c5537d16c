"""Where the synthetic world's objects go: streets, traffic, parking, people, road works and clutter.

Layout happens in road coordinates of the main road (s along it, d to its left). The ego drives straight in the
inner +u lane. Most scenes have a cross street at ``s = cross_s``; vehicles drive along both streets, change
lanes, and turn at the intersection (constant yaw rate: an arc). Vehicles park parallel, angled or perpendicular;
pedestrians walk and stand on the sidewalks, cross anywhere at any angle, and stand or walk in groups; cyclists
ride on the road; buses drive and wait at stops. Look-alike clutter (bollards, signs, bins, hydrants, benches,
bushes, parked scooters, planter pots) lines the sidewalks beside poles, trees, walls, curbs and buildings; road
works and the permanent furniture that looks like cones and barriers are ``synth_roadside``'s. Objects never overlap
each other or the ego car at any time of the scene (rejection sampling on bounding circles over a 50 ms grid; fixed
furniture tests the boxes themselves), except the decorative layer (buildings, walls, curbs, tree crowns), which is
not collision-checked.
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.data.synth_kinds import KIND_SPECS, Kind
from streamdet.data.synth_road import (
    BUILDING_LINE_M,
    CROSS_HALF_WIDTH_M,
    EGO_LANE_M,
    LANE_OFFSETS_M,
    LANE_WIDTH_M,
    PARKING_OFFSET_M,
    ROAD_HALF_WIDTH_M,
    SIDEWALK_OUTER_M,
    ground_height,
)
from streamdet.data.synth_roadside import place_lookalikes, place_stray_cones, place_work_zone
from streamdet.data.synth_shapes import build_shape
from streamdet.data.synth_world import Objects, Parts, Scene, WorldConfig, wrap_angle

# Instance albedos, drawn per object; the dark ones reflect little light and little laser alike.
CAR_COLORS = np.array(
    [[0.75, 0.08, 0.08], [0.08, 0.2, 0.7], [0.9, 0.9, 0.88], [0.06, 0.06, 0.07], [0.6, 0.62, 0.65], [0.03, 0.03, 0.04],
     [0.95, 0.75, 0.1], [0.1, 0.45, 0.2], [0.45, 0.05, 0.35], [0.2, 0.55, 0.8], [0.35, 0.35, 0.37], [0.1, 0.12, 0.2]],
    dtype=np.float32,
)
CLOTH_COLORS = np.array(
    [[0.8, 0.1, 0.1], [0.1, 0.3, 0.8], [0.95, 0.95, 0.9], [0.1, 0.1, 0.1], [0.9, 0.6, 0.1], [0.2, 0.6, 0.3],
     [0.55, 0.25, 0.6], [0.85, 0.8, 0.2], [0.05, 0.05, 0.06], [0.4, 0.4, 0.42]],
    dtype=np.float32,
)
TROUSER_COLORS = np.array([[0.1, 0.12, 0.25], [0.15, 0.15, 0.15], [0.35, 0.3, 0.25], [0.25, 0.3, 0.45], [0.05, 0.05, 0.05]], dtype=np.float32)
BUILDING_COLORS = np.array([[0.78, 0.7, 0.56], [0.6, 0.3, 0.22], [0.62, 0.62, 0.6], [0.85, 0.82, 0.75], [0.45, 0.5, 0.55]], dtype=np.float32)
FURNITURE_COLORS = np.array([[0.15, 0.3, 0.15], [0.3, 0.3, 0.32], [0.7, 0.1, 0.1], [0.9, 0.75, 0.1], [0.1, 0.2, 0.5], [0.8, 0.8, 0.8]], dtype=np.float32)
BARRIER_COLORS = np.array([[0.85, 0.08, 0.08], [0.95, 0.5, 0.05], [0.9, 0.9, 0.88], [0.95, 0.8, 0.1]], dtype=np.float32)
DISTRACTOR_WEIGHTS = {Kind.BOLLARD: 0.22, Kind.SIGN: 0.12, Kind.BIN: 0.15, Kind.HYDRANT: 0.1, Kind.BENCH: 0.08,
                      Kind.BUSH: 0.2, Kind.SCOOTER: 0.15, Kind.PLANTER: 0.1}
# Scenery that is drawn but never collision-checked (others stand in or on it, as trees under crowns).
_UNCHECKED_SCENERY = (Kind.BUILDING, Kind.WALL, Kind.CURB, Kind.TREE_CROWN)
CROSS_LANES_M = (-1.5 * LANE_WIDTH_M, -0.5 * LANE_WIDTH_M, 0.5 * LANE_WIDTH_M, 1.5 * LANE_WIDTH_M)


def layout_scene(seed: int, index: int, config: WorldConfig) -> Scene:
    """The deterministic scene number ``index`` of a dataset generated with ``seed``."""
    rng = np.random.default_rng([int(seed), int(index), 0x5CE4E])
    road_origin = rng.uniform(300.0, 1800.0, size=2)
    road_yaw = float(rng.uniform(-math.pi, math.pi))
    ego_speed = 0.0 if rng.uniform() < config.ego_stopped_prob else float(rng.uniform(*config.ego_speed_mps))
    duration = float(config.sweep_duration_s + config.sample_interval_s * (config.samples_per_scene - 1))
    cross_s = float(rng.uniform(5.0, 25.0 + ego_speed * duration)) if rng.uniform() < config.intersection_prob else None
    ground_phase = float(rng.uniform(0, 2 * math.pi))
    placer = _Placer(rng, config, duration, ego_speed, cross_s)
    placer.populate()
    rows = placer.rows
    if not rows:
        raise RuntimeError("scene has no objects")  # populate() always places clutter
    u = np.array([math.cos(road_yaw), math.sin(road_yaw)])
    n = np.array([-math.sin(road_yaw), math.cos(road_yaw)])
    sd = np.stack([r["center_sd"] for r in rows])  # (K, 2)
    xy = sd[:, :1] * u + sd[:, 1:2] * n + road_origin  # (K, 2)
    velocity_sd = np.stack([r["velocity_sd"] for r in rows])
    shapes = [r["shape"] for r in rows]
    size = np.stack([s.size_wlh for s in shapes])
    ground = ground_height(xy[:, 0], xy[:, 1], ground_phase)
    z = np.array([r["z"] if r["z"] is not None else 0.0 for r in rows]) + ground + size[:, 2] / 2
    counts = np.array([len(s.mat) for s in shapes], dtype=np.int64)
    parts = Parts(
        start=np.cumsum(counts) - counts,
        count=counts,
        center=np.concatenate([s.center for s in shapes]),
        half=np.concatenate([s.half for s in shapes]),
        rot=np.concatenate([s.rot for s in shapes]),
        shape=np.concatenate([s.shape for s in shapes]),
        mat=np.concatenate([s.mat for s in shapes]),
        albedo=np.concatenate([s.albedo for s in shapes]).astype(np.float32),
        refl=np.concatenate([s.refl for s in shapes]),
        owner=np.repeat(np.arange(len(rows)), counts),
    )
    objects = Objects(
        kind=np.array([r["kind"] for r in rows], dtype=np.int64),
        size_wlh=size.astype(np.float64),
        center0=np.concatenate([xy, z[:, None]], axis=1),
        yaw=wrap_angle(np.array([r["yaw_road"] for r in rows]) + road_yaw),
        velocity=velocity_sd[:, :1] * u + velocity_sd[:, 1:2] * n,
        yaw_rate=np.array([r["yaw_rate"] for r in rows], dtype=np.float64),
        color=np.stack([r["color"] for r in rows]).astype(np.float32),
        color2=np.stack([r["color2"] for r in rows]).astype(np.float32),
        flag=np.array([r["flag"] for r in rows], dtype=bool),
        parked=np.array([r["parked"] for r in rows], dtype=bool),
        parts=parts,
    )
    sun_az = rng.uniform(0, 2 * math.pi)
    sun_el = math.radians(rng.uniform(25.0, 65.0))
    sun = np.array([math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el)])
    return Scene(
        name=f"synth-{int(seed)}-{int(index):04d}",
        index=int(index),
        seed=int(seed),
        config=config,
        objects=objects,
        road_origin_xy=road_origin,
        road_yaw=road_yaw,
        ego_speed_mps=ego_speed,
        sun_dir_world=sun,
        cross_s_m=cross_s,
        ground_phase=ground_phase,
    )


class _Placer:
    """Rejection sampling of non-overlapping object tracks in road coordinates (s, d)."""

    TIME_STEP_S = 0.05
    MAX_TRIES = 40

    def __init__(self, rng: np.random.Generator, config: WorldConfig, duration_s: float, ego_speed: float,
                 cross_s: float | None) -> None:
        self.rng = rng
        self.config = config
        self.cross_s = cross_s
        self.times = np.arange(0.0, duration_s + self.TIME_STEP_S, self.TIME_STEP_S)  # (T,)
        self.duration_s = duration_s
        self.s_lo = -config.margin_m
        self.s_hi = ego_speed * duration_s + config.margin_m
        # The ego car's footprint (centre ~1.4 m ahead of the rear axle) blocks its lane over time.
        self.tracks = [np.stack([1.4 + ego_speed * self.times, np.full_like(self.times, EGO_LANE_M)], axis=1)]  # (T, 2)
        self.radii = [2.7]
        self.track_boxes = [np.r_[self.tracks[0].min(axis=0), self.tracks[0].max(axis=0)]]  # (4,) per track
        self.rows: list[dict] = []
        # Per row: (track (T, 2), yaw (T,), half length, half width, bounds (4,)) of its box over time, None for the
        # decorative layer; ``clear_of_boxes`` tests fixed furniture against these (tighter than bounding circles).
        self.footprints: list[tuple | None] = []
        ego_track = self.tracks[0]
        self.footprints.append((ego_track, np.zeros(len(self.times)), 2.5, 1.05,
                                np.r_[ego_track.min(axis=0) - 2.8, ego_track.max(axis=0) + 2.8]))

    # ---- bookkeeping --------------------------------------------------------------------------------
    def _size(self, kind: Kind) -> np.ndarray:
        spec = KIND_SPECS[kind]
        jitter = np.clip(self.rng.normal(1.0, spec.size_jitter, size=3), 0.7, 1.4)
        return np.asarray(spec.size_wlh_m) * jitter

    def _in_cross(self, s: float, pad: float = 0.0) -> bool:
        return self.cross_s is not None and abs(s - self.cross_s) < CROSS_HALF_WIDTH_M + pad

    def _try_add(self, kind: Kind, s: float, d: float, yaw_road: float, speed: float, size: np.ndarray | None = None,
                 z: float | None = None, check: bool = True, yaw_rate: float = 0.0, flag: bool | None = None,
                 color=None, parked: bool = False) -> bool:
        """Place an object at road position (s, d) moving along its heading; False if it would collide.

        ``parked``: left there (kerb, bay, lot, rack), as opposed to waiting in traffic or at a stop; it becomes
        ``Objects.parked``, from which the attribute is taken (vehicle.parked vs vehicle.stopped)."""
        if parked and speed != 0.0:
            raise ValueError(f"a parked {Kind(kind).name.lower()} must stand still, got speed {speed!r} m/s")
        size = self._size(kind) if size is None else np.asarray(size, dtype=np.float64)
        if yaw_rate == 0.0:
            v = speed * np.array([math.cos(yaw_road), math.sin(yaw_road)])
            track = np.array([s, d]) + self.times[:, None] * v  # (T, 2)
        else:
            h = yaw_road + yaw_rate * self.times
            track = np.stack([s + speed / yaw_rate * (np.sin(h) - math.sin(yaw_road)),
                              d + speed / yaw_rate * (math.cos(yaw_road) - np.cos(h))], axis=1)
        # A bound on the bounding circle of the box the shape will get (its parts may reach past the nominal
        # size: a stride, a rider, the annotator's margin), so shapes are only built for accepted tracks.
        radius = 0.5 * math.hypot(size[0], size[1]) * 1.25 + 0.15
        if check and self._collides(track, radius):
            return False
        c1, c2 = self._colors(kind)
        if color is not None:
            c1 = np.asarray(color, dtype=np.float32)
        flag = self._flag(kind, speed) if flag is None else flag
        shape = build_shape(kind, size, self.rng, c1, c2, flag)
        if check:
            self._claim(track, max(radius, 0.5 * math.hypot(shape.size_wlh[0], shape.size_wlh[1])))
        yaw_t = yaw_road + yaw_rate * self.times  # (T,)
        reach = 0.5 * math.hypot(shape.size_wlh[0], shape.size_wlh[1])
        self.footprints.append(None if kind in _UNCHECKED_SCENERY else
                               (track, yaw_t, 0.5 * shape.size_wlh[1], 0.5 * shape.size_wlh[0],
                                np.r_[track.min(axis=0) - reach, track.max(axis=0) + reach]))
        self.rows.append(
            {
                "kind": int(kind),
                "shape": shape,
                "center_sd": np.array([s, d]),
                "z": z,  # height of the box bottom above the ground (None: on it)
                "yaw_road": yaw_road,
                "yaw_rate": yaw_rate,
                "velocity_sd": speed * np.array([math.cos(yaw_road), math.sin(yaw_road)]),
                "color": c1,
                "color2": c2,
                "flag": flag,
                "parked": bool(parked),
            }
        )
        return True

    def _collides(self, track: np.ndarray, radius: float) -> bool:
        """Whether a circle of ``radius`` moving along ``track`` (T, 2) comes closer than the collision margin to
        any claimed track. Only tracks whose padded bounding rectangles meet can collide; those are tested over the
        time grid."""
        lo, hi = track.min(axis=0), track.max(axis=0)
        pad = np.asarray(self.radii) + radius + self.config.collision_margin_m  # (K,)
        boxes = np.asarray(self.track_boxes)  # (K, 4) s_lo, d_lo, s_hi, d_hi
        near = np.flatnonzero((boxes[:, 0] - pad <= hi[0]) & (boxes[:, 2] + pad >= lo[0])
                              & (boxes[:, 1] - pad <= hi[1]) & (boxes[:, 3] + pad >= lo[1]))
        if not len(near):
            return False
        others = np.stack([self.tracks[i] for i in near], axis=1)  # (T, N, 2)
        gap = np.linalg.norm(others - track[:, None, :], axis=-1) - np.asarray(self.radii)[near] - radius  # (T, N)
        return bool(np.any(gap < self.config.collision_margin_m))

    def clear_of_boxes(self, s: float, d: float, yaw_road: float, half_l: float, half_w: float, margin_m: float = 0.25) -> bool:
        """Whether a fixed footprint (an oriented rectangle at (s, d)) stays ``margin_m`` clear of every placed
        object's box at every time (the ego's too). Long, thin furniture (rails, dividers, posts in a median) sits
        closer to traffic than bounding circles allow; this tests the boxes themselves."""
        core = max(half_l - half_w, 0.0)
        n = max(1, int(math.ceil(2 * core / 0.5)) + 1)
        along = np.linspace(-core, core, n)
        pts = np.array([s, d]) + along[:, None] * np.array([math.cos(yaw_road), math.sin(yaw_road)])  # (P, 2)
        pad = half_w + margin_m
        lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
        for fp in self.footprints:
            if fp is None:
                continue
            track, yaw_t, hl, hw, bounds = fp
            if bounds[0] > hi[0] or bounds[2] < lo[0] or bounds[1] > hi[1] or bounds[3] < lo[1]:
                continue
            rel = pts[None, :, :] - track[:, None, :]  # (T, P, 2)
            c, sn = np.cos(yaw_t)[:, None], np.sin(yaw_t)[:, None]  # (T, 1)
            lx = rel[..., 0] * c + rel[..., 1] * sn  # (T, P)
            ly = -rel[..., 0] * sn + rel[..., 1] * c
            if np.any((np.abs(lx) < hl + pad) & (np.abs(ly) < hw + pad)):
                return False
        return True

    def add_fixed(self, kind: Kind, s: float, d: float, yaw_road: float, size=None, color=None, flag: bool | None = None,
                  margin_m: float = 0.25) -> bool:
        """Place fixed furniture where ``clear_of_boxes`` allows, and claim its length as a row of small circles,
        so objects placed later (tested with circles) keep clear of it too."""
        size = self._size(kind) if size is None else np.asarray(size, dtype=np.float64)
        half_l, half_w = 0.5 * float(size[1]), 0.5 * float(size[0])
        if not self.clear_of_boxes(s, d, yaw_road, half_l, half_w, margin_m):
            return False
        self._try_add(kind, s, d, yaw_road, 0.0, size=size, check=False, color=color, flag=flag)
        core = max(half_l - half_w, 0.0)
        for a in np.linspace(-core, core, max(1, int(math.ceil(2 * core / 1.0)) + 1)):
            centre = np.array([s + a * math.cos(yaw_road), d + a * math.sin(yaw_road)])
            self._claim(np.tile(centre, (len(self.times), 1)), half_w + 0.05)
        return True

    def _claim(self, track: np.ndarray, radius: float) -> None:
        """Reserve the circle of ``radius`` along ``track`` (T, 2): later objects keep clear of it."""
        self.tracks.append(track)
        self.track_boxes.append(np.r_[track.min(axis=0), track.max(axis=0)])
        self.radii.append(radius)

    def _flag(self, kind: Kind, speed: float) -> bool:
        """The per-object switch: a cycle's rider (always when riding), a pedestrian's motion pose, a truck's box body."""
        if kind in (Kind.BICYCLE, Kind.MOTORCYCLE):
            return bool(speed > 0 or self.rng.uniform() < 0.2)
        if kind == Kind.PEDESTRIAN:
            return bool(speed > 0 or self.rng.uniform() < 0.6)
        return bool(self.rng.uniform() < 0.6)

    def _colors(self, kind: Kind) -> tuple[np.ndarray, np.ndarray]:
        """Main and second albedo of a new object."""
        rng = self.rng
        if kind in (Kind.CAR, Kind.TRUCK, Kind.BUS, Kind.MOTORCYCLE, Kind.SCOOTER):
            c = CAR_COLORS[rng.integers(len(CAR_COLORS))] * rng.uniform(0.85, 1.05)
            c2 = CAR_COLORS[rng.integers(len(CAR_COLORS))]
        elif kind in (Kind.PEDESTRIAN, Kind.BICYCLE):
            c = CLOTH_COLORS[rng.integers(len(CLOTH_COLORS))] * rng.uniform(0.8, 1.05)
            c2 = TROUSER_COLORS[rng.integers(len(TROUSER_COLORS))]
        elif kind == Kind.BUILDING:
            c = BUILDING_COLORS[rng.integers(len(BUILDING_COLORS))] * rng.uniform(0.9, 1.05)
            c2 = c
        elif kind in (Kind.TREE_CROWN, Kind.BUSH):
            c = np.array([0.18, 0.42, 0.15]) * rng.uniform(0.75, 1.15)
            c2 = c * 0.7
        elif kind == Kind.BARRIER:
            c = BARRIER_COLORS[rng.integers(len(BARRIER_COLORS))]
            c2 = c
        elif kind == Kind.HYDRANT:
            c = np.array([0.8, 0.1, 0.08]) if rng.uniform() < 0.7 else np.array([0.9, 0.8, 0.1])
            c2 = c
        else:
            c = FURNITURE_COLORS[rng.integers(len(FURNITURE_COLORS))] * rng.uniform(0.85, 1.05)
            c2 = FURNITURE_COLORS[rng.integers(len(FURNITURE_COLORS))]
        return np.clip(c, 0, 1).astype(np.float32), np.clip(c2, 0, 1).astype(np.float32)

    # ---- layout -------------------------------------------------------------------------------------
    def populate(self) -> None:
        c, rng = self.config, self.rng

        def count(r: tuple[int, int]) -> int:
            return int(rng.integers(r[0], r[1] + 1))

        self._clutter()
        for _ in range(count(c.construction_zones)):
            self._construction_zone()
        lane_kinds = (Kind.CAR,) * 7 + (Kind.TRUCK,)
        if self.cross_s is not None:  # before the lane traffic, so turns still find room in dense traffic
            self._repeat(count(c.cross_vehicles), self._cross_or_turning_vehicle)
        self._repeat(count(c.buses), self._bus)
        self._repeat(count(c.lane_vehicles), lambda: self._lane_vehicle(lane_kinds[rng.integers(len(lane_kinds))]))
        self._repeat(count(c.motorcycles), self._motorcycle)
        self._repeat(count(c.bicycles), self._bicycle)  # before the parked cars: cyclists ride past parked rows
        self._repeat(count(c.parked_vehicles), self._parked_vehicle)
        for _ in range(count(c.pedestrian_groups)):
            self._pedestrian_group()
        self._repeat(count(c.pedestrians), self._pedestrian)
        place_stray_cones(self, count(c.stray_cones))
        place_lookalikes(self)  # fixed furniture keeps clear of the boxes of everything placed so far
        self._distractors()
        if self.cross_s is not None:  # last, so the main street's layout does not depend on it
            self._repeat(count(c.cross_pedestrians), self._cross_pedestrian)

    def _repeat(self, count: int, place) -> None:
        for _ in range(int(count)):
            for _ in range(self.MAX_TRIES):
                if place():
                    break

    def _s(self) -> float:
        return float(self.rng.uniform(self.s_lo, self.s_hi))

    def _side(self) -> float:
        return 1.0 if self.rng.uniform() < 0.5 else -1.0

    def _lane_vehicle(self, kind: Kind) -> bool:
        rng = self.rng
        d = LANE_OFFSETS_M[rng.integers(len(LANE_OFFSETS_M))] + rng.normal(0, 0.2)
        yaw = (0.0 if d < 0 else math.pi) + rng.normal(0, 0.02)
        if rng.uniform() < 0.2:  # changing lanes or pulling out: heading a few degrees off the road
            yaw += float(rng.choice([-1, 1]) * rng.uniform(0.08, 0.35))
        top = {Kind.CAR: 14.0, Kind.TRUCK: 10.0, Kind.BUS: 9.0, Kind.MOTORCYCLE: 14.0}[kind]
        speed = 0.0 if rng.uniform() < 0.15 else float(rng.uniform(2.0, top))  # some wait at a light
        s = self._s()
        if self._in_cross(s, 2.0) and speed == 0.0:
            return False  # nobody waits inside the intersection
        return self._try_add(kind, s, d, yaw, speed)

    def _bus(self) -> bool:
        rng = self.rng
        if rng.uniform() < 0.35:  # at a stop by the curb: waiting for passengers (stopped), not parked
            side = self._side()
            s = self._s()
            if self._in_cross(s, 8.0):
                return False
            return self._try_add(Kind.BUS, s, side * (PARKING_OFFSET_M - 0.6), (0.0 if side < 0 else math.pi) + rng.normal(0, 0.03), 0.0)
        return self._lane_vehicle(Kind.BUS)

    def _cross_or_turning_vehicle(self) -> bool:
        rng = self.rng
        kind = Kind.CAR if rng.uniform() < 0.85 else Kind.TRUCK
        xs = float(self.cross_s)
        if rng.uniform() < 0.5:  # along the cross street (heading +-n), some waiting before the intersection
            lane = CROSS_LANES_M[rng.integers(len(CROSS_LANES_M))]
            heading = math.pi / 2 if lane > 0 else -math.pi / 2  # right-hand traffic on the cross street
            d = float(rng.uniform(-55.0, 55.0))
            # waiting (stopped, as at a light: never parked, the cross street has no parking) or driving
            speed = 0.0 if abs(d) > ROAD_HALF_WIDTH_M + 3 and rng.uniform() < 0.4 else float(rng.uniform(2.0, 10.0))
            if speed == 0.0 and abs(d) < ROAD_HALF_WIDTH_M + 2:
                return False
            return self._try_add(kind, xs + lane + rng.normal(0, 0.15), d, heading + rng.normal(0, 0.03), speed)
        # Turning at the intersection: an arc from a main-road lane into the cross street, caught mid-turn.
        right = rng.uniform() < 0.5
        radius = float(rng.uniform(5.0, 8.0) if right else rng.uniform(8.0, 11.0))
        progress0 = float(rng.uniform(-0.4, 1.0))  # how far into the quarter turn at t = 0 (rad)
        speed = float(rng.uniform(2.0, 5.0))
        speed = max(1.0, min(speed, radius * (math.pi / 2 + 0.35 - progress0) / self.duration_s))
        lane_d = -0.5 * LANE_WIDTH_M
        if right:  # clockwise round a centre on the right
            cs, cd = xs - 0.5 * LANE_WIDTH_M - radius, lane_d - radius
            s, d, heading, rate = cs + radius * math.sin(progress0), cd + radius * math.cos(progress0), -progress0, -speed / radius
        else:
            cs, cd = xs + 0.5 * LANE_WIDTH_M - radius, lane_d + radius
            s, d, heading, rate = cs + radius * math.sin(progress0), cd - radius * math.cos(progress0), progress0, speed / radius
        if rng.uniform() < 0.5:  # the same turn by traffic coming the other way: rotate by pi about the intersection
            s, d, heading = 2 * xs - s, -d, heading + math.pi
        return self._try_add(kind, s, d, heading, speed, yaw_rate=rate)

    def _motorcycle(self) -> bool:
        rng = self.rng
        if rng.uniform() < 0.3:  # parked on the sidewalk edge, at an angle
            side = self._side()
            s = self._s()
            if self._in_cross(s, 1.0):
                return False
            yaw = (math.pi / 2 if side > 0 else -math.pi / 2) + rng.uniform(-0.9, 0.9)
            return self._try_add(Kind.MOTORCYCLE, s, side * rng.uniform(8.9, 9.6), yaw, 0.0, flag=False, parked=True)
        return self._lane_vehicle(Kind.MOTORCYCLE)

    def _parked_vehicle(self) -> bool:
        rng = self.rng
        kind = Kind.TRUCK if rng.uniform() < 0.1 else Kind.CAR
        side = self._side()
        s = self._s()
        if self._in_cross(s, 3.0):
            return False
        along = 0.0 if side < 0 else math.pi
        style = rng.uniform()
        if style < 0.3:  # parallel, by the curb
            yaw = along + rng.normal(0, 0.04)
            return self._try_add(kind, s, side * (PARKING_OFFSET_M + rng.normal(0, 0.15)), yaw, 0.0, parked=True)
        size = self._size(kind)
        if style < 0.7:  # angled bays, nose in
            off = float(rng.uniform(math.radians(35), math.radians(60)))
        else:  # perpendicular bays
            off = math.pi / 2 + rng.normal(0, 0.06)
        yaw = along + side * (1 if side < 0 else -1) * off + (math.pi if rng.uniform() < 0.2 else 0.0)
        d = side * (ROAD_HALF_WIDTH_M - 1.2 + 0.5 * size[1] * abs(math.sin(off)))
        return self._try_add(kind, s, d, yaw, 0.0, size=size, parked=True)

    def _bicycle(self) -> bool:
        """One cyclist, or one parked bicycle or rack. What it is is drawn once and then tried at other places, so
        a busy road does not turn would-be riders into parked bicycles."""
        mode = self.rng.uniform()
        if mode < 0.2:  # riding on the road by the parking strip or in the outer lane (most bicycles stand parked)
            place = self._riding_bicycle
        elif mode < 0.26 and self.cross_s is not None:  # riding along the cross street
            place = self._cross_bicycle
        else:
            place = self._parked_bicycles
        return any(place() for _ in range(self.MAX_TRIES))

    def _riding_bicycle(self) -> bool:
        rng = self.rng
        side = self._side()
        yaw = (0.0 if side < 0 else math.pi) + rng.normal(0, 0.04)
        d = side * float(rng.choice([PARKING_OFFSET_M - 0.9, 1.5 * LANE_WIDTH_M + 1.0]))
        return self._try_add(Kind.BICYCLE, self._s(), d + rng.normal(0, 0.2), yaw, float(rng.uniform(2.5, 7.0)))

    def _cross_bicycle(self) -> bool:
        rng = self.rng
        lane = CROSS_LANES_M[0] - 1.0 if rng.uniform() < 0.5 else CROSS_LANES_M[-1] + 1.0
        heading = math.pi / 2 if lane > 0 else -math.pi / 2
        return self._try_add(Kind.BICYCLE, self.cross_s + lane, float(rng.uniform(-50, 50)), heading, float(rng.uniform(2.5, 6.0)))

    def _parked_bicycles(self) -> bool:
        """A bicycle parked on the sidewalk, alone or in a rack of several side by side."""
        rng = self.rng
        side = self._side()
        s = self._s()
        if self._in_cross(s, 2.0):
            return False
        d = side * rng.uniform(11.0, 13.0)  # racks and lampposts by the shop fronts, behind the parked cars and clutter
        if rng.uniform() < 0.75:
            return self._try_add(Kind.BICYCLE, s, d, float(rng.uniform(-math.pi, math.pi)), 0.0, flag=False, parked=True)
        # A rack: bicycles side by side a stand apart, front wheels towards the road, hiding each other when seen
        # along the row. The rack is claimed as a whole; its bicycles are not tested against each other.
        yaw = (math.pi / 2 if side > 0 else -math.pi / 2) + rng.normal(0, 0.1)
        count, gap = int(rng.integers(2, 4)), float(rng.uniform(0.85, 1.0))  # stands wider than a box with its margins
        span = gap * (count - 1)
        rack = np.tile([s + span / 2, d], (len(self.times), 1))  # (T, 2) static
        radius = 0.5 * math.hypot(span + 0.8, 2.0)
        if self._collides(rack, radius):
            return False
        self._claim(rack, radius)
        for j in range(count):
            if rng.uniform() < 0.15:
                continue  # an empty stand
            self._try_add(Kind.BICYCLE, s + gap * j, d, yaw + rng.normal(0, 0.01), 0.0, check=False, flag=False, parked=True)
        return True

    def _pedestrian(self) -> bool:
        rng = self.rng
        mode = rng.uniform()
        side = self._side()
        s = self._s()
        if mode < 0.4:  # walking along the sidewalk
            yaw = (0.0 if rng.uniform() < 0.5 else math.pi) + rng.normal(0, 0.08)
            return self._try_add(Kind.PEDESTRIAN, s, side * rng.uniform(9.2, 13.2), yaw, float(rng.uniform(0.8, 1.8)))
        if mode < 0.65:  # standing on the sidewalk
            return self._try_add(Kind.PEDESTRIAN, s, side * rng.uniform(9.0, 13.2), float(rng.uniform(-math.pi, math.pi)), 0.0)
        if mode < 0.8 and self.cross_s is not None:  # on the crosswalks of the cross street
            edge = self.cross_s + float(rng.choice([-1, 1])) * (CROSS_HALF_WIDTH_M - 1.5)
            yaw = (math.pi / 2 if side < 0 else -math.pi / 2) + rng.normal(0, 0.1)
            return self._try_add(Kind.PEDESTRIAN, edge + rng.normal(0, 0.6), side * rng.uniform(0.0, 10.0), yaw, float(rng.uniform(0.8, 1.6)))
        # Crossing anywhere, at any angle, sometimes stopping in the middle.
        yaw = (math.pi / 2 if side < 0 else -math.pi / 2) + rng.uniform(-0.7, 0.7)
        speed = 0.0 if rng.uniform() < 0.2 else float(rng.uniform(0.8, 1.8))
        return self._try_add(Kind.PEDESTRIAN, s, side * rng.uniform(0.0, 10.0), yaw, speed)

    def _cross_pedestrian(self) -> bool:
        """Someone on a sidewalk of the cross street, beyond the corners: hidden by the corner blocks until the ego
        nears the intersection and looks down the cross street (annotated all the same, as nuScenes does)."""
        rng = self.rng
        s = self.cross_s + float(rng.choice([-1, 1])) * rng.uniform(CROSS_HALF_WIDTH_M + 0.6, CROSS_HALF_WIDTH_M + 4.5)
        d = self._side() * rng.uniform(BUILDING_LINE_M + 0.5, 60.0)
        if rng.uniform() < 0.6:  # walking along the cross street
            yaw = (math.pi / 2 if rng.uniform() < 0.5 else -math.pi / 2) + rng.normal(0, 0.08)
            return self._try_add(Kind.PEDESTRIAN, s, d, yaw, float(rng.uniform(0.8, 1.8)))
        return self._try_add(Kind.PEDESTRIAN, s, d, float(rng.uniform(-math.pi, math.pi)), 0.0)

    def _pedestrian_group(self) -> None:
        rng = self.rng
        size = int(rng.integers(2, 6))
        side = self._side()
        walking = rng.uniform() < 0.5
        crossing = walking and rng.uniform() < 0.4
        for _ in range(self.MAX_TRIES):
            s = self._s()
            d = side * (rng.uniform(2.0, 7.0) if crossing else rng.uniform(9.5, 12.5))
            if crossing:
                yaw = (math.pi / 2 if side < 0 else -math.pi / 2) + rng.uniform(-0.4, 0.4)
            else:
                yaw = (0.0 if rng.uniform() < 0.5 else math.pi) + rng.normal(0, 0.1)
            speed = float(rng.uniform(0.8, 1.5)) if walking else 0.0
            placed = 0
            for i in range(size):
                off = rng.normal(0, 0.7, size=2) + (np.array([i * 0.8, 0.0]) if walking else 0.0)
                heading = yaw if walking else float(rng.uniform(-math.pi, math.pi))
                placed += self._try_add(Kind.PEDESTRIAN, s + off[0], d + off[1], heading if not walking else yaw, speed)
            if placed:
                return

    def _construction_zone(self) -> None:
        place_work_zone(self, BARRIER_COLORS)

    def _distractors(self) -> None:
        """Look-alikes along both sidewalks (and the cross street's corners), collision-checked."""
        rng = self.rng
        kinds = list(DISTRACTOR_WEIGHTS)
        weights = np.array([DISTRACTOR_WEIGHTS[k] for k in kinds])
        lo, hi = self.config.distractor_spacing_m
        for side in (-1.0, 1.0):
            s = self.s_lo - 20.0 + rng.uniform(0, hi)
            while s < self.s_hi + 20.0:
                kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
                if not self._in_cross(s, 0.5):
                    if kind in (Kind.BOLLARD, Kind.SIGN, Kind.HYDRANT, Kind.PLANTER):
                        d = rng.uniform(8.8, 9.3)
                    elif kind == Kind.BUSH:
                        d = rng.uniform(12.3, 13.4)
                    else:
                        d = rng.uniform(9.3, 13.0)
                    yaw = (0.0 if side < 0 else math.pi) + (rng.uniform(-math.pi, math.pi) if kind in (Kind.SCOOTER, Kind.BIN) else rng.normal(0, 0.1))
                    self._try_add(kind, s, side * d, yaw, 0.0)
                    if kind == Kind.BOLLARD and rng.uniform() < 0.6:  # bollards come in rows
                        for j in range(1, int(rng.integers(2, 5))):
                            self._try_add(Kind.BOLLARD, s + 1.5 * j, side * d, 0.0, 0.0)
                s += rng.uniform(lo, hi)
        if self.cross_s is not None:  # corners of the intersection
            for ds in (-1.0, 1.0):
                for dd in (-1.0, 1.0):
                    for j in range(int(rng.integers(0, 4))):
                        self._try_add(Kind.BOLLARD, self.cross_s + ds * (CROSS_HALF_WIDTH_M + 0.4), dd * (ROAD_HALF_WIDTH_M + 1.0 + 1.4 * j), 0.0, 0.0)

    def _clutter(self) -> None:
        rng = self.rng
        span_lo, span_hi = self.s_lo - 30.0, self.s_hi + 30.0
        if self.cross_s is not None:
            self._cross_buildings()
        for side in (-1.0, 1.0):
            s = span_lo + rng.uniform(0, 15)
            while s < span_hi:  # street lights
                if not self._in_cross(s, 0.5):
                    self._try_add(Kind.POLE, s, side * 8.9, 0.0, 0.0)
                s += rng.uniform(15.0, 30.0)
            s = span_lo + rng.uniform(0, 10)
            while s < span_hi:  # trees: a trunk with a crown on top (the crown is not collision-checked)
                if not self._in_cross(s, 2.0) and self._try_add(Kind.TREE_TRUNK, s, side * 12.6, 0.0, 0.0):
                    trunk = self.rows[-1]
                    crown = self._size(Kind.TREE_CROWN)
                    self._try_add(Kind.TREE_CROWN, s, side * 12.6, float(rng.uniform(0, math.pi)), 0.0, size=crown,
                                  z=trunk["shape"].size_wlh[2] - 0.2, check=False)
                s += rng.uniform(12.0, 35.0)
            s = span_lo
            while s < span_hi:  # curbs along the road edge, broken at the cross street and at driveways
                length = float(rng.uniform(8.0, 30.0))
                a, b = s, s + length
                if self.cross_s is not None and a < self.cross_s + CROSS_HALF_WIDTH_M and b > self.cross_s - CROSS_HALF_WIDTH_M:
                    b = self.cross_s - CROSS_HALF_WIDTH_M
                    if b - a > 1.0:
                        self._curb(a, b, side)
                    s = self.cross_s + CROSS_HALF_WIDTH_M
                    continue
                self._curb(a, b, side)
                s = b + (rng.uniform(3.0, 6.0) if rng.uniform() < 0.2 else 0.0)
            s = span_lo
            while s < span_hi:  # building blocks with gaps; some gaps fenced by a low wall
                length = float(rng.uniform(12.0, 45.0))
                depth = float(rng.uniform(8.0, 16.0))
                height = float(rng.uniform(5.0, 22.0))
                if self.cross_s is not None and s < self.cross_s + CROSS_HALF_WIDTH_M + 5 and s + length > self.cross_s - CROSS_HALF_WIDTH_M - 5:
                    length = self.cross_s - CROSS_HALF_WIDTH_M - 5 - s
                    if length < 4.0:
                        s = self.cross_s + CROSS_HALF_WIDTH_M + 5
                        continue
                d = side * (BUILDING_LINE_M + rng.uniform(0, 3.0) + depth / 2)
                # l (the block's length) along the road, w its depth
                self._try_add(Kind.BUILDING, s + length / 2, d, 0.0, 0.0, size=[depth, length, height], check=False)
                gap = float(rng.uniform(3.0, 18.0))
                if not self._in_cross(s + length + gap / 2, gap / 2 + 1):
                    if rng.uniform() < 0.5:
                        self._try_add(Kind.WALL, s + length + gap / 2, side * (SIDEWALK_OUTER_M + 0.3), 0.0, 0.0,
                                      size=[0.3, gap, 1.4], check=False)
                    self._lot(s + length, gap, side)
                s += length + gap

    def _lot(self, s0: float, gap: float, side: float) -> None:
        """The yard or small lot between two blocks (``s0`` to ``s0 + gap``): cars parked nose-in, or people standing
        and bicycles leant against the walls; mostly hidden by the blocks and walls, and annotated all the same (as
        nuScenes annotates what its cameras or LiDAR catch of them). The cars sit in bays 2.8 m apart, so they are
        not collision-checked (their bounding circles would overlap)."""
        rng = self.rng
        if rng.uniform() < self.config.lot_prob:
            for j in range(int((gap - 0.6) // 2.8)):
                if rng.uniform() < 0.3:
                    continue  # an empty bay
                size = self._size(Kind.CAR)
                d = side * (SIDEWALK_OUTER_M + 1.0 + rng.uniform(0.0, 1.5) + size[1] / 2)
                yaw = side * math.pi / 2 + (math.pi if rng.uniform() < 0.5 else 0.0) + rng.normal(0, 0.05)
                self._try_add(Kind.CAR, s0 + 1.7 + 2.8 * j, d, yaw, 0.0, size=size, check=False, parked=True)
            return
        for _ in range(int(rng.integers(1, 6))):
            kind = Kind.PEDESTRIAN if rng.uniform() < 0.7 else Kind.BICYCLE
            yaw = float(rng.uniform(-math.pi, math.pi))
            self._try_add(kind, s0 + rng.uniform(0.7, gap - 0.7), side * (SIDEWALK_OUTER_M + rng.uniform(0.8, 4.0)), yaw, 0.0, flag=False,
                          parked=kind == Kind.BICYCLE)

    def _cross_buildings(self) -> None:
        """Blocks lining the cross street beyond the main road's building line, on its four corners."""
        rng = self.rng
        for ds in (-1.0, 1.0):
            for dd in (-1.0, 1.0):
                d = BUILDING_LINE_M
                while d < 70.0:
                    length = float(rng.uniform(10.0, 35.0))
                    depth = float(rng.uniform(8.0, 16.0))
                    s = self.cross_s + ds * (CROSS_HALF_WIDTH_M + 5.0 + rng.uniform(0, 2.0) + depth / 2)
                    self._try_add(Kind.BUILDING, s, dd * (d + length / 2), math.pi / 2, 0.0,
                                  size=[depth, length, float(rng.uniform(5.0, 22.0))], check=False)
                    d += length + float(rng.uniform(2.0, 12.0))

    def _curb(self, a: float, b: float, side: float) -> None:
        height = float(self.rng.uniform(0.1, 0.16))
        self._try_add(Kind.CURB, (a + b) / 2, side * (ROAD_HALF_WIDTH_M + 0.1), 0.0, 0.0, size=[0.2, b - a, height], check=False)
