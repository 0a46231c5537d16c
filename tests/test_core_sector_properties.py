"""Property tests of the azimuth conventions (core/sectors.py, core/slicing.py) and of the sector restriction of
post-processing (runtime_ort/postprocess.py), each against a naive reference written from the documented rule in
exact rationals: which slice a point or a box centre is in, the slice-index feature, angle_diff_deg's range, and
paired_bev_iou on degenerate boxes. The @example cases are the reproducers of a property-based review (review40):
a point on the start axis in the quadrant before it, a float32 point on a sector bound, start_deg = -360, box
centres on a shared sector bound, and a difference of angles whose mod rounds to 360."""

from __future__ import annotations

import math
import warnings
from fractions import Fraction

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")  # the dev extra

from hypothesis import assume, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from streamdet.calibration.grid import GridSpec  # noqa: E402
from streamdet.core.boxes import paired_bev_iou  # noqa: E402
from streamdet.core.points import SLICE_INDEX, SLICE_TIME, SWEEP_DURATION_S  # noqa: E402
from streamdet.core.sectors import angle_diff_deg, azimuth_deg, quadrants_of_sector, sector_bounds_deg, slice_index_of  # noqa: E402
from streamdet.core.slicing import feature_index, relative_time_s, split_sweep  # noqa: E402
from streamdet.runtime_ort.coalesce import split_by_slice  # noqa: E402
from streamdet.runtime_ort.postprocess import Detections, PostprocessConfig, SliceRun, in_slices, postprocess_slice  # noqa: E402

NS = st.sampled_from([1, 2, 4, 8, 12, 16, 28, 36, 156, 360, 4096])
STARTS = st.sampled_from([0.0, 90.0, 180.0, 270.0, -90.0, -180.0, -270.0, -360.0, -0.0, 360.0, 720.0])
DTYPES = st.sampled_from([np.float32, np.float64])
SPECIAL = [0.0, -0.0, 1e-300, -1e-300, 5e-324, -5e-324, 1e-15, -1e-15, 1.0, -1.0, 3.0, -3.0, 1e30, -1e30, 5e-6, -5e-6]
COORD = st.one_of(
    st.sampled_from(SPECIAL),
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False),
    st.floats(allow_nan=False, allow_infinity=True, width=32),
)
EPS_DEG = Fraction(1, 10**9)  # rounding slack of the reference's azimuth (math.atan2) against numpy's near a bound
FAST = settings(max_examples=150, deadline=None)


def naive_quadrant(x: float, y: float) -> int:
    """The grid's quadrant of (x, y), written out: an axis point goes to the non-negative side (GridSpec's cells)."""
    if y >= 0:
        return 0 if x >= 0 else 1
    return 2 if x < 0 else 3


def naive_slice(x: float, y: float, n: int, start: float, cw: bool, az: Fraction | None = None) -> int:
    """The slice of (x, y) from the module docstring, in exact rationals: ccw sector j is [start + 360 j / n,
    start + 360 (j + 1) / n); a clockwise scan numbers it n - 1 - j. A point whose grid quadrant that sector does not
    read (a point on an axis) goes to the slice reading its quadrant that is nearest its azimuth round the circle."""
    x, y = float(x), float(y)
    if math.isnan(x) or math.isnan(y):
        return -1
    az = (Fraction(math.degrees(math.atan2(y, x))) if az is None else az) % 360
    q = naive_quadrant(x, y)
    width = Fraction(360, n)

    def lo_of(j: int) -> Fraction:
        return (Fraction(start) + j * width) % 360

    def reads(j: int) -> bool:  # the sector overlaps quadrant q by a positive length (round the circle)
        lo = lo_of(j)
        return any(max(lo, 90 * q + 360 * w) < min(lo + width, 90 * q + 90 + 360 * w) for w in (-1, 0, 1))

    def distance(j: int) -> Fraction:  # round the circle from az to the sector's closure
        lo = lo_of(j)
        return min((lo - az) % 360, (az - lo - width) % 360)

    j = math.floor((az - Fraction(start)) % 360 / width)
    if not reads(j):
        j = min((i for i in range(n) if reads(i)), key=distance)
    return n - 1 - j if cw else j


def naive_slices_near(x: float, y: float, n: int, start: float, cw: bool) -> set[int]:
    """naive_slice at the azimuth and EPS_DEG to either side of it: both slices of a bound the point is that close to."""
    if math.isnan(float(x)) or math.isnan(float(y)):
        return {-1}
    az = Fraction(math.degrees(math.atan2(float(y), float(x))))
    return {naive_slice(x, y, n, start, cw, az + d) for d in (-EPS_DEG, 0, EPS_DEG)}


def one_slice(x, y, n, start, cw, dtype) -> int:
    return int(slice_index_of(np.array([x], dtype), np.array([y], dtype), n, start, cw)[0])


def cast(v: float, dtype) -> float:
    with np.errstate(over="ignore"):  # a float64 beyond float32's range casts to inf, as a sweep reader's would
        return float(np.array([v]).astype(dtype)[0])


# The review's cases, (x, y, n, start, clockwise, dtype, expected slice): on the start axis in the quadrant before it
# (the clamp took the far end of the quadrant, up to 90 deg away), rounded onto the 0 / 360 wrap, on a bound in
# float32 (rounded into the sector ending there), and start -360 (rounded as 0 did not).
REVIEW_CASES = [
    (-5.0, 0.0, 8, 180.0, True, np.float64, 0),  # nuScenes LIDAR_TOP layout: (135, 180), not (90, 135)
    (-5.0, 0.0, 8, 180.0, True, np.float32, 0),
    (-5.0, 0.0, 8, 180.0, False, np.float64, 7),
    (0.0, 5.0, 8, 90.0, False, np.float64, 7),  # (45, 90), not (0, 45)
    (10.0, -1e-15, 8, 0.0, False, np.float64, 7),  # azimuth rounds to 0, quadrant 3: (315, 360), not (270, 315)
    (10.0, -1e-15, 32, 0.0, False, np.float64, 31),
    (-50.0, 5e-6, 8, 180.0, True, np.float32, 0),  # 5 um off the -x axis
    (1.0, 1.0, 8, 0.0, False, np.float32, 1),  # on the 45 deg bound: the sector it starts
    (1.0, 1.0, 8, 90.0, False, np.float32, 7),
    (1.0, 1.0, 8, 180.0, True, np.float32, 2),
    (1.0, 1.0, 8, -360.0, False, np.float32, 1),
    (1.0, 1.0, 8, -360.0, False, np.float64, 1),
]


@pytest.mark.parametrize("x, y, n, start, cw, dtype, expected", REVIEW_CASES)
def test_review_cases_go_to_the_slice_next_to_them(x, y, n, start, cw, dtype, expected):
    assert one_slice(x, y, n, start, cw, dtype) == expected
    assert naive_slice(cast(x, dtype), cast(y, dtype), n, start, cw) == expected
    lo, hi = sector_bounds_deg(expected, n, start, cw)
    az = float(azimuth_deg(np.array([x], dtype), np.array([y], dtype))[0])
    assert lo - 1e-3 <= az <= hi + 1e-3 or lo - 1e-3 <= az + 360.0 <= hi + 1e-3  # next to it, not a quarter turn away
    sweep = np.array([[x, y, 0.0, 0.0, 0.0]], dtype)  # split_sweep agrees (its default-layout path at start -360 too)
    assert [k for k, s in enumerate(split_sweep(sweep, n, start, clockwise=cw)) if len(s)] == [expected]


@settings(max_examples=600, deadline=None)
@given(x=COORD, y=COORD, n=NS, start=STARTS, cw=st.booleans(), dtype=DTYPES)
@example(x=-5.0, y=0.0, n=8, start=180.0, cw=True, dtype=np.float64)
@example(x=0.0, y=5.0, n=8, start=90.0, cw=False, dtype=np.float64)
@example(x=10.0, y=-1e-15, n=8, start=0.0, cw=False, dtype=np.float64)
@example(x=-50.0, y=5e-6, n=8, start=180.0, cw=True, dtype=np.float32)
@example(x=1.0, y=1.0, n=8, start=0.0, cw=False, dtype=np.float32)
@example(x=1.0, y=1.0, n=8, start=-360.0, cw=False, dtype=np.float32)
def test_slice_index_matches_the_naive_rule(x, y, n, start, cw, dtype):
    x, y = cast(x, dtype), cast(y, dtype)
    k = one_slice(x, y, n, start, cw, dtype)
    assert k in naive_slices_near(x, y, n, start, cw), (k, naive_slice(x, y, n, start, cw))
    assert naive_quadrant(x, y) in quadrants_of_sector(k, n, start, cw)  # pillarize reads the point's quadrant
    # the dtype decides nothing (the float32 -> float64 cast is exact), nor a whole turn added to the start
    assert one_slice(x, y, n, start, cw, np.float64) == k
    assert one_slice(x, y, n, start % 360.0 + 360.0, cw, dtype) == k
    assert one_slice(x, y, n, start % 360.0 - 720.0, cw, dtype) == k
    if n >= 4:  # every layout agrees with the default one, which the slice-index feature counts
        assert feature_index(k, n, start, cw) == one_slice(x, y, n, 0.0, False, dtype)


@FAST
@given(x=COORD, y=COORD)
@example(x=10.0, y=-1e-15)
@example(x=np.float32(1.0).item(), y=np.float32(1.0).item())
def test_azimuth_is_float64_in_range_and_dtype_free(x, y):
    a64 = azimuth_deg(np.array([x]), np.array([y]))
    a32 = azimuth_deg(np.array([x], np.float32), np.array([y], np.float32))
    assert a64.dtype == np.float64 and a32.dtype == np.float64
    assert 0.0 <= a64[0] < 360.0 and 0.0 <= a32[0] < 360.0
    assert a32[0] == azimuth_deg(np.array([cast(x, np.float32)]), np.array([cast(y, np.float32)]))[0]
    ref = math.degrees(math.atan2(y, x)) % 360.0
    assert abs(angle_diff_deg(a64[0], ref)) <= 1e-12 * max(1.0, ref)


SWEEP_POINTS = st.lists(st.tuples(COORD, COORD), min_size=0, max_size=30)


@settings(max_examples=150, deadline=None)
@given(pts=SWEEP_POINTS, n=NS, start=STARTS, cw=st.booleans(), dtype=DTYPES, nan_rows=st.lists(st.integers(0, 29), max_size=3))
@example(pts=[(-5.0, 0.0), (0.0, 5.0), (10.0, -1e-15), (1.0, 1.0)], n=8, start=180.0, cw=True, dtype=np.float32, nan_rows=[])
@example(pts=[(1.0, 1.0), (-2.0, 2.0), (3.0, 3.0)], n=8, start=-360.0, cw=False, dtype=np.float32, nan_rows=[])
def test_split_sweep_partitions_and_every_point_carries_its_slices_feature(pts, n, start, cw, dtype, nan_rows):
    arr = np.zeros((len(pts), 5), dtype)
    arr[:, 0] = [cast(p[0], dtype) for p in pts]
    arr[:, 1] = [cast(p[1], dtype) for p in pts]
    for r in nan_rows:
        if r < len(arr):
            arr[r, r % 2] = np.nan
    arr[:, 2] = np.arange(len(arr))  # the row, to follow each point
    slices = split_sweep(arr, n, start, clockwise=cw)
    assert len(slices) == n
    rows = [s[:, 2].astype(np.int64) for s in slices]
    has_azimuth = ~np.isnan(arr[:, 0]) & ~np.isnan(arr[:, 1])
    assert sorted(np.concatenate(rows).tolist()) == np.flatnonzero(has_azimuth).tolist()  # each point once, NaN in none
    for k, (s, r) in enumerate(zip(slices, rows)):
        assert r.tolist() == sorted(r.tolist())  # input order kept
        for i in r:
            assert k in naive_slices_near(arr[i, 0], arr[i, 1], n, start, cw)
        if n >= 4 or start % 180.0 == 0.0:  # n = 2 from 90: a slice is two quadrants of different index features
            assert (s[:, SLICE_INDEX] == feature_index(k, n, start, cw)).all(), (k, s[:, SLICE_INDEX], arr[r, :2])
        t = s[:, SLICE_TIME].astype(np.float64) / SWEEP_DURATION_S
        assert ((t >= 0.0) & (t <= 1.0 + 1e-6)).all()  # float32 rounds the time of azimuth 360 - tiny up past it
    # a start a whole turn away is the same layout: split_sweep's default path when it is a multiple of 360
    for other in (start % 360.0, start % 360.0 + 360.0, start % 360.0 - 360.0):
        for a, b in zip(split_sweep(arr, n, other, clockwise=cw), slices):
            np.testing.assert_array_equal(a, b)


@FAST
@given(x=COORD, y=COORD, n=NS, start=STARTS, cw=st.booleans())
@example(x=10.0, y=-1e-15, n=8, start=0.0, cw=False)
@example(x=-5.0, y=0.0, n=8, start=180.0, cw=True)
def test_relative_time_falls_in_its_slices_window(x, y, n, start, cw):
    """A point of slice k arrives between k / n and (k + 1) / n of the rotation (round the circle: azimuth 0 of a
    point in quadrant 3 is the end of the last slice's window). Not the origin: atan2 of signed zeros gives it an
    azimuth of 0 or 180 whatever its quadrant."""
    assume(x != 0.0 or y != 0.0)
    p = np.array([[x, y, 0.0, 0.0, 0.0]])
    k = one_slice(x, y, n, start, cw, np.float64)
    f = float(relative_time_s(p, start, 1.0, cw)[0])
    assert 0.0 <= f <= 1.0
    centre = (k + 0.5) / n
    assert abs((f - centre + 0.5) % 1.0 - 0.5) <= 0.5 / n + 1e-9, (k, f)


def border_centres(n: int, j: int, r: float, dtype) -> tuple[float, float]:
    """The BEV centre at radius r on the ccw bound 360 j / n (from +x), as a box of that dtype holds it."""
    a = math.radians(360.0 * j / n)
    return cast(r * math.cos(a), dtype), cast(r * math.sin(a), dtype)


def box_at(x: float, y: float, dtype=np.float32) -> np.ndarray:
    b = np.zeros((1, 9), dtype)
    b[0, :7] = [x, y, 0.0, 2.0, 4.5, 1.6, 0.0]
    return b


@settings(max_examples=200, deadline=None)
@given(n=NS.filter(lambda n: 4 <= n <= 360), start=STARTS, cw=st.booleans(), dtype=DTYPES, r=st.sampled_from([5.0, 30.0, 40.0]),
       data=st.data())
@example(n=156, start=0.0, cw=False, dtype=np.float32, r=30.0, data=None)  # (30, 0): was kept by slices 0 and 155
@example(n=28, start=90.0, cw=False, dtype=np.float64, r=5.0, data=None)  # was kept by no slice
@example(n=28, start=0.0, cw=False, dtype=np.float32, r=40.0, data=None)  # was kept by slices 3 and 4
def test_in_slices_partitions_box_centres_on_sector_bounds(n, start, cw, dtype, r, data):
    """restrict_to_sector keeps a centre on a shared bound in exactly one slice, the one slice_index_of and
    split_by_slice give it, a slice of the naive rule's."""
    if data is None:  # the review's cases: (30, 0) at n = 156; the float64 centre kept by none; the 3 | 4 bound of 28
        j = {156: 0, 28: 4}[n] if dtype is np.float32 else None
        x, y = border_centres(n, j, r, dtype) if j is not None else (4.504844339512096, 2.1694186955877908)
    else:
        x, y = border_centres(n, data.draw(st.integers(0, n - 1), label="bound"), r, dtype)
    box = box_at(x, y, dtype)
    kept_by = [k for k in range(n) if in_slices(box, SliceRun((k,), n, start, cw))[0]]
    assert len(kept_by) == 1, kept_by
    assert kept_by[0] in naive_slices_near(x, y, n, start, cw)
    assert kept_by[0] == one_slice(x, y, n, start, cw, dtype)
    # coalesce hands a run's box (float32, as Detections holds it) to the slice whose restriction keeps it
    dets = Detections(box, np.ones(1, np.float32), np.zeros(1, np.int64))
    kept32 = [k for k in range(n) if in_slices(dets.boxes, SliceRun((k,), n, start, cw))[0]]
    run = tuple(k for k in (kept32[0] - 1, kept32[0], kept32[0] + 1) if 0 <= k < n)
    owner = [run[i] for i, part in enumerate(split_by_slice(dets, run, n, start, cw)) if len(part)]
    assert owner == kept32


GRID = GridSpec()


@pytest.mark.parametrize("n, j, start, cw", [(28, 4, 0.0, False), (156, 0, 0.0, False), (8, 4, 180.0, True), (12, 3, 90.0, False)])
def test_postprocess_slice_keeps_a_border_box_in_one_slice(n, j, start, cw):
    """End to end: the slices' own post-processing with restrict_to_sector, each slice its graph's box (the same
    centre, on the shared bound of two slices): exactly one keeps it."""
    x, y = border_centres(n, j, 40.0, np.float32)
    config = PostprocessConfig(restrict_to_sector=True)
    kept = []
    for k in range(n):
        qs = quadrants_of_sector(k, n, start, cw)
        det = np.zeros((len(qs), 1, 9), np.float32)
        ox, oy = GRID.quadrant_origin_m(qs[0])
        det[0, 0, :7] = [x - ox, y - oy, 0.0, 2.0, 4.5, 1.6, 0.0]
        scores = np.full((len(qs), 1), 0.9, np.float32)
        labels = np.zeros((len(qs), 1), np.int64)
        out = postprocess_slice(det, scores, labels, qs, GRID, config, slices=SliceRun((k,), n, start, cw))
        kept += [k] * len(out)
    assert kept == [one_slice(x, y, n, start, cw, np.float32)]
    assert kept[0] in naive_slices_near(x, y, n, start, cw)


def test_postprocess_slice_takes_slices_or_a_sector_not_both():
    det = np.zeros((1, 1, 9), np.float32)
    args = (det, np.zeros((1, 1), np.float32), np.zeros((1, 1), np.int64), (0,), GRID, PostprocessConfig(restrict_to_sector=True))
    with pytest.raises(ValueError, match="not both"):
        postprocess_slice(*args, sector_deg=(0.0, 90.0), slices=SliceRun((0,), 4))
    with pytest.raises(ValueError, match="no slices or sector_deg"):
        postprocess_slice(*args)


def naive_angle_diff(a: float, b: float) -> Fraction:
    """a - b wrapped to [-180, 180) in exact rationals."""
    return (Fraction(a) - Fraction(b) + 180) % 360 - 180


@settings(max_examples=400, deadline=None)
@given(a=st.one_of(st.floats(-1e4, 1e4), st.sampled_from([-180.00000000000003, 180.0, -180.0, -540.0, 1e-300, -1e-300])),
       b=st.one_of(st.floats(-1e4, 1e4), st.sampled_from([0.0, -0.0, 180.0, 1e-300])), dtype=DTYPES)
@example(a=-180.00000000000003, b=0.0, dtype=np.float64)
@example(a=-180.00001, b=0.0, dtype=np.float32)
def test_angle_diff_is_in_range_and_matches_exact_wrap(a, b, dtype):
    a, b = dtype(a), dtype(b)
    d = angle_diff_deg(a, b)
    assert -180.0 <= d < 180.0
    ref = naive_angle_diff(float(a), float(b))
    slack = 360.0 * float(np.finfo(dtype).eps) * max(1.0, abs(float(a)), abs(float(b)))  # the subtraction rounds
    assert abs(float(d) - float(ref)) <= slack or abs(abs(float(d) - float(ref)) - 360.0) <= slack, (d, ref)
    arr = angle_diff_deg(np.array([a, a]), np.array([b, b]))  # the array path wraps alike
    assert ((arr >= -180.0) & (arr < 180.0)).all() and arr[0] == d


SIDE = st.one_of(st.sampled_from([5.7e-29, 1e-310, 5e-324, 1e-45, 1e-160]), st.floats(1e-3, 8.0))
YAW = st.sampled_from([0.0, math.pi / 2, math.pi, 0.3, -1.2])


@settings(max_examples=300, deadline=None)
@given(a=st.tuples(st.floats(-3, 3), st.floats(-3, 3), SIDE, SIDE, YAW), b=st.tuples(st.floats(-3, 3), st.floats(-3, 3), SIDE, SIDE, YAW),
       dtype=DTYPES)
@example(a=(0.0, 0.0, 1.0, 1.0, 0.0), b=(0.0, 0.0, 5.7e-29, 1.0, math.pi / 2), dtype=np.float32)
def test_paired_bev_iou_of_a_denormal_side_warns_nothing(a, b, dtype):
    """A positive but denormal-small side: no RuntimeWarning leaks and the IoU is a number in [0, 1]; next to a box
    of ordinary size it stays within the naive bound min(area) / max(area) (one box inside the other at best). Two
    boxes both under the corner tolerance (``_INSIDE_TOLERANCE_M``) get no such bound: no detection is that small."""
    boxes = [np.array([[p[0], p[1], 0.0, p[2], p[3], 1.0, p[4], 0.0, 0.0]], dtype) for p in (a, b)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        iou = paired_bev_iou(boxes[0], boxes[1])
    assert 0.0 <= iou[0] <= 1.0
    if max(min(p[2], p[3]) for p in (a, b)) >= 1e-3:
        areas = [float(bx[0, 3]) * float(bx[0, 4]) for bx in boxes]
        assert iou[0] <= min(areas) / max(areas) + 1e-9
