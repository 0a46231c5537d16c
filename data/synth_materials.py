"""Surface appearance of the synthetic world: albedo (camera), coverage (alpha) and reflectance (LiDAR).

Each object is a box; its class shows in the pattern painted on the faces, computed from the hit point in the
box frame (x along the heading, y to its left, z up, origin at the centre). ``alpha`` False cuts a pixel / ray
out of the box (a bicycle's spokes, a pedestrian's outline, a cone's taper): both sensors then look past it, so
the camera and the LiDAR agree on what is solid. Patterns are deterministic functions of position, so a
surface looks the same from every camera and at every time.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from streamdet.data.synth_world import LANE_WIDTH_M, ROAD_HALF_WIDTH_M, SIDEWALK_OUTER_M, Kind

GLASS = np.array([0.06, 0.08, 0.11], dtype=np.float32)
TYRE = np.array([0.05, 0.05, 0.05], dtype=np.float32)
SKIN = np.array([0.86, 0.66, 0.52], dtype=np.float32)
ASPHALT = np.array([0.30, 0.30, 0.31], dtype=np.float32)
GROUND_PERIOD_M = 36.0  # the ground pattern repeats along the road (a multiple of 0.3, 1.5, 4 and 9 m)


def hash_noise(ix: np.ndarray, iy: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic per-lattice-cell value in [0, 1) (an integer hash, vectorised)."""
    h = (np.asarray(ix, dtype=np.int64) * 73856093) ^ (np.asarray(iy, dtype=np.int64) * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def surface(
    kind: int,
    axis: np.ndarray,
    sign: np.ndarray,
    p: np.ndarray,
    half: np.ndarray,
    color: np.ndarray,
    color2: np.ndarray,
    flag: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (P, 3) float32 in 0..1, alpha (P,) bool and reflectance (P,) float32 of hits on one kind of box.

    axis, sign: the entered face (``ray_box_entry``); p: (P, 3) hit points in the box frame; half: (P, 3) or (3,)
    half extents along x, y, z; color, color2: (P, 3) or (3,) instance albedos; flag: (P,) or () instance flag.
    """
    p = np.asarray(p)
    p = p if p.dtype in (np.float32, np.float64) else p.astype(np.float64)
    n = len(p)
    half = np.broadcast_to(np.asarray(half, dtype=p.dtype), (n, 3))
    color = np.broadcast_to(np.asarray(color, dtype=np.float32), (n, 3))
    color2 = np.broadcast_to(np.asarray(color2, dtype=np.float32), (n, 3))
    flag = np.broadcast_to(np.asarray(flag, dtype=bool), (n,))
    f = _Face(axis, sign, p, half)
    paint = _PAINTERS[int(kind)]
    albedo, alpha, refl = paint(f, color, color2, flag)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32), alpha, refl.astype(np.float32)


class _Face:
    """Per-hit face coordinates shared by the painters, each computed on first use."""

    def __init__(self, axis: np.ndarray, sign: np.ndarray, p: np.ndarray, half: np.ndarray) -> None:
        self.axis, self.sign, self.p, self.half = axis, sign, p, half
        self.x, self.y, self.z = p[:, 0], p[:, 1], p[:, 2]
        self.hx, self.hy, self.hz = half[:, 0], half[:, 1], half[:, 2]

    @cached_property
    def zb(self) -> np.ndarray:
        return self.z + self.hz  # metres above the box bottom

    @cached_property
    def zr(self) -> np.ndarray:
        return self.zb / (2 * self.hz)  # 0 at the bottom, 1 at the top

    @cached_property
    def side(self) -> np.ndarray:
        return self.axis == 1  # the long faces (left / right of the heading)

    @cached_property
    def end(self) -> np.ndarray:
        return self.axis == 0  # front (sign +1) and back (sign -1)

    @cached_property
    def top(self) -> np.ndarray:
        return (self.axis == 2) & (self.sign > 0)

    @cached_property
    def bottom(self) -> np.ndarray:
        return (self.axis == 2) & (self.sign < 0)

    @cached_property
    def lat(self) -> np.ndarray:
        """Horizontal coordinate along a vertical face."""
        return np.where(self.side, self.x, self.y)

    @cached_property
    def half_lat(self) -> np.ndarray:
        return np.where(self.side, self.hx, self.hy)

    @cached_property
    def latr(self) -> np.ndarray:
        return np.abs(self.lat) / self.half_lat  # 0 at the face centre line, 1 at its edges


def _fill(n: int, rgb) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, dtype=np.float32), (n, 3)).copy()


def _put(albedo: np.ndarray, refl: np.ndarray, mask: np.ndarray, rgb, r: float) -> None:
    albedo[mask] = rgb if np.ndim(rgb) == 1 else rgb[mask]
    refl[mask] = r


def _wheels(f: _Face, centres_x: list[np.ndarray], radius: float) -> np.ndarray:
    """Mask of the wheel discs on the side faces (wheel centres at x, one radius above the bottom)."""
    m = np.zeros(len(f.x), dtype=bool)
    for cx in centres_x:
        m |= (f.x - cx) ** 2 + (f.zb - radius) ** 2 < radius**2
    return m & f.side


def _car(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo, refl = color.copy(), np.full(n, 0.25)
    _put(albedo, refl, f.top, color * 0.85, 0.25)
    window = (f.zr > 0.6) & (f.zr < 0.9) & ((f.side & (f.x > -0.62 * f.hx) & (f.x < 0.38 * f.hx)) | (f.end & (f.latr < 0.85)))
    _put(albedo, refl, window, GLASS, 0.05)
    _put(albedo, refl, f.zr < 0.12, TYRE * 2, 0.1)
    front, back = f.end & (f.sign > 0), f.end & (f.sign < 0)
    _put(albedo, refl, front & (f.zr > 0.42) & (f.zr < 0.55) & (f.latr > 0.55) & (f.latr < 0.92), [1.0, 0.95, 0.8], 0.9)
    _put(albedo, refl, front & (f.zr > 0.22) & (f.zr < 0.4) & (f.latr < 0.45), [0.12, 0.12, 0.13], 0.2)
    _put(albedo, refl, back & (f.zr > 0.48) & (f.zr < 0.6) & (f.latr > 0.6) & (f.latr < 0.94), [0.8, 0.05, 0.05], 0.8)
    _put(albedo, refl, f.end & (f.zr > 0.25) & (f.zr < 0.36) & (f.latr < 0.22), [0.95, 0.95, 0.95], 0.9)  # plate
    _put(albedo, refl, _wheels(f, [0.62 * f.hx, -0.62 * f.hx], 0.33), TYRE, 0.05)
    return albedo, np.ones(n, dtype=bool), refl


def _truck(f: _Face, color, color2, flag):
    n = len(f.x)
    cab = f.x > f.hx - 2.2
    cargo = np.where(flag[:, None], np.float32([0.88, 0.88, 0.85]), color2)
    albedo = np.where(cab[:, None], color, cargo).astype(np.float32)
    refl = np.where(cab, 0.3, 0.45)
    window = (f.zr > 0.58) & (f.zr < 0.82) & (
        (f.end & (f.sign > 0) & (f.latr < 0.88)) | (f.side & (f.x > f.hx - 1.6) & (f.x < f.hx - 0.3))
    )
    _put(albedo, refl, window, GLASS, 0.05)
    _put(albedo, refl, f.end & (f.sign > 0) & (f.zr > 0.2) & (f.zr < 0.3) & (f.latr > 0.6), [1.0, 0.95, 0.8], 0.9)
    _put(albedo, refl, f.end & (f.sign < 0) & (np.abs(f.lat) < 0.04), [0.15, 0.15, 0.15], 0.2)  # rear doors
    _put(albedo, refl, f.zr < 0.1, TYRE * 2, 0.1)
    _put(albedo, refl, _wheels(f, [f.hx - 1.2, -f.hx + 1.3, -f.hx + 2.5], 0.45), TYRE, 0.05)
    return albedo, np.ones(n, dtype=bool), refl


def _bus(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo, refl = color.copy(), np.full(n, 0.35)
    window = (f.side & (f.zr > 0.42) & (f.zr < 0.82) & (np.abs(f.x) < f.hx - 0.6) & (np.mod(f.x, 1.6) > 0.12)) | (
        f.end & (f.zr > 0.38) & (f.zr < 0.88) & (f.latr < 0.9)
    )
    _put(albedo, refl, window, GLASS, 0.05)
    _put(albedo, refl, f.end & (f.sign > 0) & (f.zr > 0.9) & (f.zr < 0.97) & (f.latr < 0.7), [1.0, 0.6, 0.1], 0.6)
    _put(albedo, refl, f.zr < 0.08, TYRE * 2, 0.1)
    _put(albedo, refl, _wheels(f, [f.hx - 2.5, -f.hx + 3.0], 0.5), TYRE, 0.05)
    return albedo, np.ones(n, dtype=bool), refl


def _rider(f: _Face, shirt, trousers, x_lo, x_hi, seat_zr):
    """Mask and albedo of a seated rider's silhouette on any face (torso, legs, helmet/head)."""
    on_vertical = ~(f.top | f.bottom)
    span = np.where(f.side, (f.x > x_lo) & (f.x < x_hi), f.latr < 0.55)
    body = on_vertical & span & (f.zr > seat_zr - 0.25)
    head = f.zr > 0.86
    head_span = np.where(f.side, np.abs(f.x - 0.5 * (x_lo + x_hi)) < 0.14, f.latr < 0.3)
    mask = body & (~head | head_span)
    rgb = np.where((f.zr < seat_zr)[:, None], trousers, shirt)
    rgb = np.where(head[:, None], SKIN * 0.6, rgb)  # helmet / hair
    top = f.top & (np.abs(f.x - 0.5 * (x_lo + x_hi)) < 0.2) & (f.latr < 0.5)
    return mask | top, rgb


def _cycle(f: _Face, color, color2, flag, motor: bool):
    n = len(f.x)
    albedo, refl = _fill(n, [0.08, 0.08, 0.09]), np.full(n, 0.3)
    radius = 0.34 if not motor else 0.32
    wheel_x = 0.62 * f.hx
    dist = np.minimum(np.hypot(f.x - wheel_x, f.zb - radius), np.hypot(f.x + wheel_x, f.zb - radius))
    if motor:
        wheel = dist < radius
        frame = (f.x > -0.5 * f.hx) & (f.x < 0.55 * f.hx) & (f.zr > 0.25) & (f.zr < 0.6)
    else:
        wheel = np.abs(dist - radius) < 0.045
        # Frame tubes: the top tube, the down tube and the seat stay as thick lines between wheel hub height and the saddle.
        hub, saddle = radius, 0.62 * 2 * f.hz
        frame = (np.abs(f.zb - saddle) < 0.04) & (np.abs(f.x) < 0.45 * f.hx)
        frame |= np.abs((f.zb - hub) - (saddle - hub) * (wheel_x - f.x) / (wheel_x + 1e-6)) < 0.05
        frame &= (f.zb > hub - 0.05) & (f.zb < saddle + 0.05) & (f.x > -wheel_x) & (f.x < wheel_x)
    side_mask = f.side & (wheel | frame)
    end_mask = f.end & ((f.latr < 0.12) & (f.zr < 0.8) | ((np.abs(f.zr - 0.78) < 0.04) & (f.latr < 0.85)))
    mask = side_mask | end_mask
    if motor:
        _put(albedo, refl, side_mask & frame & ~wheel, color, 0.35)
    rider, rider_rgb = _rider(f, color if not motor else color2, color2 if not motor else TYRE * 3, -0.45 * f.hx, 0.1 * f.hx, 0.55)
    rider &= flag
    _put(albedo, refl, rider, rider_rgb, 0.2)
    _put(albedo, refl, f.end & (f.zr > 0.5) & (f.zr < 0.6) & (f.latr < 0.1), [0.9, 0.9, 0.7], 0.9)  # reflector
    return albedo, mask | rider, refl


def _bicycle(f, color, color2, flag):
    return _cycle(f, color, color2, flag, motor=False)


def _motorcycle(f, color, color2, flag):
    return _cycle(f, color, color2, flag, motor=True)


def _pedestrian(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo, refl = color.copy(), np.full(n, 0.2)
    legs = f.zr < 0.48
    head = f.zr > 0.86
    vertical = ~(f.top | f.bottom)
    # Outline: a narrow head, shoulders-wide torso with arms, two legs seen from the front, one from the side.
    outline = np.where(head, f.latr < 0.32, np.where(legs, np.where(f.side, f.latr < 0.45, (f.latr > 0.1) & (f.latr < 0.55)), f.latr < 0.92))
    mask = vertical & outline
    rr = np.hypot(f.x / f.hx, f.y / f.hy)
    mask |= f.top & (rr < 0.75)
    _put(albedo, refl, legs, color2, 0.15)
    _put(albedo, refl, head | (f.top & (rr < 0.35)), SKIN * np.where(flag, 1.0, 0.55)[:, None], 0.25)
    _put(albedo, refl, legs & (f.zr < 0.06), [0.1, 0.08, 0.07], 0.1)  # shoes
    return albedo, mask, refl


def _barrier(f: _Face, color, color2, flag):
    n = len(f.x)
    stripe = np.mod(np.floor((f.lat + f.zb) / 0.4), 2) == 0
    albedo = np.where(stripe[:, None], np.float32([0.85, 0.08, 0.08]), np.float32([0.95, 0.95, 0.93])).astype(np.float32)
    refl = np.where(stripe, 0.55, 0.85)
    _put(albedo, refl, f.top | (f.side & ~f.end), [0.9, 0.9, 0.88], 0.6)
    _put(albedo, refl, f.zr < 0.15, [0.25, 0.25, 0.25], 0.2)
    return albedo, np.ones(n, dtype=bool), refl


def _cone(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo, refl = _fill(n, [1.0, 0.42, 0.05]), np.full(n, 0.5)
    band = (f.zr > 0.45) & (f.zr < 0.62)
    _put(albedo, refl, band, [0.97, 0.97, 0.95], 0.95)
    base = f.zr < 0.06
    _put(albedo, refl, base, [0.08, 0.08, 0.08], 0.1)
    vertical = ~(f.top | f.bottom)
    mask = vertical & ((f.latr < 1.0 - 0.82 * f.zr) | base)
    mask |= f.top & (np.maximum(np.abs(f.x / f.hx), np.abs(f.y / f.hy)) < 0.2)
    return albedo, mask, refl


def _pole(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo = _fill(n, [0.52, 0.53, 0.55])
    refl = np.full(n, 0.35)
    _put(albedo, refl, f.zr > 0.97, [0.95, 0.95, 0.85], 0.7)  # lamp
    return albedo, np.ones(n, dtype=bool), refl


def _trunk(f: _Face, color, color2, flag):
    n = len(f.x)
    streak = hash_noise(np.floor(f.lat / 0.06), np.floor(f.zb / 0.5), 7)
    albedo = (np.float32([0.36, 0.25, 0.15]) * (0.75 + 0.4 * streak)[:, None]).astype(np.float32)
    return albedo, np.ones(n, dtype=bool), np.full(n, 0.3)


def _crown(f: _Face, color, color2, flag):
    n = len(f.x)
    u = np.where(f.top | f.bottom, f.x, f.lat)
    v = np.where(f.top | f.bottom, f.y, f.zb)
    leaf = hash_noise(np.floor(u / 0.25), np.floor(v / 0.25), 11)
    albedo = (color * (0.6 + 0.7 * leaf)[:, None]).astype(np.float32)
    mask = hash_noise(np.floor(u / 0.5), np.floor(v / 0.5), 13) > 0.18  # gaps between the leaves
    return albedo, mask, np.full(n, 0.22)


def _building(f: _Face, color, color2, flag):
    n = len(f.x)
    albedo, refl = color.copy(), np.full(n, 0.35, dtype=np.float32)
    vertical = ~(f.top | f.bottom)
    col = np.mod(f.lat, 3.0)
    floor = np.mod(f.zb, 3.2)
    window = vertical & (col > 0.7) & (col < 2.3) & (floor > 1.0) & (floor < 2.4) & (f.zb > 3.2) & (f.zb < 2 * f.hz - 0.8)
    _put(albedo, refl, window, color2, 0.08)
    shop = vertical & (f.zb < 3.0) & (f.zb > 0.3) & (np.mod(f.lat, 6.0) > 0.8)
    _put(albedo, refl, shop, color2 * 1.3, 0.1)
    _put(albedo, refl, f.top, [0.4, 0.4, 0.42], 0.3)
    return albedo, np.ones(n, dtype=bool), refl


def _wall(f: _Face, color, color2, flag):
    n = len(f.x)
    joint = np.mod(f.zb, 0.35) < 0.03
    albedo = np.where(joint[:, None], np.float32([0.45, 0.44, 0.42]), np.float32([0.66, 0.63, 0.58])).astype(np.float32)
    return albedo, np.ones(n, dtype=bool), np.full(n, 0.4)


_PAINTERS = {
    Kind.CAR: _car,
    Kind.TRUCK: _truck,
    Kind.BUS: _bus,
    Kind.BICYCLE: _bicycle,
    Kind.MOTORCYCLE: _motorcycle,
    Kind.PEDESTRIAN: _pedestrian,
    Kind.BARRIER: _barrier,
    Kind.TRAFFIC_CONE: _cone,
    Kind.POLE: _pole,
    Kind.TREE_TRUNK: _trunk,
    Kind.TREE_CROWN: _crown,
    Kind.BUILDING: _building,
    Kind.WALL: _wall,
}


def ground(s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo (P, 3) float32 and reflectance (P,) float32 of the ground at road coordinates (s along, d left).

    Asphalt with lane markings (the centre line, dashed lines between the two lanes of each direction, edge
    lines between the lanes and the parking strips), tiled sidewalks and grass beyond: the layout of
    ``synth_world``.
    """
    s = np.asarray(s, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    ad = np.abs(d)
    # The noise repeats every GROUND_PERIOD_M along the road so the renderer can pre-sample one period.
    grain = hash_noise(np.mod(np.floor(s / 0.3), GROUND_PERIOD_M / 0.3), np.floor(d / 0.3), 1)
    patch = hash_noise(np.mod(np.floor(s / 4.0), GROUND_PERIOD_M / 4.0), np.floor(d / 4.0), 2)
    road = ad < ROAD_HALF_WIDTH_M
    sidewalk = (ad >= ROAD_HALF_WIDTH_M) & (ad < SIDEWALK_OUTER_M)
    shade = (0.85 + 0.2 * grain + 0.1 * patch)[..., None]
    albedo = np.where(road[..., None], ASPHALT * shade, np.float32([0.33, 0.45, 0.22]) * (0.7 + 0.5 * grain)[..., None])
    tile = (np.mod(s, 1.5) < 0.05) | (np.mod(ad - ROAD_HALF_WIDTH_M, 1.5) < 0.05)
    side_rgb = np.where(tile[..., None], np.float32([0.45, 0.45, 0.44]), np.float32([0.66, 0.65, 0.62]) * (0.92 + 0.12 * grain)[..., None])
    albedo = np.where(sidewalk[..., None], side_rgb, albedo)
    refl = np.where(road, 0.08 + 0.03 * grain, np.where(sidewalk, 0.2, 0.15))
    marking = (np.abs(ad - LANE_WIDTH_M) < 0.07) & (np.mod(s, 9.0) < 3.0)  # 3 m dashes every 9 m
    marking |= np.abs(ad - 2 * LANE_WIDTH_M) < 0.09
    centre = ad < 0.1
    albedo = np.where(marking[..., None], np.float32([0.92, 0.92, 0.9]), albedo)
    albedo = np.where(centre[..., None], np.float32([0.9, 0.75, 0.2]), albedo)
    refl = np.where(marking | centre, 0.6, refl)
    return albedo.astype(np.float32), refl.astype(np.float32)
