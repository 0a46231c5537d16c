"""The shapes of the synthetic world's objects: each object is a set of parts (boxes, ellipsoids, cylinders).

A car has a lower body, a bonnet, a glass cabin under a rounded roof, bumpers, four wheels, mirrors, lamps and
plates; vans, trucks and buses differ in silhouette; a pedestrian has a torso, a head, legs and arms in one of
several poses; bicycles and motorcycles have wheels, a frame and usually a rider; cones are tapered; barriers come
as concrete, fence and water-filled kinds. Each builder works in the object frame (x forward, y left, z up from
the ground under the object) and returns parts; ``ObjectShape.tight`` then fits the annotated box: the tight
axis-aligned box of the parts in the object frame, as nuScenes annotators draw a box around what they see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from streamdet.data.synth_kinds import KIND_SPECS, Kind
from streamdet.data.synth_materials import Mat, draw_reflectance
from streamdet.data.synth_raycast import SHAPE_BOX, SHAPE_CYLINDER, SHAPE_ELLIPSOID

TYRE = (0.05, 0.05, 0.05)
GLASS = (0.06, 0.08, 0.11)
SKIN_TONES = ((0.86, 0.66, 0.52), (0.6, 0.42, 0.3), (0.35, 0.24, 0.17), (0.93, 0.78, 0.66))
HAIR = ((0.1, 0.07, 0.05), (0.3, 0.2, 0.1), (0.6, 0.5, 0.3), (0.15, 0.15, 0.15))
BIKE_TUBE_M = 0.016  # radius of the main tubes and the fork (about 32 mm across)
BIKE_STAY_M = 0.009  # radius of the seat and chain stays


def rotation(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """(3, 3) part -> object rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


WHEEL_ROT = rotation(roll=math.pi / 2)  # a cylinder's axis (z) along the object's y
WHEEL_ROT_X = WHEEL_ROT  # (for barriers: the long axis y; the cross-section's half extents are (x, z) = (a, b))


@dataclass(frozen=True, eq=False)
class ObjectShape:
    """One object's parts in the frame of its annotated box (centre at the box centre)."""

    center: np.ndarray  # (P, 3)
    half: np.ndarray  # (P, 3) half extents in the part frame
    rot: np.ndarray  # (P, 3, 3) part -> object
    shape: np.ndarray  # (P,) int64 SHAPE_*
    mat: np.ndarray  # (P,) int64 Mat
    albedo: np.ndarray  # (P, 3) float32
    refl: np.ndarray  # (P,) float64 LiDAR reflectance
    size_wlh: np.ndarray  # (3,) the tight box: w (along y), l (along x), h


class _Builder:
    """Collects parts in the object frame (z from the ground); reflectance drawn once per material and colour."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.rows: list[tuple] = []
        self._refl: dict[tuple, float] = {}

    def add(self, center, half, mat: Mat, albedo, shape: int = SHAPE_BOX, rot: np.ndarray | None = None) -> None:
        albedo = tuple(float(a) for a in albedo)
        key = (int(mat), albedo)
        if key not in self._refl:
            self._refl[key] = draw_reflectance(mat, np.asarray(albedo), self.rng)
        self.rows.append((np.asarray(center, float), np.abs(np.asarray(half, float)), np.eye(3) if rot is None else rot,
                          int(shape), int(mat), albedo, self._refl[key]))

    def limb(self, top, length: float, radius: float, pitch: float, mat: Mat, albedo, roll: float = 0.0) -> None:
        """A cylinder hanging from ``top`` (its upper end), swung by ``pitch`` about y (forward positive)."""
        rot = rotation(pitch=pitch, roll=roll)
        centre = np.asarray(top, float) - rot @ np.array([0.0, 0.0, length / 2])
        self.add(centre, (radius, radius, length / 2), mat, albedo, SHAPE_CYLINDER, rot)

    def tight(self, slack_m: np.ndarray | None = None) -> ObjectShape:
        """The parts in the frame of their tight box, widened by ``slack_m`` (5,): -x, +x, -y, +y, +z (metres)."""
        center = np.stack([r[0] for r in self.rows])
        half = np.stack([r[1] for r in self.rows])
        rot = np.stack([r[2] for r in self.rows])
        shape = np.array([r[3] for r in self.rows], dtype=np.int64)
        ext = part_extents(half, rot, shape)  # (P, 3) half extents along the object axes
        lo = (center - ext).min(axis=0)
        hi = (center + ext).max(axis=0)
        if slack_m is not None:
            lo = lo - np.array([slack_m[0], slack_m[2], 0.0])
            hi = hi + np.array([slack_m[1], slack_m[3], slack_m[4]])
        mid = (lo + hi) / 2
        size = hi - lo
        return ObjectShape(
            center=center - mid,
            half=half,
            rot=rot,
            shape=shape,
            mat=np.array([r[4] for r in self.rows], dtype=np.int64),
            albedo=np.array([r[5] for r in self.rows], dtype=np.float32),
            refl=np.array([r[6] for r in self.rows], dtype=np.float64),
            size_wlh=np.array([size[1], size[0], size[2]]),
        )


def part_extents(half: np.ndarray, rot: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(P, 3) exact half extents along the object axes of rotated boxes, ellipsoids and cylinders."""
    scaled = rot * half[:, None, :]  # (P, 3 object axes, 3 part axes)
    box = np.abs(scaled).sum(axis=2)
    ell = np.sqrt((scaled**2).sum(axis=2))
    cyl = np.abs(scaled[:, :, 2]) + np.sqrt((scaled[:, :, :2] ** 2).sum(axis=2))
    return np.where((shape == SHAPE_BOX)[:, None], box, np.where((shape == SHAPE_ELLIPSOID)[:, None], ell, cyl))


# ---- vehicles -----------------------------------------------------------------------------------------

def _wheels(b: _Builder, xs, half_track: float, radius: float, half_width: float) -> None:
    for x in xs:
        for side in (-1, 1):
            b.add((x, side * half_track, radius), (radius, radius, half_width), Mat.TYRE, TYRE, SHAPE_CYLINDER, WHEEL_ROT)


def _lamps_and_plates(b: _Builder, x_front: float, x_back: float, half_w: float, z: float) -> None:
    for side in (-1, 1):
        b.add((x_front - 0.03, side * (half_w - 0.18), z + 0.15), (0.04, 0.14, 0.06), Mat.LAMP, (1.0, 0.95, 0.8))
        b.add((x_back + 0.03, side * (half_w - 0.16), z + 0.2), (0.04, 0.12, 0.07), Mat.LAMP, (0.8, 0.05, 0.05))
    b.add((x_front - 0.01, 0.0, z), (0.015, 0.24, 0.06), Mat.RETRO, (0.95, 0.95, 0.95))
    b.add((x_back + 0.01, 0.0, z + 0.05), (0.015, 0.24, 0.06), Mat.RETRO, (0.95, 0.95, 0.95))


def car(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    rng = b.rng
    style = int(rng.integers(4))  # 0 sedan, 1 hatchback, 2 SUV, 3 van
    mirror = float(rng.uniform(0.08, 0.14))
    hw = w / 2 - mirror  # the body's half width (mirrors stick out to the box)
    r = float(np.clip(0.3 + 0.08 * (h - 1.5), 0.28, 0.42))
    belt = h * (0.55 if style < 2 else 0.58)
    front, back = l / 2, -l / 2
    _wheels(b, (front - 0.85 - 0.05 * l / 4.6, back + 0.95), hw - 0.14, r, 0.1)
    # Lower body between the bumpers, a bonnet that slopes down to the front, bumpers with rounded ends.
    b.add((0.0, 0.0, (0.3 + belt) / 2), (l / 2 - 0.22, hw, (belt - 0.3) / 2), Mat.PAINT, color)
    b.add((front - 0.2, 0.0, 0.45), (0.2, hw - 0.04, 0.17), Mat.PLASTIC, color, SHAPE_CYLINDER)
    b.add((back + 0.2, 0.0, 0.47), (0.2, hw - 0.04, 0.18), Mat.PLASTIC, color, SHAPE_CYLINDER)
    cab_back = {0: -0.3, 1: -0.44, 2: -0.44, 3: -0.47}[style] * l
    cab_front = {0: 0.12, 1: 0.1, 2: 0.16, 3: 0.3}[style] * l
    bonnet_len = front - 0.2 - cab_front
    if bonnet_len > 0.2:
        b.add((cab_front + bonnet_len / 2, 0.0, belt - 0.02), (bonnet_len / 2, hw - 0.03, 0.06), Mat.PAINT, color,
              rot=rotation(pitch=0.08))
    # The glass cabin (most beams pass through) under a rounded painted roof; pillars of paint at the corners.
    roof_h = 0.1
    cab_h = h - belt - roof_h
    cx, cl = (cab_front + cab_back) / 2, (cab_front - cab_back) / 2
    b.add((cx, 0.0, belt + cab_h / 2), (cl, hw - 0.1, cab_h / 2), Mat.GLASS, GLASS)
    for x in (cab_front - 0.05, cab_back + 0.05):
        for side in (-1, 1):
            b.add((x, side * (hw - 0.13), belt + cab_h / 2), (0.05, 0.04, cab_h / 2), Mat.PAINT, color)
    b.add((cx - 0.05 * cl, 0.0, h - roof_h), (cl * 0.95, hw - 0.12, roof_h), Mat.PAINT, color, SHAPE_ELLIPSOID)
    for side in (-1, 1):  # mirrors: the widest points
        b.add((cab_front - 0.05, side * (w / 2 - mirror / 2), belt + 0.12), (0.06, mirror / 2, 0.07), Mat.PAINT, color)
    _lamps_and_plates(b, front, back, hw, 0.45)


def truck(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    rng = b.rng
    mirror = float(rng.uniform(0.12, 0.2))
    hw = w / 2 - mirror
    r = float(rng.uniform(0.42, 0.52))
    cab_len = float(rng.uniform(1.8, 2.4))
    cab_h = min(h, float(rng.uniform(2.3, 3.0)))
    front, back = l / 2, -l / 2
    # Cab: body, windscreen, roof; the cargo behind is a box body (flag) or a low open bed with sides.
    b.add((front - 0.1 - cab_len / 2, 0.0, (0.6 + cab_h * 0.6) / 2), (cab_len / 2 - 0.1, hw, (cab_h * 0.6 - 0.6) / 2), Mat.PAINT, color)
    b.add((front - 0.2, 0.0, 0.65), (0.2, hw - 0.05, 0.2), Mat.PLASTIC, (0.2, 0.2, 0.22), SHAPE_CYLINDER)  # front bumper
    b.add((front - cab_len / 2 - 0.05, 0.0, cab_h * 0.8), (cab_len / 2 - 0.05, hw - 0.05, cab_h * 0.2), Mat.GLASS, GLASS)
    b.add((front - cab_len / 2 - 0.1, 0.0, cab_h - 0.04), (cab_len / 2 - 0.1, hw - 0.06, 0.04), Mat.PAINT, color)
    for side in (-1, 1):
        b.add((front - 0.3, side * (w / 2 - mirror / 2), cab_h * 0.7), (0.05, mirror / 2, 0.2), Mat.METAL, (0.2, 0.2, 0.2))
    cargo_len = l - cab_len - 0.3
    cargo_x = back + cargo_len / 2
    if flag:
        body = (0.88, 0.88, 0.85) if rng.uniform() < 0.6 else color2
        b.add((cargo_x, 0.0, (0.9 + h) / 2), (cargo_len / 2, hw + 0.02, (h - 0.9) / 2), Mat.PAINT, body)
    else:
        b.add((cargo_x, 0.0, 0.95), (cargo_len / 2, hw, 0.12), Mat.METAL, (0.3, 0.3, 0.32))
        for side in (-1, 1):
            b.add((cargo_x, side * (hw - 0.04), 1.35), (cargo_len / 2, 0.04, 0.3), Mat.PAINT, color2)
        b.add((back + 0.04, 0.0, 1.35), (0.04, hw, 0.3), Mat.PAINT, color2)
    b.add((0.0, 0.0, 0.7), (l / 2 - 0.3, hw * 0.5, 0.12), Mat.METAL, (0.15, 0.15, 0.15))  # chassis
    b.add((back - 0.12, 0.0, 0.5), (0.05, hw - 0.1, 0.06), Mat.METAL, (0.3, 0.3, 0.3))  # rear underride bar
    _wheels(b, (front - 1.2, back + 1.3, back + 2.5), hw - 0.25, r, 0.15)
    _lamps_and_plates(b, front, back, hw, 0.6)


def bus(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    rng = b.rng
    mirror = float(rng.uniform(0.15, 0.25))
    hw = w / 2 - mirror
    front, back = l / 2 - 0.25, -l / 2
    b.add(((front + back) / 2, 0.0, 0.35 + 0.38 * (h - 0.35) / 2), ((front - back) / 2, hw, 0.38 * (h - 0.35) / 2), Mat.PAINT, color)
    win_lo, win_hi = 0.35 + 0.38 * (h - 0.35), h - 0.35
    b.add(((front + back) / 2, 0.0, (win_lo + win_hi) / 2), ((front - back) / 2 - 0.05, hw - 0.02, (win_hi - win_lo) / 2), Mat.GLASS, GLASS)
    for x in np.arange(back + 0.8, front - 0.5, float(rng.uniform(1.3, 1.8))):  # window posts
        for side in (-1, 1):
            b.add((x, side * (hw - 0.03), (win_lo + win_hi) / 2), (0.06, 0.03, (win_hi - win_lo) / 2), Mat.PAINT, color)
    b.add(((front + back) / 2, 0.0, h - 0.2), ((front - back) / 2, hw, 0.15), Mat.PAINT, color2 if flag else color)
    b.add(((front + back) / 2, 0.0, h - 0.05), ((front - back) / 2 - 0.4, hw - 0.15, 0.05), Mat.METAL, (0.5, 0.5, 0.5))
    for side in (-1, 1):  # mirrors on arms, ahead of the front
        b.add((front + 0.15, side * (w / 2 - mirror / 2 - 0.02), h * 0.6), (0.1, mirror / 2, 0.25), Mat.METAL, (0.15, 0.15, 0.15))
    _wheels(b, (front - 2.3, back + 3.0), hw - 0.3, 0.5, 0.17)
    b.add((back - 0.1, 0.0, 0.45), (0.1, hw - 0.05, 0.12), Mat.PLASTIC, (0.1, 0.1, 0.1), SHAPE_CYLINDER)  # rear bumper
    _lamps_and_plates(b, front, back, hw, 0.5)


# ---- people and cycles --------------------------------------------------------------------------------

def _person(b: _Builder, x0: float, h: float, shirt, trousers, pose: str, seat_z: float | None = None) -> None:
    """A person standing at x0 (or seated at height seat_z, leaning forward), facing +x."""
    rng = b.rng
    skin = SKIN_TONES[int(rng.integers(len(SKIN_TONES)))]
    hair = HAIR[int(rng.integers(len(HAIR)))] if rng.uniform() < 0.8 else skin
    head_r = 0.11 * h / 1.75
    if seat_z is None:
        hip = 0.5 * h
        stride = {"walk": float(rng.uniform(0.25, 0.45)), "stand": float(rng.uniform(0.0, 0.08)), "phone": 0.05, "bag": 0.15}[pose]
        for side, swing in ((1, stride), (-1, -stride)):
            b.limb((x0, side * 0.09, hip), hip, 0.065, swing, Mat.CLOTH, trousers)
            foot_x = x0 - hip * math.sin(swing) + 0.07
            b.add((foot_x, side * 0.1, 0.045), (0.13, 0.05, 0.045), Mat.PLASTIC, (0.1, 0.08, 0.07))  # shoes
        lean = 0.05 if pose == "walk" else 0.0
        torso_x = x0
    else:
        hip = seat_z
        for side in (-1, 1):  # thighs forward, shins down
            b.limb((x0, side * 0.12, hip), 0.42, 0.075, 1.35, Mat.CLOTH, trousers)
            b.limb((x0 + 0.4, side * 0.14, hip - 0.05), hip - 0.15, 0.065, -0.2, Mat.CLOTH, trousers)
        lean = 0.45
        torso_x = x0 + 0.1
        stride = 0.0
    torso_h = 0.3 * h
    rot = rotation(pitch=lean)
    torso_c = np.array([torso_x, 0.0, hip]) + rot @ np.array([0.0, 0.0, torso_h / 2 + 0.02])
    b.add(torso_c, (0.11, 0.17, torso_h / 2 + 0.04), Mat.CLOTH, shirt, SHAPE_ELLIPSOID, rot)
    neck = np.array([torso_x, 0.0, hip]) + rot @ np.array([0.0, 0.0, torso_h + 0.04])
    b.add(neck + [0.0, 0.0, head_r * 0.9], (head_r * 0.9, head_r * 0.8, head_r), Mat.SKIN, skin, SHAPE_ELLIPSOID)
    b.add(neck + [-0.02, 0.0, head_r * 1.3], (head_r * 0.85, head_r * 0.8, head_r * 0.6), Mat.CLOTH, hair, SHAPE_ELLIPSOID)
    shoulder = neck - rot @ np.array([0.0, 0.0, 0.05])
    for side in (-1, 1):
        if seat_z is not None:
            b.limb(shoulder + [0, side * 0.22, 0], 0.55, 0.045, 1.0, Mat.CLOTH, shirt)
        elif pose == "phone" and side > 0:
            b.limb(shoulder + [0, side * 0.22, 0], 0.3, 0.045, 0.3, Mat.CLOTH, shirt)
            b.limb(shoulder + [0.1, side * 0.2, -0.28], 0.28, 0.04, 2.2, Mat.SKIN, skin)
        else:
            swing = -side * stride * 0.8 if pose == "walk" else float(rng.uniform(-0.3, 0.3))
            b.limb(shoulder + [0, side * 0.22, 0], 0.36 * h, 0.045, swing, Mat.CLOTH, shirt, roll=-side * 0.08)
    if pose == "bag":
        b.add((x0, -0.33, 0.3 * h), (0.15, 0.06, 0.15), Mat.PLASTIC, (0.3, 0.2, 0.1) if rng.uniform() < 0.5 else (0.1, 0.1, 0.1))
    if rng.uniform() < 0.25:  # backpack
        b.add(np.array([torso_x, 0.0, hip]) + rot @ np.array([-0.17, 0.0, torso_h * 0.6]), (0.08, 0.15, 0.2), Mat.CLOTH,
              tuple(np.asarray(trousers) * 0.8), rot=rot)


def pedestrian(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    pose = ("walk", "stand", "phone", "bag")[int(b.rng.choice(4, p=(0.45, 0.3, 0.1, 0.15)))] if flag else "stand"
    _person(b, 0.0, h, color, color2, pose)


def _cycle(b: _Builder, w: float, l: float, h: float, color, color2, rider: bool, motor: bool) -> None:
    rng = b.rng
    radius = 0.34 if not motor else float(rng.uniform(0.28, 0.33))
    wheel_x = l / 2 - radius
    tyre_w = 0.025 if not motor else 0.065
    for x in (wheel_x, -wheel_x):
        b.add((x, 0.0, radius), (radius, radius, tyre_w), Mat.TYRE if motor else Mat.SPOKED, TYRE, SHAPE_CYLINDER, WHEEL_ROT)
    frame_col = color2 if motor else color
    saddle_z = 0.85 if not motor else 0.8
    if motor:
        b.add((0.0, 0.0, 0.55), (wheel_x * 0.7, 0.2, 0.22), Mat.PAINT, frame_col, SHAPE_ELLIPSOID)  # tank and engine
        b.add((-0.25, 0.0, saddle_z - 0.05), (0.35, 0.15, 0.06), Mat.PLASTIC, (0.08, 0.08, 0.08))
        b.add((wheel_x - 0.15, 0.0, 0.95), (0.04, w / 2 - 0.02, 0.03), Mat.METAL, (0.2, 0.2, 0.2))
        b.add((wheel_x - 0.05, 0.0, 0.85), (0.06, 0.1, 0.08), Mat.LAMP, (1.0, 0.95, 0.8))
        b.add((-wheel_x - 0.1, 0.0, 0.6), (0.02, 0.1, 0.05), Mat.RETRO, (0.95, 0.95, 0.95))
    else:
        hub = radius
        # Round tubes (seat stays and chain stays thinner than the main triangle): a beam meets a tube's crest
        # head-on but its flanks at a grazing angle, and a tube fills only part of the beam's footprint.
        for (x1, z1), (x2, z2), r in [((-wheel_x, hub), (-0.15, saddle_z), BIKE_STAY_M), ((-0.15, saddle_z), (wheel_x - 0.15, saddle_z), BIKE_TUBE_M),
                                      ((-0.15, hub + 0.05), (wheel_x - 0.15, saddle_z), BIKE_TUBE_M),
                                      ((wheel_x - 0.15, saddle_z + 0.1), (wheel_x, hub), BIKE_TUBE_M),
                                      ((-wheel_x, hub), (-0.15, hub + 0.05), BIKE_STAY_M)]:
            length = math.hypot(x2 - x1, z2 - z1)
            pitch = math.atan2(x2 - x1, z2 - z1)
            b.add(((x1 + x2) / 2, 0.0, (z1 + z2) / 2), (r, r, length / 2), Mat.PAINT, frame_col, SHAPE_CYLINDER, rotation(pitch=pitch))
        b.add((-0.15, 0.0, saddle_z + 0.03), (0.12, 0.07, 0.03), Mat.PLASTIC, (0.08, 0.08, 0.08))
        b.add((wheel_x - 0.12, 0.0, saddle_z + 0.15), (0.012, 0.012, w / 2 - 0.02), Mat.METAL, (0.3, 0.3, 0.3), SHAPE_CYLINDER, WHEEL_ROT)
        b.add((-wheel_x - 0.02, 0.0, radius + 0.25), (0.01, 0.04, 0.03), Mat.RETRO, (0.9, 0.1, 0.1))
    if rider:
        h_rider = float(rng.uniform(1.6, 1.9))
        _person(b, -0.2 if not motor else -0.3, h_rider, color if not motor else color2, color2 if not motor else TYRE,
                "stand", seat_z=saddle_z + 0.05)


def bicycle(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    _cycle(b, w, l, h, color, color2, flag, motor=False)


def motorcycle(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    _cycle(b, w, l, h, color, color2, flag, motor=True)


def scooter(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A parked moped: small wheels, a body and a steering column, nobody on it (unannotated)."""
    for x in (l / 2 - 0.25, -l / 2 + 0.25):
        b.add((x, 0.0, 0.24), (0.24, 0.24, 0.05), Mat.TYRE, TYRE, SHAPE_CYLINDER, WHEEL_ROT)
    b.add((-0.15, 0.0, 0.55), (l / 2 - 0.35, 0.2, 0.2), Mat.PAINT, color, SHAPE_ELLIPSOID)
    b.add((l / 2 - 0.35, 0.0, 0.75), (0.06, 0.12, 0.35), Mat.PAINT, color, rot=rotation(pitch=-0.25))
    b.add((l / 2 - 0.45, 0.0, h - 0.05), (0.04, w / 2, 0.03), Mat.METAL, (0.2, 0.2, 0.2))


# ---- road furniture -----------------------------------------------------------------------------------

def traffic_cone(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    base = min(w, l) / 2
    b.add((0.0, 0.0, 0.02), (base, base, 0.02), Mat.PLASTIC, (0.08, 0.08, 0.08))
    steps = 6
    body_h = h - 0.04
    for i in range(steps):
        r0 = base * 0.72 * (1 - 0.75 * (i + 0.5) / steps)
        band = i == (3 if flag else 4)  # one retroreflective collar
        b.add((0.0, 0.0, 0.04 + body_h * (i + 0.5) / steps), (r0, r0, body_h / steps / 2), Mat.RETRO if band else Mat.PLASTIC,
              (0.95, 0.95, 0.93) if band else (1.0, 0.42, 0.05), SHAPE_CYLINDER)


def barrier(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A barrier across y (its long side ``w``): concrete jersey, a striped fence on feet, or a water-filled block."""
    style = int(b.rng.integers(3))
    if style == 0:  # concrete: a low foot under a body that narrows upwards (a horizontal half-ellipse)
        b.add((0.0, 0.0, 0.06 * h), (l / 2 * 0.9, w / 2, 0.06 * h), Mat.CONCRETE, (0.58, 0.57, 0.53))
        b.add((0.0, 0.0, 0.3 * h), (l / 2, 0.3 * h, w / 2), Mat.CONCRETE, (0.58, 0.57, 0.53), SHAPE_CYLINDER, WHEEL_ROT_X)
        b.add((0.0, 0.0, 0.5 * h), (l / 2 * 0.55, 0.5 * h, w / 2 - 0.01), Mat.CONCRETE, (0.58, 0.57, 0.53), SHAPE_CYLINDER, WHEEL_ROT_X)
    elif style == 1:  # a striped fence on feet
        for side in (-1, 1):
            b.add((0.0, side * (w / 2 - 0.15), 0.04), (l / 2, 0.15, 0.04), Mat.WEATHERED, (0.15, 0.15, 0.15))
            b.add((0.0, side * (w / 2 - 0.15), h / 2), (0.03, 0.03, h / 2), Mat.METAL, (0.6, 0.6, 0.6))
        for z in (0.45, 0.8):
            b.add((0.0, 0.0, h * z), (0.02, w / 2 - 0.1, h * 0.1), Mat.STRIPES, color)
    else:  # a water-filled plastic block: rounded all round
        b.add((0.0, 0.0, h * 0.45), (l / 2, h * 0.45, w / 2), Mat.WEATHERED, color, SHAPE_CYLINDER, WHEEL_ROT_X)
        b.add((0.0, 0.0, h * 0.55), (l / 2 * 0.7, h * 0.45, w / 2 - 0.02), Mat.WEATHERED, color, SHAPE_CYLINDER, WHEEL_ROT_X)
        b.add((l / 2 * 0.75, 0.0, h * 0.55), (0.01, w / 4, 0.05), Mat.RETRO, (0.95, 0.95, 0.9))


def pole(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (w / 2 * 0.6, w / 2 * 0.6, h / 2), Mat.METAL, (0.52, 0.53, 0.55), SHAPE_CYLINDER)
    b.add((0.0, 0.0, h - 0.1), (w / 2, w / 2, 0.1), Mat.LAMP, (0.95, 0.95, 0.85))


def tree_trunk(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (w / 2, l / 2, h / 2), Mat.BARK, (0.36, 0.25, 0.15), SHAPE_CYLINDER)


def tree_crown(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (w / 2, l / 2, h / 2), Mat.FOLIAGE, color, SHAPE_ELLIPSOID)


def building(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (l / 2, w / 2, h / 2), Mat.FACADE, color)


def wall(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (l / 2, w / 2, h / 2), Mat.CONCRETE, (0.66, 0.63, 0.58))


def curb(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (l / 2, w / 2, h / 2), Mat.CONCRETE, (0.62, 0.62, 0.6))


def bollard(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (w / 2, w / 2, h / 2), Mat.METAL if flag else Mat.PLASTIC, color, SHAPE_CYLINDER)
    b.add((0.0, 0.0, h * 0.8), (w / 2 + 0.005, w / 2 + 0.005, 0.04), Mat.RETRO, (0.95, 0.95, 0.9), SHAPE_CYLINDER)


def sign(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h / 2), (0.035, 0.035, h / 2), Mat.METAL, (0.55, 0.55, 0.57), SHAPE_CYLINDER)
    plate = min(w, 0.9) / 2
    shape = SHAPE_CYLINDER if flag else SHAPE_BOX
    b.add((0.05, 0.0, h - plate), (plate, plate, 0.01), Mat.RETRO, color, shape, rotation(pitch=math.pi / 2))


def bin_(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    shape = SHAPE_CYLINDER if flag else SHAPE_BOX
    b.add((0.0, 0.0, h / 2 - 0.03), (l / 2 * 0.92, w / 2 * 0.92, h / 2 - 0.03), Mat.WEATHERED, color, shape)
    b.add((0.0, 0.0, h - 0.03), (l / 2, w / 2, 0.03), Mat.PLASTIC, color2, shape)


def hydrant(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, h * 0.4), (0.12, 0.12, h * 0.4), Mat.PAINT, color, SHAPE_CYLINDER)
    b.add((0.0, 0.0, h * 0.85), (0.13, 0.13, h * 0.15), Mat.PAINT, color, SHAPE_ELLIPSOID)
    b.add((0.0, 0.0, h * 0.55), (0.05, w / 2, 0.05), Mat.PAINT, color, SHAPE_CYLINDER, WHEEL_ROT)


def bench(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    b.add((0.0, 0.0, 0.45), (w / 2, l / 2, 0.03), Mat.WOOD, (0.45, 0.3, 0.18))
    b.add((-w / 2 + 0.04, 0.0, 0.65), (0.03, l / 2, 0.15), Mat.WOOD, (0.45, 0.3, 0.18), rot=rotation(pitch=-0.2))
    for y in (-l / 2 + 0.1, l / 2 - 0.1):
        b.add((0.0, y, 0.22), (w / 2 - 0.05, 0.03, 0.22), Mat.METAL, (0.2, 0.2, 0.2))


def bush(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    rng = b.rng
    for _ in range(int(rng.integers(1, 4))):
        c = (rng.uniform(-0.25, 0.25) * l, rng.uniform(-0.25, 0.25) * w, h * rng.uniform(0.4, 0.55))
        b.add(c, (l / 2 * rng.uniform(0.5, 0.8), w / 2 * rng.uniform(0.5, 0.8), h * rng.uniform(0.35, 0.45)), Mat.FOLIAGE,
              color, SHAPE_ELLIPSOID)



# ---- permanent road furniture that looks like cones and barriers (unannotated) ---------------------------

ALONG_X = rotation(pitch=math.pi / 2)  # a cylinder's axis (z) along the object's x; its half extents (x, y) become (z, y)


def delineator(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A flexible post on a lane edge or a median: a round plastic tube with two retroreflective bands, on a
    low dark base (``flag``: a bare tube set in the road)."""
    r = min(w, l) / 2
    z0 = 0.0
    if not flag:
        b.add((0.0, 0.0, 0.025), (r, r, 0.025), Mat.PLASTIC, (0.08, 0.08, 0.08), SHAPE_CYLINDER)
        z0 = 0.05
    post_r = r * (0.55 if not flag else 1.0)
    b.add((0.0, 0.0, (z0 + h) / 2), (post_r, post_r, (h - z0) / 2), Mat.PLASTIC, color, SHAPE_CYLINDER)
    for z in (h - 0.1, h - 0.25):
        b.add((0.0, 0.0, z), (post_r + 0.004, post_r + 0.004, 0.04), Mat.RETRO, (0.95, 0.95, 0.93), SHAPE_CYLINDER)


def planter(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A round pot of concrete or plastic, tapering down, with a shrub on top (``flag``) or bare soil."""
    r = min(w, l) / 2
    pot_h = h * (0.6 if flag else 1.0)
    b.add((0.0, 0.0, pot_h * 0.3), (r * 0.8, r * 0.8, pot_h * 0.3), Mat.CONCRETE, color, SHAPE_CYLINDER)
    b.add((0.0, 0.0, pot_h * 0.8), (r, r, pot_h * 0.2), Mat.CONCRETE, color, SHAPE_CYLINDER)
    if flag:
        b.add((0.0, 0.0, pot_h + (h - pot_h) / 2), (r * 0.9, r * 0.9, (h - pot_h) / 2), Mat.FOLIAGE, color2, SHAPE_ELLIPSOID)


def guard_rail(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A galvanised W-beam on posts about 2 m apart (``flag``: a second beam lower down)."""
    n = max(2, int(round(l / 2.0)) + 1)
    for x in np.linspace(-l / 2 + 0.05, l / 2 - 0.05, n):
        b.add((x, -w / 2 + 0.05, (h - 0.05) / 2), (0.05, 0.05, (h - 0.05) / 2), Mat.METAL, (0.5, 0.5, 0.52))
    b.add((0.0, w / 2 - 0.05, h - 0.2), (l / 2, 0.05, 0.17), Mat.METAL, (0.62, 0.63, 0.65))
    if flag:
        b.add((0.0, w / 2 - 0.05, h - 0.55), (l / 2, 0.04, 0.08), Mat.METAL, (0.62, 0.63, 0.65))


def divider(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A permanent concrete divider of Jersey profile, as a temporary concrete barrier but long and cast in place."""
    grey = (0.6, 0.59, 0.55)
    b.add((0.0, 0.0, 0.06 * h), (l / 2, w / 2, 0.06 * h), Mat.CONCRETE, grey)
    b.add((0.0, 0.0, 0.3 * h), (0.3 * h, w / 2, l / 2), Mat.CONCRETE, grey, SHAPE_CYLINDER, ALONG_X)
    b.add((0.0, 0.0, 0.5 * h), (0.5 * h, w / 2 * 0.55, l / 2), Mat.CONCRETE, grey, SHAPE_CYLINDER, ALONG_X)
    if flag:  # painted hazard stripes along the top, the kind temporary barriers carry
        b.add((0.0, 0.0, 0.85 * h), (l / 2, w / 2 * 0.3, 0.1 * h), Mat.STRIPES, color)


def planter_box(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A long concrete trough with a hedge (``flag``) or low flowers in it."""
    body_h = h * (0.7 if flag else 0.9)
    b.add((0.0, 0.0, body_h / 2), (l / 2, w / 2, body_h / 2), Mat.CONCRETE, color)
    top = h - body_h
    b.add((0.0, 0.0, body_h + top / 2 - 0.03), (l / 2 * 0.95, w / 2 * 0.85, top / 2 + 0.03), Mat.FOLIAGE, color2, SHAPE_ELLIPSOID)


def railing(b: _Builder, w: float, l: float, h: float, color, color2, flag: bool) -> None:
    """A pedestrian railing along the kerb: posts, a top and a lower rail, painted (``flag``: a middle rail too)."""
    n = max(2, int(round(l / 1.8)) + 1)
    r = w / 2 * 0.6
    for x in np.linspace(-l / 2 + r, l / 2 - r, n):
        b.add((x, 0.0, h / 2), (r, r, h / 2), Mat.PAINT, color, SHAPE_CYLINDER)
    for z in (h - r, 0.25 * h) + ((0.6 * h,) if flag else ()):
        b.add((0.0, 0.0, z), (r, r, l / 2), Mat.PAINT, color, SHAPE_CYLINDER, ALONG_X)

# Builders take (w, l, h): l along the object's x (its heading), w along y.
BUILDERS: dict[Kind, Callable] = {
    Kind.CAR: car,
    Kind.TRUCK: truck,
    Kind.BUS: bus,
    Kind.BICYCLE: bicycle,
    Kind.MOTORCYCLE: motorcycle,
    Kind.PEDESTRIAN: pedestrian,
    Kind.BARRIER: barrier,
    Kind.TRAFFIC_CONE: traffic_cone,
    Kind.POLE: pole,
    Kind.TREE_TRUNK: tree_trunk,
    Kind.TREE_CROWN: tree_crown,
    Kind.BUILDING: building,
    Kind.WALL: wall,
    Kind.BOLLARD: bollard,
    Kind.SIGN: sign,
    Kind.BIN: bin_,
    Kind.HYDRANT: hydrant,
    Kind.BENCH: bench,
    Kind.BUSH: bush,
    Kind.SCOOTER: scooter,
    Kind.CURB: curb,
    Kind.DELINEATOR: delineator,
    Kind.PLANTER: planter,
    Kind.GUARD_RAIL: guard_rail,
    Kind.DIVIDER: divider,
    Kind.PLANTER_BOX: planter_box,
    Kind.RAILING: railing,
}
assert len(BUILDERS) == len(KIND_SPECS)


ANNOTATOR_SLACK_M = (0.0, 0.08)  # uniform range of the margin an annotator leaves on each side (not below)


def build_shape(kind: Kind, size_wlh, rng: np.random.Generator, color, color2, flag: bool) -> ObjectShape:
    """The parts of one object of ``kind`` drawn around the nominal size (w, l, h).

    Its box is their tight box; for annotated kinds widened by an annotator's margin on each side but the bottom
    (real annotations are not tight to the centimetre: the points of the bundled nuScenes sample lie a median
    10-30 cm inside their boxes' faces).
    """
    w, l, h = (float(v) for v in size_wlh)
    b = _Builder(rng)
    BUILDERS[Kind(kind)](b, w, l, h, tuple(float(c) for c in color), tuple(float(c) for c in color2), bool(flag))
    annotated = KIND_SPECS[Kind(kind)].detection_class is not None
    return b.tight(rng.uniform(*ANNOTATOR_SLACK_M, size=5) if annotated else None)
