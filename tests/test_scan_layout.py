"""The LiDAR's scan layout (start azimuth, direction; core/sectors.py) against naive references: sectors and
quadrants in both directions and for every slice count, layout-free point features, the detector, the phase
lock's quadrant order, the replay's layout read from per-point times, and the CLIs' options."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.core.sectors import (
    MAX_NUM_SLICES, azimuth_deg, quadrants_of_sector, run_bounds_deg, scan_fraction, sector_bounds_deg, slice_index_of,
)
from streamdet.core.slicing import feature_index, relative_time_s, split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.core.scan_layout import check_layout, choose_layout
from streamdet.replay.scan_layout import NUSCENES_LIDAR_TOP, drive_layout, layout_from_times, resolve_layout
from streamdet.replay.source import LidarSweep
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.phase_lock import RotationPhase

STARTS = (-360.0, -90.0, 0.0, 90.0, 180.0, 270.0)


def _naive_bounds(k: int, n: int, start: float, clockwise: bool) -> tuple[float, float]:
    w = 360.0 / n
    lo = start - (k + 1) * w if clockwise else start + k * w
    return lo % 360.0, lo % 360.0 + w


def _naive_quadrants(lo: float, hi: float) -> tuple[int, ...]:
    """Quadrants whose azimuth range [90 q, 90 q + 90) meets [lo, hi), in exact fractions of a degree."""
    return tuple(sorted({int((a % 360.0) // 90.0) for a in np.linspace(lo, hi, 721)[:-1]}))


@pytest.mark.parametrize("clockwise", [False, True])
@pytest.mark.parametrize("n", [1, 2, 4, 8, 12, 32])
def test_sectors_match_a_naive_reference(n, clockwise):
    for start in STARTS:
        for k in range(n):
            lo, hi = sector_bounds_deg(k, n, start, clockwise)
            assert (lo, hi) == pytest.approx(_naive_bounds(k, n, start, clockwise), abs=1e-9)
            assert quadrants_of_sector(k, n, start, clockwise) == _naive_quadrants(lo, hi)
        # the slices partition the turn, each point in the sector whose bounds hold it, numbered in scan order
        rng = np.random.default_rng(n)
        az = rng.uniform(0, 360, 2000)
        ks = slice_index_of(np.cos(np.radians(az)), np.sin(np.radians(az)), n, start, clockwise)
        for a, k in zip(az, ks):
            lo, _ = sector_bounds_deg(int(k), n, start, clockwise)
            assert (a - lo) % 360.0 < 360.0 / n + 1e-9
        frac = scan_fraction(az, start, clockwise)
        assert np.all((frac >= ks / n - 1e-12) & (frac <= (ks + 1) / n + 1e-12))  # the scan reaches slice k during k


def test_every_slice_count_puts_each_slice_in_the_quadrant_its_points_are_in():
    """j * (360 / n) rounded below an axis for 26 counts (156, 312, ...): their slice there named the quadrant before
    it and pillarize dropped every point of it (geometry review M1)."""
    wrong = []
    for n in range(4, MAX_NUM_SLICES + 1, 4):
        ks = np.arange(n)
        mid = np.radians((ks + 0.5) * 360.0 / n)  # (n,) each sector's middle
        if not np.array_equal(slice_index_of(np.cos(mid), np.sin(mid), n), ks):
            wrong.append((n, "slice_index_of"))
        # the slices next to an axis are where rounding could move a bound across it
        for k in {0, n // 4 - 1, n // 4, n // 2 - 1, n // 2, 3 * n // 4 - 1, 3 * n // 4, n - 1}:
            lo = sector_bounds_deg(k, n)[0]
            if quadrants_of_sector(k, n) != ((4 * k) // n,) or int(lo // 90.0) != (4 * k) // n:
                wrong.append((n, k))
    assert not wrong, wrong[:5]


def test_azimuth_is_below_360():
    tiny = -np.logspace(-300, -13, 50)
    assert np.all(azimuth_deg(np.ones_like(tiny), tiny) < 360.0)
    assert azimuth_deg(1.0, -1e-300) == 0.0


@pytest.mark.parametrize("clockwise", [False, True])
def test_a_run_of_slices_spans_its_sectors(clockwise):
    for start in STARTS:
        lo, hi = run_bounds_deg(2, 3, 8, start, clockwise)
        parts = [sector_bounds_deg(k, 8, start, clockwise) for k in (2, 3)]
        assert hi - lo == pytest.approx(90.0)
        assert {p[0] for p in parts} == {lo % 360.0, (lo + 45.0) % 360.0}
    with pytest.raises(ValueError, match="ends at or after"):
        run_bounds_deg(3, 2, 8)


@pytest.mark.parametrize("n", [1, 2, 8, 32])
def test_the_points_features_do_not_depend_on_the_layout(n):
    """Slice index and time say where a point lies (counted from +x, counter-clockwise): a sensor that starts
    elsewhere or turns the other way feeds a model the values it learnt for those azimuths."""
    points = load_bundled_sample().points
    ref = {tuple(r[:4]): r[4:] for r in np.concatenate(split_sweep(points, n))}
    for start in STARTS:
        for clockwise in (False, True):
            slices = split_sweep(points, n, start, clockwise=clockwise)
            for k, s in enumerate(slices):
                want = np.array([ref[tuple(r[:4])] for r in s[:200]]).reshape(-1, 2)
                np.testing.assert_array_equal(s[:200, 4:], want)
                if len(s) and (n >= 4 or start % 180 == 0):  # the slice covers one feature sector
                    assert np.all(s[:, 5] == feature_index(k, n, start, clockwise))


@pytest.mark.parametrize("clockwise", [False, True])
def test_a_slice_s_feature_index_is_the_sector_it_covers(clockwise):
    """Counted in integers: floor(lo * n / 360) in floats gave slice 11 of 28 the index 10 (diff review M1)."""
    for n in [1, 2, *range(4, 260, 4)]:
        for start in STARTS:
            got = [feature_index(k, n, start, clockwise) for k in range(n)]
            if n >= 4:  # one feature sector per slice: the one holding its middle
                mids = [sum(sector_bounds_deg(k, n, start, clockwise)) / 2 % 360.0 for k in range(n)]
                assert got == [int(m * n // 360) for m in mids], (n, start)
            else:  # n = 1, 2: the feature sector holding the slice's first bound
                assert got == [int(sector_bounds_deg(k, n, start, clockwise)[0] * n // 360) % n for k in range(n)]
    assert [feature_index(k, 28) for k in range(28)] == list(range(28))


def test_relative_time_follows_the_scan():
    pts = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])  # azimuths 0, 90, 180, 270
    np.testing.assert_allclose(relative_time_s(pts, 0.0, 0.1), [0, 0.025, 0.05, 0.075])
    np.testing.assert_allclose(relative_time_s(pts, 180.0, 0.1, clockwise=True), [0.05, 0.025, 0.1, 0.075])


def test_a_clockwise_detector_finds_what_the_default_one_finds(tiny_export):
    """Same sectors, same features: the same boxes, only the slices' order and numbers differ."""
    sweep = load_bundled_sample().points
    with StreamingDetector(tiny_export) as a, StreamingDetector(tiny_export, DetectorConfig(start_deg=180.0, clockwise=True)) as b:
        da, db = a.detect_sweep_slices(sweep), b.detect_sweep_slices(sweep)
        for k in range(a.num_slices):
            j = a.num_slices - 1 - (k - 4) % a.num_slices  # the default's slice of the same sector
            np.testing.assert_array_equal(db.points[k], da.points[j])
            assert db.slices[k].slice_index == k and da.slices[j].slice_index == j
            np.testing.assert_allclose(db.slices[k].detections.boxes, da.slices[j].detections.boxes, rtol=1e-6, atol=1e-6)
        order = lambda d: np.lexsort(d.boxes.T[:3])  # noqa: E731
        np.testing.assert_allclose(db.detections.boxes[order(db.detections)], da.detections.boxes[order(da.detections)],
                                   rtol=1e-6, atol=1e-6)  # fmt: skip
    with pytest.raises(ValueError, match="clockwise must be True or False"):
        DetectorConfig(clockwise="yes")


def test_the_phase_lock_enters_the_quadrants_in_scan_order():
    assert RotationPhase(8).quadrant_order == (0, 1, 2, 3)
    assert RotationPhase(8, 180.0, clockwise=True).quadrant_order == (1, 0, 3, 2)  # nuScenes' LIDAR_TOP
    assert RotationPhase(4, 90.0, clockwise=True).quadrant_order == (0, 3, 2, 1)


def _ring(start: float, clockwise: bool, jitter: float = 0.0) -> LidarSweep:
    """A 32-ring sweep fired column by column from ``start``, with per-point times."""
    cols = (np.arange(1800) + 0.5) / 1800.0  # share of the turn
    az = start - 360.0 * cols if clockwise else start + 360.0 * cols
    az = np.repeat(az, 32) + np.random.default_rng(1).normal(0, jitter, 32 * len(cols))
    pts = np.zeros((len(az), 5), np.float32)
    pts[:, 0], pts[:, 1] = 20 * np.cos(np.radians(az)), 20 * np.sin(np.radians(az))
    times = np.repeat(cols * 0.05, 32)
    return LidarSweep(0, 0.05, 0.05, pts, times, np.eye(4), np.eye(4))


@pytest.mark.parametrize("start, clockwise", [(0.0, False), (189.0, True), (-95.0, False), (93.0, True), (271.0, True)])
def test_the_replay_reads_the_layout_from_per_point_times(start, clockwise):
    found = layout_from_times(_ring(start, clockwise, jitter=0.2).points, _ring(start, clockwise, jitter=0.2).point_time_s)
    assert found is not None and found.clockwise == clockwise
    assert found.start_deg == (round(start / 90.0) * 90.0) % 360.0


def test_the_real_sample_turns_as_nuscenes_lidar_top_is_said_to():
    """nuScenes stores a sweep's points in firing order: read as times, the bundled real sweep's order shows the
    layout the replay assumes for nuScenes tables without per-point times (clockwise, from the axis at 180 deg)."""
    points = load_bundled_sample().points
    found = layout_from_times(points, np.arange(len(points), dtype=np.float64))
    assert (found.start_deg, found.clockwise) == (NUSCENES_LIDAR_TOP.start_deg, NUSCENES_LIDAR_TOP.clockwise)


def test_times_that_show_no_steady_turn_say_nothing():
    sweep = _ring(45.0 + 0.1, True)  # a start just past an axis midpoint is not pulled the other way by the group mean
    assert layout_from_times(sweep.points, sweep.point_time_s).start_deg == 90.0
    sweep = _ring(44.9, False)
    assert layout_from_times(sweep.points, sweep.point_time_s).start_deg == 0.0
    rng = np.random.default_rng(3)
    assert layout_from_times(sweep.points, rng.permutation(sweep.point_time_s)) is None  # shuffled
    assert layout_from_times(sweep.points, np.zeros(len(sweep.points))) is None  # constant
    assert layout_from_times(sweep.points, rng.uniform(0, 0.05, len(sweep.points))) is None  # random
    constant = LidarSweep(0, 0.05, 0.05, sweep.points, np.zeros(len(sweep.points)), np.eye(4), np.eye(4))
    assert "show no steady turn" in drive_layout([constant]).source
    assert (drive_layout([constant]).start_deg, drive_layout([constant]).clockwise) == (180.0, True)


def test_without_per_point_times_the_layout_is_nuscenes_lidar_top():
    sweep = _ring(0.0, False)
    untimed = LidarSweep(0, 0.05, 0.05, sweep.points, None, np.eye(4), np.eye(4))
    assert drive_layout([untimed]) == NUSCENES_LIDAR_TOP
    assert (NUSCENES_LIDAR_TOP.start_deg, NUSCENES_LIDAR_TOP.clockwise) == (180.0, True)
    assert drive_layout([untimed, sweep]).clockwise is False  # the first timed sweep says it
    assert layout_from_times(sweep.points[:50], sweep.point_time_s[:50]) is None  # too few points say nothing
    given = resolve_layout([untimed], 90.0, False)
    assert (given.start_deg, given.clockwise, given.source) == (90.0, False, "as given")
    partly = resolve_layout([untimed], None, False)
    assert (partly.start_deg, partly.clockwise) == (180.0, False) and "partly given" in partly.source
    for bad in ((45.0, None), (None, "yes"), (float("nan"), None), (360.0, None)):
        with pytest.raises(ValueError):
            resolve_layout([untimed], *bad)


@pytest.mark.parametrize("command", ["replay", "bag"])
def test_the_clis_take_the_scan_layout(command):
    if command == "replay":
        from streamdet.replay.cli import main
    else:
        from streamdet.bag.cli import run_cmd as main
    text = " ".join(CliRunner().invoke(main, ["--help"]).output.split())
    assert "--scan-start-deg" in text and "--clockwise / --counter-clockwise" in text and "from the data" in text


@pytest.mark.parametrize("n", [1, 2, 4, 8, 32])
@pytest.mark.parametrize("start, clockwise", [(0.0, False), (90.0, False), (180.0, True), (-90.0, True)])
def test_points_on_an_axis_are_in_a_slice_of_their_grid_quadrant(n, start, clockwise):
    """(0, 5) and (-5, 0) were in the slice after their grid quadrant's (azimuth 90 and 180 open the next sector,
    the grid puts x = 0 and y = 0 on the non-negative side) and pillarize dropped them; so did float32 points within
    about 1e-7 rad of an axis (geometry review M2)."""
    from streamdet.calibration.grid import GridSpec
    from streamdet.runtime_ort.pillarize import pillarize

    grid = GridSpec()
    on_axes = [(0.0, 5.0), (-5.0, 0.0), (5.0, 0.0), (0.0, -5.0), (-0.0, 5.0), (-5.0, -0.0), (0.0, 0.0)]
    rng = np.random.default_rng(n)
    angle = np.repeat(np.radians([0.0, 90.0, 180.0, 270.0]), 500) + rng.uniform(-1e-6, 1e-6, 2000)
    near = np.stack([20 * np.cos(angle), 20 * np.sin(angle)], axis=1).astype(np.float32)  # (2000, 2) float32
    xy = np.concatenate([np.array(on_axes, np.float32), near])
    sweep = np.zeros((len(xy), 5), np.float32)
    sweep[:, :2] = xy
    slices = split_sweep(sweep, n, start, clockwise=clockwise)
    assert sum(len(s) for s in slices) == len(xy)
    for k, s in enumerate(slices):
        if len(s):
            q = quadrants_of_sector(k, n, start, clockwise)
            assert set(grid.quadrant_of_xy(s[:, 0], s[:, 1]).tolist()) <= set(q), k
            kept = pillarize(s, grid, q, 32, 4096)
            assert kept.num_outside_dropped == 0, (k, kept.num_outside_dropped)


def test_the_replay_names_the_synthetic_world_of_its_drives(tmp_path):
    """World 6 plays differently from world 4 (sensor timing, annotations): a replay's notes name the world."""
    import json

    from streamdet.data.synth_world import WORLD_FILE, world_version_of

    assert world_version_of(tmp_path) is None  # real nuScenes: no world.json
    (tmp_path / WORLD_FILE).write_text(json.dumps({"world_version": 6, "scenes": {}}))
    assert world_version_of(tmp_path) == 6
    for bad in ("{", json.dumps({"world_version": "6"}), json.dumps([6])):
        (tmp_path / WORLD_FILE).write_text(bad)
        assert world_version_of(tmp_path) is None


def test_a_replay_of_world_6_drives_says_its_world_and_layout(tiny_drive_data):
    from streamdet.replay.nuscenes_source import DatasetTables, load_drive

    tables = DatasetTables(tiny_drive_data, "v1.0-synth")
    drive = load_drive(tables, tables.scene_names()[0], None, max_seconds=0.2)
    assert "data: streamdet-synth world 6" in " ".join(drive.notes)
    assert (drive.scan_layout.start_deg, drive.scan_layout.clockwise) == (180.0, True)


@pytest.mark.parametrize("start, clockwise", [(None, None), (0, True), (-360, False), (270.0, None), (np.float32(90), np.bool_(True))])
def test_check_layout_takes_axes_bools_and_none_from_data(start, clockwise):
    check_layout(start, clockwise)
    if start is not None and clockwise is not None:
        check_layout(start, clockwise, from_data=False)


@pytest.mark.parametrize("start, clockwise, match", [
    (45, True, "start_deg must be a multiple of 90 .* got 45"),
    (360, True, "start_deg .* got 360"),
    (1e300, True, "start_deg .* got 1e\\+300"),
    (float("nan"), True, "start_deg .* got nan"),
    (True, True, "start_deg .* got True"),
    ("90", True, "start_deg .* got '90'"),
    (0, 1, "clockwise must be True or False .* got 1"),
    (0, "yes", "clockwise must be True or False .* got 'yes'"),
])  # fmt: skip
def test_check_layout_refuses_quoting_the_value(start, clockwise, match):
    with pytest.raises(ValueError, match=match):
        check_layout(start, clockwise)
    with pytest.raises(ValueError, match=match):
        choose_layout(None, NUSCENES_LIDAR_TOP, start, clockwise)


def test_none_is_refused_where_the_layout_is_not_read_from_data():
    with pytest.raises(ValueError, match=r"start_deg must be a multiple of 90 degrees in \[-360, 360\), got None"):
        check_layout(None, True, from_data=False)
    with pytest.raises(ValueError, match="DetectorConfig.clockwise must be True or False, got None"):
        DetectorConfig(clockwise=None)


def test_check_layout_gives_python_numbers_for_the_reports():
    """numpy numbers are taken, and handed on as Python ones: a replay's config goes into its JSON report."""
    import json
    from pathlib import Path

    from streamdet.replay.run import ReplayConfig

    start, cw = check_layout(np.float32(180), np.bool_(True))
    assert (start, cw) == (180.0, True) and type(start) is float and type(cw) is bool
    assert check_layout(None, None) == (None, None)
    config = ReplayConfig(data=Path("x"), export_dir=Path("y"), start_deg=np.float32(180), clockwise=np.bool_(True))
    assert type(config.start_deg) is float and type(config.clockwise) is bool
    json.dumps(config.to_dict())
    det_config = DetectorConfig(start_deg=np.int64(90), clockwise=np.bool_(False))
    assert type(det_config.start_deg) is float and det_config.clockwise is False
