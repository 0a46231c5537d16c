"""What the objects of the synthetic world are: annotated road users, unannotated clutter and look-alikes."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class Kind(IntEnum):
    """What an object is; the first eight are annotated (nuScenes detection classes), the rest is not."""

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
    BOLLARD = 13
    SIGN = 14
    BIN = 15
    HYDRANT = 16
    BENCH = 17
    BUSH = 18
    SCOOTER = 19  # parked scooter / moped, unannotated
    CURB = 20
    DELINEATOR = 21  # flexible post on lane edges and medians, with retroreflective bands
    PLANTER = 22  # round planter pot by the kerb
    GUARD_RAIL = 23  # a metal rail on posts, one segment
    DIVIDER = 24  # a permanent concrete median divider (Jersey profile), one segment
    PLANTER_BOX = 25  # a long concrete planter on a median or the sidewalk edge
    RAILING = 26  # a pedestrian railing along the kerb, one segment


@dataclass(frozen=True)
class KindSpec:
    detection_class: str | None  # one of CLASS_NAMES, None for unannotated objects
    category: str | None  # nuScenes category name written to the category table
    size_wlh_m: tuple[float, float, float]  # mean size (nuScenes v1.0-trainval class means for road users)
    size_jitter: float  # relative standard deviation of each size component (nuScenes-like spread)


KIND_SPECS: tuple[KindSpec, ...] = (
    KindSpec("car", "vehicle.car", (1.95, 4.62, 1.73), 0.09),
    KindSpec("truck", "vehicle.truck", (2.52, 6.94, 2.84), 0.18),
    KindSpec("bus", "vehicle.bus.rigid", (2.94, 11.19, 3.47), 0.10),
    KindSpec("bicycle", "vehicle.bicycle", (0.60, 1.70, 1.28), 0.08),
    KindSpec("motorcycle", "vehicle.motorcycle", (0.77, 2.11, 1.47), 0.10),
    KindSpec("pedestrian", "human.pedestrian.adult", (0.67, 0.73, 1.77), 0.09),
    KindSpec("barrier", "movable_object.barrier", (2.53, 0.50, 0.98), 0.12),
    KindSpec("traffic_cone", "movable_object.trafficcone", (0.41, 0.41, 1.07), 0.12),
    KindSpec(None, None, (0.25, 0.25, 6.5), 0.15),  # pole (street light)
    KindSpec(None, None, (0.45, 0.45, 2.6), 0.10),  # tree trunk
    KindSpec(None, None, (3.2, 3.2, 3.0), 0.15),  # tree crown, sits on its trunk
    KindSpec(None, None, (10.0, 25.0, 12.0), 0.0),  # building, sized per instance
    KindSpec(None, None, (0.3, 12.0, 1.4), 0.0),  # low wall / fence, sized per instance
    KindSpec(None, None, (0.2, 0.2, 0.9), 0.12),  # bollard
    KindSpec(None, None, (0.6, 0.1, 2.5), 0.12),  # sign on a post (w: the plate's width)
    KindSpec(None, None, (0.6, 0.6, 1.1), 0.12),  # bin
    KindSpec(None, None, (0.4, 0.4, 0.8), 0.10),  # hydrant
    KindSpec(None, None, (0.6, 1.8, 0.85), 0.10),  # bench
    KindSpec(None, None, (1.2, 1.6, 1.1), 0.25),  # bush
    KindSpec(None, None, (0.65, 1.75, 1.15), 0.08),  # parked scooter
    KindSpec(None, None, (0.2, 12.0, 0.14), 0.0),  # curb segment, sized per instance
    KindSpec(None, None, (0.16, 0.16, 0.92), 0.14),  # delineator post (0.08-0.25 m wide, 0.75-1.1 m tall)
    KindSpec(None, None, (0.6, 0.6, 0.75), 0.18),  # round planter pot, with or without a shrub
    KindSpec(None, None, (0.35, 4.0, 0.75), 0.0),  # guard rail segment, sized per instance (l along the road)
    KindSpec(None, None, (0.6, 6.0, 0.82), 0.0),  # median divider segment, sized per instance
    KindSpec(None, None, (0.7, 2.4, 0.75), 0.15),  # long planter
    KindSpec(None, None, (0.08, 3.0, 1.0), 0.0),  # pedestrian railing segment, sized per instance
)
NUM_ANNOTATED_KINDS = 8
# Unannotated look-alikes of the small road users (what `streamdet-synth stats` counts as distractors).
DISTRACTOR_KINDS: tuple[Kind, ...] = (Kind.BOLLARD, Kind.SIGN, Kind.BIN, Kind.HYDRANT, Kind.BENCH, Kind.BUSH, Kind.SCOOTER,
                                     Kind.DELINEATOR, Kind.PLANTER)
# Unannotated look-alikes of cones (small upright things by and on the road) and of barriers (low structures of a
# barrier's size along the road): nuScenes annotates only temporary cones and barriers, so these are background.
CONE_LOOKALIKE_KINDS: tuple[Kind, ...] = (Kind.BOLLARD, Kind.HYDRANT, Kind.DELINEATOR, Kind.PLANTER)
BARRIER_LOOKALIKE_KINDS: tuple[Kind, ...] = (Kind.GUARD_RAIL, Kind.DIVIDER, Kind.PLANTER_BOX, Kind.RAILING)
