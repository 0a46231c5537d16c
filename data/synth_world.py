"""The synthetic world: a street with an intersection, moving, turning and parked road users, look-alike
clutter and an ego car.

Frames and time
---------------
The world frame is the nuScenes global frame: z up; the ego pose has z = 0 and no roll or pitch (as nuScenes ego
poses nearly have); the ground undulates by a few centimetres around z = 0 (``synth_road.ground_height``) and
objects stand on it. A scene has a time axis ``t`` in seconds from the scene start; every object moves at constant
speed with a constant yaw rate (0 for straight tracks, the turn of a vehicle at the intersection otherwise), so its
pose at any t is exact (``Objects.boxes_at``) and its velocity is the derivative of that pose. Key frames (samples)
sit at ``sample_times_s``; a sample's timestamp is the END of its LiDAR sweep (nuScenes: the time the rotation
completes), and its annotated boxes are the poses at that timestamp.

Objects are not their boxes: each is a set of parts (``synth_shapes``) made of materials (``synth_materials``),
and its box is the tight box around the parts. Where things go is ``synth_layout``. ``WORLD_VERSION`` names this
world in every dataset written from it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.core.json_input import read_json
from streamdet.core.points import SWEEP_DURATION_S
from streamdet.data.synth_kinds import DISTRACTOR_KINDS, KIND_SPECS, NUM_ANNOTATED_KINDS, Kind, KindSpec  # noqa: F401
from streamdet.data.synth_road import (  # noqa: F401 (re-exported: the world's layout constants)
    BUILDING_LINE_M,
    EGO_LANE_M,
    LANE_OFFSETS_M,
    LANE_WIDTH_M,
    PARKING_OFFSET_M,
    ROAD_HALF_WIDTH_M,
    SIDEWALK_OUTER_M,
    ground_height,
)

# The world's version, written into every dataset (world.json) so results can be labelled with the world they were
# measured on. 1: boxes with class-painted faces on one straight street (until issue 18); 2: objects made of parts
# and materials, a return model, an intersection with turns and angled parking, look-alike clutter, curbs and an
# undulating ground; 3: bicycles of round, thinner tubes on silver rims, parked alone or in racks where they hide
# each other, cyclists placed before the parked rows (they were mostly squeezed out), people on the cross street's
# sidewalks hidden by the corner blocks, denser look-alikes on the sidewalks; 4: permanent furniture that looks
# like cones and barriers and is not annotated (delineator posts on medians, lane edges and corners, planter pots,
# more hydrants by the kerb; railings and guard rails in barrier-sized segments behind the kerb, concrete dividers
# and long planters on medians and sidewalks: ``synth_roadside``), and road works where real ones are (a lane
# closed by a taper of cones, works on the sidewalk, cones among the barriers, single cones beside parked cars); 5: the
# same scenes (layouts, sweeps and images byte for byte), annotated as the devkit counts: num_lidar_pts is the key
# frame's points inside the box (it counted the rays that hit the object), and a vehicle is parked only where the
# layout parked it (cars waiting in a cross-street lane and buses at a stop were called parked: now stopped); 6: the
# sensor timing of the real rig (docs/synth/timing.md): the LiDAR turns clockwise seen from above from 180 deg (the
# car's left), as nuScenes' LIDAR_TOP does (it turned counter-clockwise from 0 deg, the car's right), so the per-point
# times and the rolling-shutter smear follow it; each camera exposes when the LiDAR crosses its optical axis, 2.6 to
# 45 ms before the sweep's end (it exposed at the end), rendered with the ego and the objects at that moment, and its
# sample_data carries that timestamp and an ego_pose of that time. The same scenes (layouts and trajectories); the
# sweeps, images, masks, visibility and num_lidar_pts change, the annotations' poses do not.
WORLD_VERSION = 6
WORLD_FILE = "world.json"  # beside a dataset's tables: the world version, roads and distractors per scene
# world.json of 10,000 scenes is tens of MB; a larger file is no sidecar of ours and is not read to find out.
MAX_WORLD_BYTES = 512 << 20


def world_version_of(root: str | Path) -> int | None:
    """The synthetic world a dataset at ``root`` was generated in (its world.json's ``world_version``), None for a
    dataset without one (real nuScenes) or an unreadable one: what a report names beside its results, since the
    worlds differ (WORLD_VERSION's history)."""
    path = Path(root) / WORLD_FILE
    if not path.is_file():
        return None
    try:
        doc = read_json(path, "world file", MAX_WORLD_BYTES)
    except ValueError:
        return None
    version = doc.get("world_version") if type(doc) is dict else None
    return version if type(version) is int else None


@dataclass(frozen=True)
class WorldConfig:
    """How a synthetic scene is laid out and timed."""

    samples_per_scene: int = 10  # key frames per scene
    sample_interval_s: float = 0.5  # 2 Hz key frames, as nuScenes
    sweep_duration_s: float = SWEEP_DURATION_S  # one LiDAR rotation, as nuScenes
    ego_speed_mps: tuple[float, float] = (3.0, 12.0)  # uniform range when the ego drives
    ego_stopped_prob: float = 0.2  # chance the ego waits the whole scene
    lane_vehicles: tuple[int, int] = (9, 16)  # inclusive ranges of counts per scene; dense traffic hides what is behind it
    cross_vehicles: tuple[int, int] = (2, 5)  # on the cross street, some turning
    parked_vehicles: tuple[int, int] = (18, 34)  # city kerbs are lined with them: they hide each other and the sidewalk
    buses: tuple[int, int] = (16, 21)  # most drive out of the annotated range: the count keeps buses a tail class above 5 %
    pedestrians: tuple[int, int] = (10, 24)  # singles; groups come on top
    pedestrian_groups: tuple[int, int] = (1, 3)
    cross_pedestrians: tuple[int, int] = (10, 20)  # on the cross street's sidewalks, mostly hidden by the corner blocks
    bicycles: tuple[int, int] = (4, 8)
    motorcycles: tuple[int, int] = (5, 9)
    construction_zones: tuple[int, int] = (1, 4)  # road works: barriers by the kerb, closed lanes, sidewalk works, with cones
    stray_cones: tuple[int, int] = (1, 3)  # single cones beside parked cars and on sidewalks
    lot_prob: float = 0.6  # chance a gap between two blocks holds cars parked nose-in (a yard or a small lot)
    distractor_spacing_m: tuple[float, float] = (1.0, 2.8)  # gap between look-alikes along each sidewalk
    intersection_prob: float = 0.85  # chance a scene has a cross street
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
        for name in ("lane_vehicles", "cross_vehicles", "parked_vehicles", "buses", "pedestrians", "pedestrian_groups", "cross_pedestrians",
                     "bicycles", "motorcycles", "construction_zones", "stray_cones"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"WorldConfig.{name} must be a (min, max) count range with 0 <= min <= max, got {(lo, hi)}")
        lo, hi = self.distractor_spacing_m
        if not 0 < lo <= hi:
            raise ValueError(f"WorldConfig.distractor_spacing_m must be (min, max) with 0 < min <= max, got {(lo, hi)}")
        if not 0 <= self.intersection_prob <= 1:
            raise ValueError(f"WorldConfig.intersection_prob must be in [0, 1], got {self.intersection_prob!r}")


@dataclass(frozen=True, eq=False)
class Parts:
    """Every object's parts, concatenated; object k owns parts ``start[k] : start[k] + count[k]``."""

    start: np.ndarray  # (K,) int64
    count: np.ndarray  # (K,) int64
    center: np.ndarray  # (P, 3) in the frame of the owner's box (x forward, y left, z up, origin at its centre)
    half: np.ndarray  # (P, 3) half extents in the part's frame
    rot: np.ndarray  # (P, 3, 3) part -> box frame
    shape: np.ndarray  # (P,) int64 synth_raycast.SHAPE_*
    mat: np.ndarray  # (P,) int64 synth_materials.Mat
    albedo: np.ndarray  # (P, 3) float32
    refl: np.ndarray  # (P,) float64 LiDAR reflectance
    owner: np.ndarray  # (P,) int64 object index

    def expand(self, objects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For (Q,) object indices: (pair index, part index) of every (query, part) combination, query-major."""
        counts = self.count[objects]
        pair = np.repeat(np.arange(len(objects)), counts)
        offsets = np.cumsum(counts) - counts  # (Q,)
        part = self.start[objects][pair] + (np.arange(len(pair)) - offsets[pair])
        return pair, part


@dataclass(frozen=True, eq=False)
class Objects:
    """Every object of a scene as parallel arrays (K of them); poses are at scene time 0."""

    kind: np.ndarray  # (K,) int64 Kind
    size_wlh: np.ndarray  # (K, 3) float64 metres: the tight box around the parts
    center0: np.ndarray  # (K, 3) float64 world box centre at t = 0
    yaw: np.ndarray  # (K,) float64 heading about world z at t = 0
    velocity: np.ndarray  # (K, 2) float64 world m/s at t = 0 (along the heading for moving objects)
    yaw_rate: np.ndarray  # (K,) float64 rad/s (turning vehicles; 0 elsewhere)
    color: np.ndarray  # (K, 3) float32 main albedo 0..1 (paint, shirt)
    color2: np.ndarray  # (K, 3) float32 second albedo (trousers, cargo)
    flag: np.ndarray  # (K,) bool: cycle with rider / truck with box body / pedestrian in motion pose
    # (K,) bool: left where it stands (a car at the kerb, in a bay or a lot; a cycle in a rack or on the sidewalk),
    # as the layout placed it. A vehicle waiting in a lane (either street) or at a bus stop is not parked though it
    # stands as still: nuScenes calls that stopped, and the attribute rule (synth_tables.attribute_indices) reads
    # this flag, not where the object stands.
    parked: np.ndarray
    parts: Parts

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def annotated(self) -> np.ndarray:
        return self.kind < NUM_ANNOTATED_KINDS

    def poses_at(self, t_s, index: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (..., 3), yaws (...) and velocities (..., 2) of objects ``index`` at scene time(s) ``t_s``.

        ``t_s`` broadcasts against the selected objects (a scalar, or one time per selected object).
        """
        t = np.asarray(t_s, dtype=np.float64)
        c0, yaw0, v0, w = self.center0[index], self.yaw[index], self.velocity[index], self.yaw_rate[index]
        shape = np.broadcast_shapes(t.shape, yaw0.shape)
        t = np.broadcast_to(t, shape)
        centre = np.empty(shape + (3,))
        centre[..., 0] = c0[..., 0] + v0[..., 0] * t
        centre[..., 1] = c0[..., 1] + v0[..., 1] * t
        centre[..., 2] = c0[..., 2]
        vel = np.empty(shape + (2,))
        vel[...] = v0
        yaw = yaw0 + w * t  # (shape)
        turning = np.broadcast_to(np.abs(w) > 1e-9, shape)
        yaw = np.broadcast_to(yaw, shape)
        if np.any(turning):
            # Turning at speed s along the heading h: an arc of radius s / w.
            tw = t[turning]
            c0w, v0w = (np.broadcast_to(a, shape + a.shape[np.ndim(w):])[turning] for a in (c0, v0))
            ww = np.broadcast_to(w, shape)[turning]
            speed = np.hypot(v0w[:, 0], v0w[:, 1])
            h0 = np.arctan2(v0w[:, 1], v0w[:, 0])
            h_t = h0 + ww * tw
            centre[turning, 0] = c0w[:, 0] + speed / ww * (np.sin(h_t) - np.sin(h0))
            centre[turning, 1] = c0w[:, 1] + speed / ww * (np.cos(h0) - np.cos(h_t))
            vel[turning] = np.stack([speed * np.cos(h_t), speed * np.sin(h_t)], axis=1)
        return centre, yaw, vel

    def boxes_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """(K, 9) world boxes x, y, z, w, l, h, yaw, vx, vy at scene time t (or (T, K, 9) for (T,) times)."""
        t = np.asarray(t_s, dtype=np.float64)[..., None]  # (..., 1) against (K,)
        centre, yaw, vel = self.poses_at(t)
        k = centre.shape[:-1]
        return np.concatenate([centre, np.broadcast_to(self.size_wlh, k + (3,)), yaw[..., None], vel], axis=-1)


@dataclass(frozen=True)
class Road:
    """A straight road strip: its centre line through ``origin_xy`` along ``yaw``, ``half_width_m`` to each side."""

    origin_xy: tuple[float, float]
    yaw: float
    half_width_m: float


@dataclass(frozen=True, eq=False)
class Scene:
    """One synthetic scene: the streets, their objects, the ego's motion and the key-frame times."""

    name: str
    index: int
    seed: int
    config: WorldConfig
    objects: Objects
    road_origin_xy: np.ndarray  # (2,) world position of the main road's frame origin
    road_yaw: float  # direction u of the main road (rad)
    ego_speed_mps: float
    sun_dir_world: np.ndarray  # (3,) unit vector towards the sun
    cross_s_m: float | None = None  # where the cross street meets the main road (road coordinate s), None: none
    ground_phase: float = 0.0  # phase of the ground's undulation

    @property
    def road_u(self) -> np.ndarray:
        return np.array([math.cos(self.road_yaw), math.sin(self.road_yaw)])

    @property
    def road_n(self) -> np.ndarray:
        return np.array([-math.sin(self.road_yaw), math.cos(self.road_yaw)])

    @property
    def roads(self) -> tuple[Road, ...]:
        """The road strips of the scene (headings of vehicles are measured against these)."""
        main = Road((float(self.road_origin_xy[0]), float(self.road_origin_xy[1])), float(self.road_yaw), ROAD_HALF_WIDTH_M)
        if self.cross_s_m is None:
            return (main,)
        from streamdet.data.synth_road import CROSS_HALF_WIDTH_M

        o = self.road_origin_xy + self.cross_s_m * self.road_u
        return main, Road((float(o[0]), float(o[1])), float(self.road_yaw + math.pi / 2), CROSS_HALF_WIDTH_M)

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

    def to_road(self, xy_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates (s along the main road, d to its left) of world (..., 2) positions."""
        rel = np.asarray(xy_world) - self.road_origin_xy
        return rel @ self.road_u, rel @ self.road_n

    def ground_z(self, xy_world: np.ndarray) -> np.ndarray:
        """Height of the ground at world (..., 2) positions."""
        xy = np.asarray(xy_world, dtype=np.float64)
        return ground_height(xy[..., 0], xy[..., 1], self.ground_phase)


@functools.lru_cache(maxsize=128)
def make_scene(seed: int, index: int, config: WorldConfig = WorldConfig()) -> Scene:
    """The deterministic scene number ``index`` of a dataset generated with ``seed``.

    Cached: the writer, the world sidecar and the trajectories sidecar ask for the same scenes (treat the
    returned arrays as read-only).
    """
    from streamdet.data.synth_layout import layout_scene  # the layout builds on the types above

    return layout_scene(int(seed), int(index), config)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + math.pi, 2 * math.pi) - math.pi
