"""The synthetic world: a straight street with moving and parked road users, static clutter and an ego car.

Frames and time
---------------
The world frame is the nuScenes global frame: z up, the ground is the plane z = 0 and the ego pose has z = 0,
no roll or pitch (as nuScenes ego poses nearly have). A scene has a time axis ``t`` in seconds from the scene
start; every object moves on a straight line at constant velocity with its heading fixed, so its pose at any t
is exact and the nuScenes centred-difference velocity equals its true velocity. Key frames (samples) sit at
``sample_times_s``; a sample's timestamp is the END of its LiDAR sweep (nuScenes: the time the rotation
completes), and its annotated boxes are the poses at that timestamp.

The street runs along the road direction ``u`` with ``n`` to its left: lanes at lateral offsets
``+-1.75, +-5.25`` m (traffic on the right, ``-`` lanes drive along +u), a parking strip at ``+-7.6`` m, sidewalks
from 8.5 to 13.5 m, buildings beyond. Objects never overlap each other or the ego car at any time of the scene
(rejection sampling on bounding circles over a 50 ms time grid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

# The world's version, written into every dataset (world.json) so results can be labelled with the world they were
# measured on. 1: boxes with painted faces on one straight street; 2: see the module docstring.
WORLD_VERSION = 1
WORLD_FILE = "world.json"  # beside a dataset's tables: the world version, roads and distractors per scene


class Kind(IntEnum):
    """What an object is; the first eight are annotated (nuScenes detection classes), the rest is clutter."""

    CAR = 0
    TRUCK = 1
    BUS = 2
    BICYCLE = 3
    MOTORCYCLE = 4
    PEDESTRIAN = 5
    BARRIER = 6
    TRAFFIC_CONE = 7
    POLE = 8
    TREE_TRUNK = 9
    TREE_CROWN = 10
    BUILDING = 11
    WALL = 12


@dataclass(frozen=True)
class KindSpec:
    detection_class: str | None  # one of CLASS_NAMES, None for unannotated clutter
    category: str | None  # nuScenes category name written to the category table
    size_wlh_m: tuple[float, float, float]  # mean size (nuScenes v1.0-trainval class means for road users)
    size_jitter: float  # relative standard deviation of each size component


KIND_SPECS: tuple[KindSpec, ...] = (
    KindSpec("car", "vehicle.car", (1.95, 4.62, 1.73), 0.06),
    KindSpec("truck", "vehicle.truck", (2.52, 6.94, 2.84), 0.10),
    KindSpec("bus", "vehicle.bus.rigid", (2.94, 11.19, 3.47), 0.06),
    KindSpec("bicycle", "vehicle.bicycle", (0.60, 1.70, 1.28), 0.06),
    KindSpec("motorcycle", "vehicle.motorcycle", (0.77, 2.11, 1.47), 0.06),
    KindSpec("pedestrian", "human.pedestrian.adult", (0.67, 0.73, 1.77), 0.06),
    KindSpec("barrier", "movable_object.barrier", (2.53, 0.50, 0.98), 0.04),
    KindSpec("traffic_cone", "movable_object.trafficcone", (0.41, 0.41, 1.07), 0.06),
    KindSpec(None, None, (0.25, 0.25, 6.5), 0.15),  # pole (street light)
    KindSpec(None, None, (0.45, 0.45, 2.6), 0.10),  # tree trunk
    KindSpec(None, None, (3.2, 3.2, 3.0), 0.15),  # tree crown, sits on its trunk
    KindSpec(None, None, (10.0, 25.0, 12.0), 0.0),  # building, sized per instance
    KindSpec(None, None, (0.3, 12.0, 1.4), 0.0),  # low wall / fence, sized per instance
)
NUM_ANNOTATED_KINDS = 8
DISTRACTOR_KINDS: tuple[Kind, ...] = ()  # unannotated look-alikes of small road users (counted by the stats)

# Road layout (lateral offsets in metres from the road centre line, + = left of the road direction).
LANE_WIDTH_M = 3.5
LANE_OFFSETS_M = (-1.5 * LANE_WIDTH_M, -0.5 * LANE_WIDTH_M, 0.5 * LANE_WIDTH_M, 1.5 * LANE_WIDTH_M)
EGO_LANE_M = LANE_OFFSETS_M[1]  # the inner lane along +u
PARKING_OFFSET_M = 7.6
ROAD_HALF_WIDTH_M = 8.5
SIDEWALK_OUTER_M = 13.5
BUILDING_LINE_M = 14.0

# Instance albedos, drawn per object.
CAR_COLORS = np.array(
    [[0.75, 0.08, 0.08], [0.08, 0.2, 0.7], [0.9, 0.9, 0.88], [0.06, 0.06, 0.07], [0.6, 0.62, 0.65],
     [0.95, 0.75, 0.1], [0.1, 0.45, 0.2], [0.45, 0.05, 0.35], [0.2, 0.55, 0.8]],
    dtype=np.float32,
)
CLOTH_COLORS = np.array(
    [[0.8, 0.1, 0.1], [0.1, 0.3, 0.8], [0.95, 0.95, 0.9], [0.1, 0.1, 0.1], [0.9, 0.6, 0.1], [0.2, 0.6, 0.3],
     [0.55, 0.25, 0.6], [0.85, 0.8, 0.2]],
    dtype=np.float32,
)
TROUSER_COLORS = np.array([[0.1, 0.12, 0.25], [0.15, 0.15, 0.15], [0.35, 0.3, 0.25], [0.25, 0.3, 0.45]], dtype=np.float32)
BUILDING_COLORS = np.array([[0.78, 0.7, 0.56], [0.6, 0.3, 0.22], [0.62, 0.62, 0.6], [0.85, 0.82, 0.75], [0.45, 0.5, 0.55]], dtype=np.float32)


@dataclass(frozen=True)
class WorldConfig:
    """How a synthetic scene is laid out and timed."""

    samples_per_scene: int = 10  # key frames per scene
    sample_interval_s: float = 0.5  # 2 Hz key frames, as nuScenes
    sweep_duration_s: float = 0.05  # one LiDAR rotation (20 Hz)
    ego_speed_mps: tuple[float, float] = (3.0, 12.0)  # uniform range when the ego drives
    ego_stopped_prob: float = 0.2  # chance the ego waits the whole scene
    lane_vehicles: tuple[int, int] = (6, 14)  # inclusive ranges of counts per scene
    parked_vehicles: tuple[int, int] = (3, 10)
    pedestrians: tuple[int, int] = (6, 18)
    bicycles: tuple[int, int] = (1, 4)
    motorcycles: tuple[int, int] = (0, 2)
    construction_zones: tuple[int, int] = (0, 2)  # rows of barriers with cones
    margin_m: float = 70.0  # objects are placed this far before and beyond the ego's path
    annotation_range_m: float = 80.0  # objects farther than this (BEV, from the ego) are not annotated
    collision_margin_m: float = 0.3  # clearance between bounding circles
    start_us: int = 1_600_000_000_000_000  # timestamp of scene 0's start
    scene_spacing_s: float = 100.0  # scene i starts at start_us + i * scene_spacing_s

    def __post_init__(self) -> None:
        if not (isinstance(self.samples_per_scene, int) and self.samples_per_scene >= 1):
            raise ValueError(f"WorldConfig.samples_per_scene must be an integer >= 1, got {self.samples_per_scene!r}")
        for name in ("sample_interval_s", "sweep_duration_s", "annotation_range_m", "margin_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"WorldConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if self.sweep_duration_s > self.sample_interval_s:
            raise ValueError(
                f"WorldConfig.sweep_duration_s ({self.sweep_duration_s}) exceeds sample_interval_s ({self.sample_interval_s})"
            )
        for name in ("lane_vehicles", "parked_vehicles", "pedestrians", "bicycles", "motorcycles", "construction_zones"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"WorldConfig.{name} must be a (min, max) count range with 0 <= min <= max, got {(lo, hi)}")


@dataclass(frozen=True, eq=False)
class Objects:
    """Every object of a scene as parallel arrays (K of them); poses are at scene time 0."""

    kind: np.ndarray  # (K,) int64 Kind
    size_wlh: np.ndarray  # (K, 3) float64 metres
    center0: np.ndarray  # (K, 3) float64 world centre at t = 0 (geometric centre)
    yaw: np.ndarray  # (K,) float64 heading about world z
    velocity: np.ndarray  # (K, 2) float64 world m/s, constant
    color: np.ndarray  # (K, 3) float32 main albedo 0..1 (body, shirt, facade)
    color2: np.ndarray  # (K, 3) float32 second albedo (trousers, cab)
    flag: np.ndarray  # (K,) bool: cycle with rider / truck with box body

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def annotated(self) -> np.ndarray:
        return self.kind < NUM_ANNOTATED_KINDS

    def boxes_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """(K, 9) world boxes x, y, z, w, l, h, yaw, vx, vy at scene time t (or (T, K, 9) for (T,) times)."""
        t = np.asarray(t_s, dtype=np.float64)
        centre = self.center0 + np.concatenate([self.velocity, np.zeros((len(self), 1))], axis=1) * t[..., None, None]
        k = centre.shape[:-1]
        return np.concatenate(
            [centre, np.broadcast_to(self.size_wlh, k + (3,)), np.broadcast_to(self.yaw[:, None], k + (1,)),
             np.broadcast_to(self.velocity, k + (2,))],
            axis=-1,
        )


@dataclass(frozen=True)
class Road:
    """A straight road strip: its centre line through ``origin_xy`` along ``yaw``, ``half_width_m`` to each side."""

    origin_xy: tuple[float, float]
    yaw: float
    half_width_m: float


@dataclass(frozen=True, eq=False)
class Scene:
    """One synthetic scene: the street, its objects, the ego's motion and the key-frame times."""

    name: str
    index: int
    seed: int
    config: WorldConfig
    objects: Objects
    road_origin_xy: np.ndarray  # (2,) world position of the road frame origin
    road_yaw: float  # direction u of the road (rad)
    ego_speed_mps: float
    sun_dir_world: np.ndarray  # (3,) unit vector towards the sun

    @property
    def road_u(self) -> np.ndarray:
        return np.array([math.cos(self.road_yaw), math.sin(self.road_yaw)])

    @property
    def road_n(self) -> np.ndarray:
        return np.array([-math.sin(self.road_yaw), math.cos(self.road_yaw)])

    @property
    def sample_times_s(self) -> np.ndarray:
        """(M,) key-frame times: each is the end of its sweep."""
        c = self.config
        return c.sweep_duration_s + c.sample_interval_s * np.arange(c.samples_per_scene)

    @property
    def start_us(self) -> int:
        return int(self.config.start_us + round(self.index * self.config.scene_spacing_s * 1e6))

    def timestamp_us(self, t_s: float) -> int:
        return self.start_us + int(round(t_s * 1e6))

    def ego_xy(self, t_s: float | np.ndarray) -> np.ndarray:
        """(2,) or (T, 2) ego (rear axle) position in the world at time t."""
        t = np.asarray(t_s, dtype=np.float64)[..., None]
        start = self.road_origin_xy + EGO_LANE_M * self.road_n
        return start + self.ego_speed_mps * t * self.road_u

    def ego2global(self, t_s: float) -> np.ndarray:
        """(4, 4) ego pose at time t: on the ground, heading along the road."""
        c, s = math.cos(self.road_yaw), math.sin(self.road_yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = self.ego_xy(t_s)
        return T

    @property
    def roads(self) -> tuple[Road, ...]:
        """The road strips of the scene (headings of vehicles are measured against these)."""
        return (Road((float(self.road_origin_xy[0]), float(self.road_origin_xy[1])), float(self.road_yaw), ROAD_HALF_WIDTH_M),)

    def to_road(self, xy_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates (s along the road, d to its left) of world (..., 2) positions."""
        rel = np.asarray(xy_world) - self.road_origin_xy
        return rel @ self.road_u, rel @ self.road_n


def make_scene(seed: int, index: int, config: WorldConfig = WorldConfig()) -> Scene:
    """The deterministic scene number ``index`` of a dataset generated with ``seed``."""
    rng = np.random.default_rng([int(seed), int(index), 0x5CE4E])
    road_origin = rng.uniform(300.0, 1800.0, size=2)
    road_yaw = float(rng.uniform(-math.pi, math.pi))
    if rng.uniform() < config.ego_stopped_prob:
        ego_speed = 0.0
    else:
        ego_speed = float(rng.uniform(*config.ego_speed_mps))
    duration = float(config.sweep_duration_s + config.sample_interval_s * (config.samples_per_scene - 1))
    placer = _Placer(rng, config, duration, ego_speed)
    placer.populate()
    objs = placer.objects()
    # Road frame -> world: s along u, d along n, from the road origin.
    u = np.array([math.cos(road_yaw), math.sin(road_yaw)])
    n = np.array([-math.sin(road_yaw), math.cos(road_yaw)])
    center0 = objs["center_sd"][:, :1] * u + objs["center_sd"][:, 1:2] * n + road_origin  # (K, 2)
    velocity = objs["velocity_sd"][:, :1] * u + objs["velocity_sd"][:, 1:2] * n  # (K, 2)
    sun_az = rng.uniform(0, 2 * math.pi)
    sun_el = math.radians(rng.uniform(30.0, 65.0))
    sun = np.array([math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el)])
    objects = Objects(
        kind=objs["kind"],
        size_wlh=objs["size"],
        center0=np.concatenate([center0, objs["z"][:, None]], axis=1),
        yaw=_wrap_angle(objs["yaw_road"] + road_yaw),
        velocity=velocity,
        color=objs["color"],
        color2=objs["color2"],
        flag=objs["flag"],
    )
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
    )


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + math.pi, 2 * math.pi) - math.pi


class _Placer:
    """Rejection sampling of non-overlapping object tracks in road coordinates (s, d)."""

    TIME_STEP_S = 0.05
    MAX_TRIES = 40

    def __init__(self, rng: np.random.Generator, config: WorldConfig, duration_s: float, ego_speed: float) -> None:
        self.rng = rng
        self.config = config
        self.times = np.arange(0.0, duration_s + self.TIME_STEP_S, self.TIME_STEP_S)  # (T,)
        self.s_lo = -config.margin_m
        self.s_hi = ego_speed * duration_s + config.margin_m
        # The ego car's footprint (centre ~1.4 m ahead of the rear axle) blocks its lane over time.
        self.tracks = [np.stack([1.4 + ego_speed * self.times, np.full_like(self.times, EGO_LANE_M)], axis=1)]  # (T, 2)
        self.radii = [2.7]
        self.rows: list[dict] = []

    # ---- bookkeeping --------------------------------------------------------------------------------
    def _size(self, kind: Kind) -> np.ndarray:
        spec = KIND_SPECS[kind]
        jitter = np.clip(self.rng.normal(1.0, spec.size_jitter, size=3), 0.8, 1.25)
        return np.asarray(spec.size_wlh_m) * jitter

    def _try_add(self, kind: Kind, s: float, d: float, yaw_road: float, speed: float, size: np.ndarray | None = None,
                 z: float | None = None, check: bool = True) -> bool:
        """Place an object at road position (s, d) moving along its heading; False if it would collide."""
        size = self._size(kind) if size is None else np.asarray(size, dtype=np.float64)
        v = speed * np.array([math.cos(yaw_road), math.sin(yaw_road)])
        track = np.array([s, d]) + self.times[:, None] * v  # (T, 2)
        radius = 0.5 * math.hypot(size[0], size[1])
        if check:
            others = np.stack(self.tracks, axis=1)  # (T, K, 2)
            gap = np.linalg.norm(others - track[:, None, :], axis=-1) - np.asarray(self.radii) - radius  # (T, K)
            if np.any(gap < self.config.collision_margin_m):
                return False
            self.tracks.append(track)
            self.radii.append(radius)
        color, color2 = self._colors(kind)
        self.rows.append(
            {
                "kind": int(kind),
                "size": size,
                "center_sd": np.array([s, d]),
                "z": size[2] / 2 if z is None else z,
                "yaw_road": yaw_road,
                "velocity_sd": v,
                "color": color,
                "color2": color2,
                "flag": self._flag(kind, speed),
            }
        )
        return True

    def _flag(self, kind: Kind, speed: float) -> bool:
        """The per-object switch: a cycle's rider (always when riding), a pedestrian's light skin, a truck's box body."""
        if kind in (Kind.BICYCLE, Kind.MOTORCYCLE):
            return bool(speed > 0 or self.rng.uniform() < 0.2)
        return bool(self.rng.uniform() < 0.6)

    def _colors(self, kind: Kind) -> tuple[np.ndarray, np.ndarray]:
        """Main and second albedo of a new object (body and cab, shirt and trousers, facade and glass)."""
        rng = self.rng
        if kind in (Kind.CAR, Kind.TRUCK, Kind.BUS, Kind.MOTORCYCLE):
            c = CAR_COLORS[rng.integers(len(CAR_COLORS))] * rng.uniform(0.85, 1.05)
            c2 = CAR_COLORS[rng.integers(len(CAR_COLORS))]
        elif kind in (Kind.PEDESTRIAN, Kind.BICYCLE):
            c = CLOTH_COLORS[rng.integers(len(CLOTH_COLORS))] * rng.uniform(0.8, 1.05)
            c2 = TROUSER_COLORS[rng.integers(len(TROUSER_COLORS))]
        elif kind == Kind.BUILDING:
            c = BUILDING_COLORS[rng.integers(len(BUILDING_COLORS))] * rng.uniform(0.9, 1.05)
            c2 = np.array([0.2, 0.25, 0.32]) * rng.uniform(0.8, 1.2)
        elif kind == Kind.TREE_CROWN:
            c = np.array([0.18, 0.42, 0.15]) * rng.uniform(0.75, 1.15)
            c2 = c * 0.7
        else:
            c = np.array([0.5, 0.5, 0.5])
            c2 = c
        return np.clip(c, 0, 1).astype(np.float32), np.clip(c2, 0, 1).astype(np.float32)

    def objects(self) -> dict:
        if not self.rows:
            raise RuntimeError("scene has no objects")  # populate() always places clutter
        return {
            "kind": np.array([r["kind"] for r in self.rows], dtype=np.int64),
            "size": np.stack([r["size"] for r in self.rows]).astype(np.float64),
            "center_sd": np.stack([r["center_sd"] for r in self.rows]),
            "z": np.array([r["z"] for r in self.rows], dtype=np.float64),
            "yaw_road": np.array([r["yaw_road"] for r in self.rows], dtype=np.float64),
            "velocity_sd": np.stack([r["velocity_sd"] for r in self.rows]),
            "color": np.stack([r["color"] for r in self.rows]).astype(np.float32),
            "color2": np.stack([r["color2"] for r in self.rows]).astype(np.float32),
            "flag": np.array([r["flag"] for r in self.rows], dtype=bool),
        }

    # ---- layout -------------------------------------------------------------------------------------
    def populate(self) -> None:
        c, rng = self.config, self.rng
        self._clutter()
        for _ in range(rng.integers(c.construction_zones[0], c.construction_zones[1] + 1)):
            self._construction_zone()
        lane_kinds = (Kind.CAR,) * 8 + (Kind.TRUCK, Kind.BUS)
        self._repeat(rng.integers(c.lane_vehicles[0], c.lane_vehicles[1] + 1), lambda: self._lane_vehicle(lane_kinds[rng.integers(len(lane_kinds))]))
        self._repeat(rng.integers(c.motorcycles[0], c.motorcycles[1] + 1), lambda: self._lane_vehicle(Kind.MOTORCYCLE))
        self._repeat(rng.integers(c.parked_vehicles[0], c.parked_vehicles[1] + 1), self._parked_vehicle)
        self._repeat(rng.integers(c.bicycles[0], c.bicycles[1] + 1), self._bicycle)
        self._repeat(rng.integers(c.pedestrians[0], c.pedestrians[1] + 1), self._pedestrian)

    def _repeat(self, count: int, place) -> None:
        for _ in range(int(count)):
            for _ in range(self.MAX_TRIES):
                if place():
                    break

    def _s(self) -> float:
        return float(self.rng.uniform(self.s_lo, self.s_hi))

    def _lane_vehicle(self, kind: Kind) -> bool:
        rng = self.rng
        d = LANE_OFFSETS_M[rng.integers(len(LANE_OFFSETS_M))] + rng.normal(0, 0.2)
        yaw = (0.0 if d < 0 else math.pi) + rng.normal(0, 0.02)
        top = {Kind.CAR: 14.0, Kind.TRUCK: 10.0, Kind.BUS: 9.0, Kind.MOTORCYCLE: 14.0}[kind]
        speed = 0.0 if rng.uniform() < 0.15 else float(rng.uniform(2.0, top))  # some wait at a light
        return self._try_add(kind, self._s(), d, yaw, speed)

    def _parked_vehicle(self) -> bool:
        rng = self.rng
        kind = Kind.TRUCK if rng.uniform() < 0.12 else Kind.CAR
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        yaw = (0.0 if side < 0 else math.pi) + rng.normal(0, 0.04)
        return self._try_add(kind, self._s(), side * (PARKING_OFFSET_M + rng.normal(0, 0.15)), yaw, 0.0)

    def _bicycle(self) -> bool:
        rng = self.rng
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        if rng.uniform() < 0.65:  # riding along the parking strip's inner edge
            yaw = (0.0 if side < 0 else math.pi) + rng.normal(0, 0.03)
            return self._try_add(Kind.BICYCLE, self._s(), side * (PARKING_OFFSET_M - 0.3), yaw, float(rng.uniform(2.5, 6.5)))
        yaw = float(rng.uniform(-math.pi, math.pi))  # parked on the sidewalk
        return self._try_add(Kind.BICYCLE, self._s(), side * rng.uniform(9.0, 12.5), yaw, 0.0)

    def _pedestrian(self) -> bool:
        rng = self.rng
        mode = rng.uniform()
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        if mode < 0.5:  # walking along the sidewalk
            yaw = (0.0 if rng.uniform() < 0.5 else math.pi) + rng.normal(0, 0.05)
            return self._try_add(Kind.PEDESTRIAN, self._s(), side * rng.uniform(9.2, 12.8), yaw, float(rng.uniform(0.8, 1.8)))
        if mode < 0.75:  # standing
            return self._try_add(Kind.PEDESTRIAN, self._s(), side * rng.uniform(9.0, 13.0), float(rng.uniform(-math.pi, math.pi)), 0.0)
        yaw = (math.pi / 2 if side < 0 else -math.pi / 2) + rng.normal(0, 0.1)  # crossing the street
        return self._try_add(Kind.PEDESTRIAN, self._s(), side * rng.uniform(6.0, 10.0), yaw, float(rng.uniform(0.8, 1.6)))

    def _construction_zone(self) -> None:
        rng = self.rng
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        s0 = self._s()
        count = int(rng.integers(3, 9))
        # A row of barriers along the parking strip: the long side (w) along the road, heading across it.
        for i in range(count):
            self._try_add(Kind.BARRIER, s0 + i * 2.7, side * (PARKING_OFFSET_M + rng.normal(0, 0.05)), math.pi / 2 + rng.normal(0, 0.03), 0.0)
        for i in range(int(rng.integers(1, 5))):
            self._try_add(Kind.TRAFFIC_CONE, s0 - 3.0 - i * 2.5, side * (PARKING_OFFSET_M - 0.6 + rng.normal(0, 0.2)), float(rng.uniform(-math.pi, math.pi)), 0.0)

    def _clutter(self) -> None:
        rng = self.rng
        span_lo, span_hi = self.s_lo - 30.0, self.s_hi + 30.0
        for side in (-1.0, 1.0):
            s = span_lo + rng.uniform(0, 15)
            while s < span_hi:  # street lights
                self._try_add(Kind.POLE, s, side * 8.9, 0.0, 0.0)
                s += rng.uniform(15.0, 30.0)
            s = span_lo + rng.uniform(0, 10)
            while s < span_hi:  # trees: a trunk with a crown on top (the crown is not collision-checked)
                if self._try_add(Kind.TREE_TRUNK, s, side * 12.6, 0.0, 0.0):
                    trunk = self.rows[-1]
                    crown = self._size(Kind.TREE_CROWN)
                    self._try_add(Kind.TREE_CROWN, s, side * 12.6, float(rng.uniform(0, math.pi)), 0.0, size=crown,
                                  z=trunk["size"][2] + crown[2] / 2 - 0.2, check=False)
                s += rng.uniform(12.0, 35.0)
            s = span_lo
            while s < span_hi:  # building blocks with gaps; some gaps fenced by a low wall
                length = float(rng.uniform(12.0, 45.0))
                depth = float(rng.uniform(8.0, 16.0))
                height = float(rng.uniform(5.0, 22.0))
                d = side * (BUILDING_LINE_M + rng.uniform(0, 3.0) + depth / 2)
                # l (the block's length) along the road, w its depth
                self._try_add(Kind.BUILDING, s + length / 2, d, 0.0, 0.0, size=[depth, length, height], check=False)
                gap = float(rng.uniform(3.0, 18.0))
                if rng.uniform() < 0.5:
                    self._try_add(Kind.WALL, s + length + gap / 2, side * (SIDEWALK_OUTER_M + 0.3), 0.0, 0.0,
                                  size=[0.3, gap, 1.4], check=False)
                s += length + gap
