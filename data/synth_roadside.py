"""Road works (the annotated cones and barriers) and the permanent furniture that looks like them (not annotated).

nuScenes annotates only temporary traffic cones and barriers; real streets also hold many things of their size
and shape that are background: flexible delineator posts on lane edges and medians, bollards, hydrants and planter
pots by the kerb, guard rails, pedestrian railings, concrete dividers and long planters along the road. Without
them, "a small upright thing on the road is a cone" and "a low long thing by the kerb is a barrier" would be true
in this world and false in nuScenes. Works come in three kinds: a row of barriers along the parking strip with
cones between and ahead of it, a lane closed by a taper of cones, and works on the sidewalk fenced by barriers;
single cones stand beside parked cars and on sidewalks, often half hidden.

Everything here works in road coordinates of the main road (s along it, d to its left), through the placer of
``synth_layout`` (its ``_try_add`` tests bounding circles; ``add_fixed`` tests the boxes themselves).
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.data.synth_kinds import Kind
from streamdet.data.synth_road import CROSS_HALF_WIDTH_M, LANE_WIDTH_M, PARKING_OFFSET_M, ROAD_HALF_WIDTH_M

LANE_EDGE_M = 2 * LANE_WIDTH_M  # the line between the outer lane and the parking strip
KERB_LINE_M = ROAD_HALF_WIDTH_M + 0.3  # rails and railings stand just behind the kerb
DELINEATOR_COLORS = np.array([[0.95, 0.45, 0.08], [0.92, 0.92, 0.9], [0.95, 0.8, 0.1], [0.8, 0.1, 0.08], [0.15, 0.45, 0.2]], dtype=np.float32)
POT_COLORS = np.array([[0.6, 0.32, 0.2], [0.55, 0.55, 0.53], [0.2, 0.2, 0.22], [0.75, 0.72, 0.66]], dtype=np.float32)
RAILING_COLORS = np.array([[0.15, 0.35, 0.2], [0.55, 0.56, 0.58], [0.9, 0.9, 0.88], [0.12, 0.15, 0.3], [0.85, 0.7, 0.1]], dtype=np.float32)
STRIPE_COLORS = np.array([[0.85, 0.08, 0.08], [0.95, 0.8, 0.1], [0.1, 0.1, 0.1]], dtype=np.float32)
FOLIAGE = np.array([0.18, 0.42, 0.15], dtype=np.float32)


def _pick(rng: np.random.Generator, colors: np.ndarray, spread: tuple[float, float] = (0.85, 1.05)) -> np.ndarray:
    return np.clip(colors[rng.integers(len(colors))] * rng.uniform(*spread), 0, 1).astype(np.float32)


def _runs(rng: np.random.Generator, lo: float, hi: float, run_m: tuple[float, float], gap_m: tuple[float, float],
          cross_s: float | None, start_prob: float) -> list[tuple[float, float]]:
    """Stretches [a, b) of the road from ``lo`` to ``hi``, broken by gaps and kept out of the intersection."""
    runs = []
    s = lo + float(rng.uniform(0, gap_m[1]))
    while s < hi:
        length = float(rng.uniform(*run_m))
        a, b = s, min(s + length, hi)
        if cross_s is not None and a < cross_s + CROSS_HALF_WIDTH_M + 2 and b > cross_s - CROSS_HALF_WIDTH_M - 2:
            if cross_s - CROSS_HALF_WIDTH_M - 2 - a > 2.0 and rng.uniform() < start_prob:
                runs.append((a, cross_s - CROSS_HALF_WIDTH_M - 2))  # a median or rail often runs up to the crossing
            s = cross_s + CROSS_HALF_WIDTH_M + 2 + float(rng.uniform(0, gap_m[0]))
            continue
        if rng.uniform() < start_prob:
            runs.append((a, b))
        s = b + float(rng.uniform(*gap_m))
    return runs


# ---- look-alikes ----------------------------------------------------------------------------------------

def place_lookalikes(placer) -> None:
    """Median furniture, lane-edge posts, kerbside rails and planters, and posts at the intersection's corners.

    Placed after the road users: fixed furniture keeps clear of their boxes over the whole scene (a lane-changing
    car or a crossing pedestrian leaves a gap), so the traffic is the same as without it.
    """
    _median(placer)
    for side in (-1.0, 1.0):
        _lane_edge_posts(placer, side)
        _kerbside(placer, side)
    if placer.cross_s is not None:
        _corner_posts(placer)


def _median(placer) -> None:
    rng = placer.rng
    style = rng.uniform()
    lo, hi = placer.s_lo - 10.0, placer.s_hi + 10.0
    if style < 0.3:  # a painted median with flexible posts
        for a, b in _runs(rng, lo, hi, (15.0, 60.0), (5.0, 25.0), placer.cross_s, 0.8):
            color, gap = _pick(rng, DELINEATOR_COLORS), float(rng.uniform(1.8, 4.0))
            flag = bool(rng.uniform() < 0.5)
            for s in np.arange(a, b, gap):
                placer.add_fixed(Kind.DELINEATOR, float(s), float(rng.normal(0, 0.05)), 0.0, color=color, flag=flag, margin_m=0.1)
    elif style < 0.45:  # a cast concrete divider, in segments
        for a, b in _runs(rng, lo, hi, (20.0, 70.0), (8.0, 30.0), placer.cross_s, 0.85):
            h, w, stripes = float(rng.uniform(0.7, 0.95)), float(rng.uniform(0.5, 0.65)), bool(rng.uniform() < 0.3)
            color = _pick(rng, STRIPE_COLORS)
            s = a
            while s < b - 2.0:
                length = min(float(rng.uniform(4.0, 8.0)), b - s)
                placer.add_fixed(Kind.DIVIDER, s + length / 2, 0.0, 0.0, size=[w, length, h], color=color, flag=stripes, margin_m=0.1)
                s += length + 0.05
    elif style < 0.55:  # a raised median of long planters
        for a, b in _runs(rng, lo, hi, (15.0, 50.0), (6.0, 25.0), placer.cross_s, 0.85):
            s = a
            while s < b - 1.5:
                size = placer._size(Kind.PLANTER_BOX)
                placer.add_fixed(Kind.PLANTER_BOX, s + size[1] / 2, 0.0, 0.0, size=size, color=_pick(rng, POT_COLORS[1:]),
                                 flag=bool(rng.uniform() < 0.6), margin_m=0.1)
                s += size[1] + float(rng.uniform(0.5, 2.5))
    # else: a painted line only


def _lane_edge_posts(placer, side: float) -> None:
    """Posts separating a cycle lane or the parking strip from traffic; parked cars leave gaps."""
    rng = placer.rng
    if rng.uniform() < 0.6:
        return
    for a, b in _runs(rng, placer.s_lo - 10.0, placer.s_hi + 10.0, (10.0, 35.0), (10.0, 40.0), placer.cross_s, 0.8):
        color, gap, flag = _pick(rng, DELINEATOR_COLORS), float(rng.uniform(2.0, 5.0)), bool(rng.uniform() < 0.5)
        for s in np.arange(a, b, gap):
            placer.add_fixed(Kind.DELINEATOR, float(s), side * (LANE_EDGE_M + rng.normal(0, 0.08)), 0.0, color=color, flag=flag,
                             margin_m=0.1)


def _kerbside(placer, side: float) -> None:
    """Railings and guard rails just behind the kerb, in barrier-sized segments, and long planters on the sidewalk's
    edge."""
    rng = placer.rng
    for a, b in _runs(rng, placer.s_lo - 10.0, placer.s_hi + 10.0, (6.0, 30.0), (10.0, 40.0), placer.cross_s, 0.45):
        guard = rng.uniform() < 0.35
        kind = Kind.GUARD_RAIL if guard else Kind.RAILING
        h = float(rng.uniform(0.7, 0.85) if guard else rng.uniform(0.85, 1.15))
        w = float(rng.uniform(0.3, 0.4) if guard else rng.uniform(0.06, 0.1))
        color, flag = _pick(rng, RAILING_COLORS), bool(rng.uniform() < 0.5)
        yaw = 0.0 if side < 0 else math.pi
        s = a
        while s < b - 1.0:
            length = min(float(rng.uniform(2.5, 4.0)), b - s)
            placer.add_fixed(kind, s + length / 2, side * (KERB_LINE_M + w / 2), yaw, size=[w, length, h], color=color, flag=flag,
                             margin_m=0.15)
            s += length + (0.02 if rng.uniform() < 0.85 else float(rng.uniform(1.0, 3.0)))
    for a, b in _runs(rng, placer.s_lo - 10.0, placer.s_hi + 10.0, (4.0, 12.0), (10.0, 45.0), placer.cross_s, 0.5):
        color = _pick(rng, POT_COLORS[1:])
        s = a
        while s < b:
            size = placer._size(Kind.PLANTER_BOX)
            placer.add_fixed(Kind.PLANTER_BOX, s + size[1] / 2, side * (KERB_LINE_M + 0.3 + size[0] / 2), 0.0, size=size, color=color,
                             flag=bool(rng.uniform() < 0.6))
            s += size[1] + float(rng.uniform(0.8, 2.5))


def _corner_posts(placer) -> None:
    """Delineators and bollards guarding the intersection's corners and its pedestrian islands."""
    rng = placer.rng
    for ds in (-1.0, 1.0):
        for dd in (-1.0, 1.0):
            kind = Kind.DELINEATOR if rng.uniform() < 0.6 else Kind.BOLLARD
            color = _pick(rng, DELINEATOR_COLORS)
            for j in range(int(rng.integers(0, 5))):
                s = placer.cross_s + ds * (CROSS_HALF_WIDTH_M + 0.3 + 1.2 * j * rng.uniform(0.8, 1.2))
                placer.add_fixed(kind, s, dd * (ROAD_HALF_WIDTH_M + 0.2), 0.0, color=color, margin_m=0.1)


# ---- road works (annotated) -----------------------------------------------------------------------------

def place_work_zone(placer, barrier_colors: np.ndarray) -> None:
    """One road works: a row by the kerb (cones between and ahead), a closed lane, or works on the sidewalk."""
    rng = placer.rng
    side = placer._side()
    s0 = placer._s()
    color = barrier_colors[rng.integers(len(barrier_colors))] * rng.uniform(0.45, 0.85)  # weathered and dirty
    kind = rng.uniform()
    if kind < 0.45:
        _kerb_row(placer, side, s0, color)
    elif kind < 0.75:
        _lane_closure(placer, side, s0, color)
    else:
        _sidewalk_works(placer, side, s0, color)


def _kerb_row(placer, side: float, s0: float, color) -> None:
    """Barriers along the parking strip (long side along the road), a cone in some of the gaps on the traffic side,
    and a short taper of cones ahead."""
    rng = placer.rng
    angle = float(rng.uniform(-0.4, 0.4)) if rng.uniform() < 0.3 else 0.0
    for i in range(int(rng.integers(3, 8))):  # end to end, closer than bounding circles allow
        s = s0 + i * 3.1 * math.cos(angle)
        d = side * (PARKING_OFFSET_M + i * 3.1 * math.sin(angle) + rng.normal(0, 0.05))
        placer.add_fixed(Kind.BARRIER, s, d, math.pi / 2 + angle + rng.normal(0, 0.04), color=color, margin_m=0.05)
        if rng.uniform() < 0.35:  # in the gap to the next barrier, on the traffic side (closer than circles allow)
            placer.add_fixed(Kind.TRAFFIC_CONE, s + 1.55 * math.cos(angle), d - side * 0.6, float(rng.uniform(-math.pi, math.pi)),
                             margin_m=0.05)
    for i in range(int(rng.integers(2, 6))):
        placer._try_add(Kind.TRAFFIC_CONE, s0 - 3.0 - i * 2.5, side * (PARKING_OFFSET_M - 0.6 + rng.normal(0, 0.3)),
                        float(rng.uniform(-math.pi, math.pi)), 0.0)


def _lane_closure(placer, side: float, s0: float, color) -> None:
    """The outer lane closed: a taper of cones from the parking strip into the lane line, a row along it, and a
    few barriers in the closed lane. Placed before the traffic, which then keeps to the open lanes."""
    rng = placer.rng
    ahead = 1.0 if side < 0 else -1.0  # traffic on this side drives towards +s (right-hand traffic)
    taper = int(rng.integers(3, 5))
    spacing = float(rng.uniform(2.5, 4.0))
    for i in range(taper):
        d = PARKING_OFFSET_M - 0.4 - (PARKING_OFFSET_M - 0.4 - (LANE_WIDTH_M + 0.3)) * i / (taper - 1)
        placer._try_add(Kind.TRAFFIC_CONE, s0 + ahead * i * spacing, side * (d + rng.normal(0, 0.1)), float(rng.uniform(-math.pi, math.pi)), 0.0)
    row_start = s0 + ahead * (taper - 1) * spacing
    for i in range(1, int(rng.integers(3, 7))):
        placer._try_add(Kind.TRAFFIC_CONE, row_start + ahead * i * float(rng.uniform(4.0, 6.0)), side * (LANE_WIDTH_M + 0.3 + rng.normal(0, 0.1)),
                        float(rng.uniform(-math.pi, math.pi)), 0.0)
    for i in range(int(rng.integers(1, 4))):
        yaw = (math.pi / 2 if rng.uniform() < 0.6 else 0.0) + rng.normal(0, 0.1)
        placer._try_add(Kind.BARRIER, row_start + ahead * (2.0 + 3.0 * i), side * (1.5 * LANE_WIDTH_M + rng.normal(0, 0.3)), yaw, 0.0, color=color)


def _sidewalk_works(placer, side: float, s0: float, color) -> None:
    """Works on the sidewalk: barriers along its road side and across its ends, cones at the kerb and beside them."""
    rng = placer.rng
    count = int(rng.integers(3, 6))
    d_row = side * float(rng.uniform(9.0, 9.6))
    for i in range(count):
        placer.add_fixed(Kind.BARRIER, s0 + 2.8 * i, d_row, math.pi / 2 + rng.normal(0, 0.04), color=color, margin_m=0.05)
    for end in (s0 - 1.7, s0 + 2.8 * (count - 1) + 1.7):
        if rng.uniform() < 0.3:
            placer.add_fixed(Kind.BARRIER, end, d_row + side * 1.4, float(rng.normal(0, 0.05)), color=color, margin_m=0.05)
    for _ in range(int(rng.integers(2, 6))):
        d = side * (float(rng.uniform(7.6, 8.3)) if rng.uniform() < 0.5 else float(rng.uniform(10.8, 12.5)))
        placer._try_add(Kind.TRAFFIC_CONE, s0 + float(rng.uniform(-3.0, 2.7 * count + 1.0)), d, float(rng.uniform(-math.pi, math.pi)), 0.0)


def place_stray_cones(placer, count: int) -> None:
    """Single cones where people leave them: beside a parked car (often hidden by it), on the sidewalk, at a
    lot's entrance. Placed after the parked cars, tested against the boxes themselves."""
    rng = placer.rng
    parked = [i for i, r in enumerate(placer.rows) if r["kind"] == int(Kind.CAR) and not np.any(r["velocity_sd"])]
    for _ in range(count):
        for _ in range(placer.MAX_TRIES):
            if parked and rng.uniform() < 0.6:
                row = placer.rows[parked[int(rng.integers(len(parked)))]]
                s_car, d_car = (float(v) for v in row["center_sd"])
                if abs(d_car) < ROAD_HALF_WIDTH_M - 3.0:
                    continue
                reach = 0.5 * float(row["shape"].size_wlh[1]) + float(rng.uniform(0.4, 1.2))
                s = s_car + (reach if rng.uniform() < 0.5 else -reach) * abs(math.cos(row["yaw_road"]))
                d = d_car + float(rng.uniform(-0.8, 0.8))
            else:
                s, d = placer._s(), placer._side() * float(rng.uniform(9.0, 12.8))
            if placer.add_fixed(Kind.TRAFFIC_CONE, s, d, float(rng.uniform(-math.pi, math.pi)), margin_m=0.15):
                break
