"""The replay on non-finite LiDAR data (a NaN / inf coordinate or per-point time: a corrupted file, a non-dense
cloud): the slicing and timing helpers against a naive reference, the player, and streamdet-replay end to end. The
other tools take the same files (the detector drops and counts such points), so the replay must too; an input error
inside the player reaches the user as one line."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.replay.clock import FakeClock
from streamdet.replay.player import WARM_UP_BEFORE_S, PlayerConfig, ReplayInputError, play
from streamdet.replay.schedule import slice_sweep
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import lidar_synced_triggers
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult
from streamdet.runtime_ort.postprocess import Detections

PERIOD_S = 0.05
NAN, INF = float("nan"), float("inf")


def ring(n: int = 720, seed: int = 0, clockwise: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(N, 5) points on a ring at random azimuths and their firing times (counter-clockwise from azimuth 0)."""
    rng = np.random.default_rng(seed)
    az = np.sort(rng.uniform(0.0, 360.0, n))
    pts = np.zeros((n, 5), np.float32)
    pts[:, 0] = 10 * np.cos(np.radians(az))
    pts[:, 1] = 10 * np.sin(np.radians(az))
    pts[:, 2] = rng.uniform(-1.0, 1.0, n)
    pts[:, 3] = rng.uniform(0.0, 255.0, n)
    times = ((360.0 - az) if clockwise else az) / 360.0 * PERIOD_S
    return pts, times


def spoil(pts: np.ndarray, times: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Copies with NaN / inf put in every column and in the times, at random rows."""
    rng = np.random.default_rng(seed)
    pts, times = pts.copy(), times.copy()
    rows = rng.choice(len(pts), size=60, replace=False)
    for i, r in enumerate(rows):
        if i % 6 == 5:
            times[r] = (NAN, INF, -INF)[i % 3]
        else:
            pts[r, i % 5] = (NAN, INF, -INF)[i % 3]
    pts[rows[0], :2] = NAN  # one without any azimuth
    pts[rows[1], :2] = INF  # atan2(inf, inf): an azimuth (45 deg) but no position
    return pts, times


def with_azimuth(pts: np.ndarray) -> int:
    return int((~(np.isnan(pts[:, 0]) | np.isnan(pts[:, 1]))).sum())


def naive_slices(sweep: LidarSweep, n: int, start_deg: float) -> tuple[list[list[int]], list[float]]:
    """Point by point: the rows of each slice (every row with an azimuth; eval's split_sweep leaves a NaN one out)
    and each slice's release (its latest finite firing time among rows finite in every column, else the sector's
    end; a full sweep at the rotation's end)."""
    members: list[list[int]] = [[] for _ in range(n)]
    latest = [-math.inf] * n
    for i, p in enumerate(sweep.points.astype(np.float64)):
        x, y = float(p[0]), float(p[1])
        if math.isnan(x) or math.isnan(y):
            continue
        rel = (math.degrees(math.atan2(y, x)) % 360.0 - start_deg) % 360.0
        k = min(int(rel // (360.0 / n)), n - 1)
        # in a slice of the quadrant the grid puts the point in (axes to the non-negative side): (inf, -0.5) has
        # azimuth -0.0, but it lies below the x axis
        q = (0 if x >= 0 else 1) if y >= 0 else (2 if x < 0 else 3)
        r = (q - round(start_deg / 90.0)) % 4
        lo, hi = r * n // 4, ((r + 1) * n - 1) // 4
        if not lo <= k <= hi:  # on the quadrant's edge: the end of its slices next to the azimuth, round the circle
            k = lo if (lo - k) % n <= (k - hi) % n else hi
        members[k].append(i)
        t = float(sweep.point_time_s[i]) if sweep.point_time_s is not None else rel / 360.0 * sweep.duration_s
        if all(math.isfinite(v) for v in p) and math.isfinite(t):
            latest[k] = max(latest[k], t)
    release = []
    for k in range(n):
        if n == 1:
            t = sweep.duration_s
        elif math.isfinite(latest[k]):
            t = min(latest[k], sweep.duration_s)
        else:
            t = sweep.duration_s * (k + 1) / n
        release.append(sweep.start_s + t)
    return members, release


@pytest.mark.parametrize("n", [1, 4, 8])
@pytest.mark.parametrize("with_times", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_slice_sweep_with_non_finite_rows_matches_a_naive_reference(n, with_times, seed):
    pts, times = spoil(*ring(seed=seed), seed=seed)
    sweep = LidarSweep(3, 4 * PERIOD_S, PERIOD_S, pts, times if with_times else None, np.eye(4), np.eye(4))
    start_deg = 90.0 * seed
    slices = slice_sweep(sweep, n, start_deg)
    members, release = naive_slices(sweep, n, start_deg)
    assert [s.slice_index for s in slices] == list(range(n))
    for s, rows, t in zip(slices, members, release):
        assert s.scan_end_s == pytest.approx(t, abs=1e-7)  # azimuths of float32 points
        assert sweep.start_s <= s.scan_end_s <= sweep.end_s + 1e-12
        # the same points, in input order (x, y, z of the slice layout; NaN == NaN here)
        np.testing.assert_array_equal(s.points[:, :3], pts[rows, :3])
    assert 0 < sum(len(s.points) for s in slices) == with_azimuth(pts) < len(pts)  # all but the rows without an azimuth


def test_a_slice_whose_points_all_lack_a_time_is_released_when_the_sensor_leaves_its_sector():
    pts, times = ring()
    times = times.copy()
    in_first = np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360.0 < 90.0
    times[in_first] = NAN
    pts = pts.copy()
    pts[~in_first & (np.arange(len(pts)) % 2 == 0), 2] = NAN  # half of the others: no position, a real time
    sweep = LidarSweep(0, PERIOD_S, PERIOD_S, pts, times, np.eye(4), np.eye(4))
    slices = slice_sweep(sweep, 4)
    assert slices[0].scan_end_s == pytest.approx(PERIOD_S / 4)  # the sector's end
    assert len(slices[0].points) == int(in_first.sum())  # still handed to the detector
    members, release = naive_slices(sweep, 4, 0.0)
    np.testing.assert_allclose([s.scan_end_s for s in slices], release, atol=1e-12)


def test_an_all_nan_sweep_slices_into_empty_slices_released_at_their_sector_ends():
    pts = np.full((50, 5), NAN, np.float32)
    sweep = LidarSweep(0, PERIOD_S, PERIOD_S, pts, np.full(50, NAN), np.eye(4), np.eye(4))
    slices = slice_sweep(sweep, 4)
    assert [len(s.points) for s in slices] == [0, 0, 0, 0]
    np.testing.assert_allclose([s.scan_end_s for s in slices], PERIOD_S * np.arange(1, 5) / 4)


@pytest.mark.parametrize("clockwise", [False, True])
def test_lidar_synced_triggers_of_the_timing_rows_are_finite_and_match_the_clean_sweep(clockwise):
    clean = [LidarSweep(i, (i + 1) * PERIOD_S, PERIOD_S, *ring(seed=i, n=3600, clockwise=clockwise), np.eye(4), np.eye(4))
             for i in range(6)]  # fmt: skip
    spoilt = []
    for s in clean:
        pts, times = s.points.copy(), s.point_time_s.copy()
        times[::7] = NAN
        times[3::11] = INF
        pts[5::13, 0] = NAN
        spoilt.append(LidarSweep(s.index, s.end_s, s.duration_s, pts, times, s.lidar2ego, s.ego2global))
    axes = {"A": 45.0, "B": 100.0, "C": 250.0}  # off the rotation start, where a window mixes both ends
    want = lidar_synced_triggers(clean, axes, 12.0)
    got = lidar_synced_triggers([s.for_timing() for s in spoilt], axes, 12.0)
    for name in axes:
        assert np.isfinite(got[name]).all()
        np.testing.assert_allclose(got[name], want[name], atol=2e-4)  # the median of a few fewer points
    assert spoilt[0].for_timing().timing_rows().all() and clean[0].for_timing() is clean[0]


class FakeDetector:
    uses_images = True

    def __init__(self, clock, fail_images: bool = False) -> None:
        self.clock, self.fail_images = clock, fail_images
        self.slice_points: list[int] = []

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        self.clock.sleep(0.001)
        finite = int(np.isfinite(points).all(axis=1).sum())
        self.slice_points.append(len(points))
        return SliceResult(Detections.empty(), slice_index, num_slices, timestamp, None, finite, 0, len(points) - finite)

    def update_images(self, images, timestamp=None, **options):
        self.clock.sleep(0.002)
        if self.fail_images and timestamp > WARM_UP_BEFORE_S:
            raise ValueError("camera_timestamps['CAM_FRONT'] must be a finite number of seconds, got nan")
        return ImageUpdate(timestamp, tuple(images), ())


def hostile_drive(sweeps: int = 3) -> Drive:
    out = []
    for i in range(sweeps):
        pts, times = spoil(*ring(seed=i), seed=i)
        out.append(LidarSweep(i, (i + 1) * PERIOD_S, PERIOD_S, pts, times, np.eye(4), np.eye(4)))
    image = {"CAM_FRONT": np.zeros((4, 4, 3), np.uint8)}
    triggers = np.arange(0.0, sweeps * PERIOD_S + 1e-9, 1.0 / 12.0)
    return Drive("hostile", tuple(out), tuple(ImageSet(i, float(t), dict(image), float(t)) for i, t in enumerate(triggers)), 0)


@pytest.mark.parametrize("mode", ["streaming", "full-sweep", "sequential"])
def test_the_player_plays_non_finite_points_to_the_detector(mode):
    clock = FakeClock()
    drive = hostile_drive()
    det = FakeDetector(clock)
    rec = play(drive, det, clock, PlayerConfig(mode, 4))
    assert all(s.emitted for s in rec.slices)
    assert all(math.isfinite(s.release_s) and math.isfinite(s.scan_end_s) for s in rec.slices)
    # every point with an azimuth reached the detector (which drops the non-finite ones and counts them)
    assert sum(det.slice_points) == sum(with_azimuth(s.points) for s in drive.sweeps)


def test_an_input_error_inside_the_player_is_a_value_error_naming_its_cause():
    clock = FakeClock()
    with pytest.raises(ReplayInputError) as info:
        play(hostile_drive(), FakeDetector(clock, fail_images=True), clock, PlayerConfig("streaming", 4))
    e = info.value
    assert isinstance(e, ValueError) and isinstance(e, RuntimeError)  # one line in the tools; old callers still catch it
    assert str(e) == "streaming replay of hostile: camera_timestamps['CAM_FRONT'] must be a finite number of seconds, got nan"
    assert isinstance(e.__cause__, ValueError)


def test_a_bug_inside_the_player_stays_a_runtime_error():
    class Buggy(FakeDetector):
        def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
            raise KeyError("oops")

    clock = FakeClock()
    with pytest.raises(RuntimeError, match="failed: KeyError") as info:
        play(hostile_drive(1), Buggy(clock), clock, PlayerConfig("streaming", 4))
    assert not isinstance(info.value, ValueError)


# ---- streamdet-replay end to end -----------------------------------------------------------------------------


def _lidar_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*.pcd.bin") if "LIDAR_TOP" in p.name)


@pytest.fixture(scope="module")
def hostile_data(tiny_drive_data, tmp_path_factory) -> Path:
    """tiny_drive_data with NaN / inf coordinates in every sweep (x and y of a few rows: no azimuth) and NaN / inf
    per-point times."""
    out = tmp_path_factory.mktemp("hostile") / "data"
    shutil.copytree(tiny_drive_data, out)
    files = _lidar_files(out)
    assert files and all(Path(f"{p}.time").is_file() for p in files)
    for i, path in enumerate(files):
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 5)
        pts[i % 7 :: 97, 0] = NAN
        pts[3::211, 1] = NAN
        pts[5::101, 2] = INF
        pts[7::151, 3] = -INF
        pts.tofile(path)
        times = np.fromfile(f"{path}.time", dtype="<f4")
        times[::50] = NAN
        times[1::173] = INF
        times.tofile(f"{path}.time")
    return out


def _replay_args(data: Path, export: Path, *more: str) -> list[str]:
    return ["--data", str(data), "--split", "all", "--export-dir", str(export), "--max-seconds", "0.2", *more]


@pytest.mark.parametrize("trigger", ["lidar-synced", "simultaneous"])
def test_streamdet_replay_plays_non_finite_points_and_times(hostile_data, tiny_export, tmp_path, trigger):
    from streamdet.replay.cli import main

    args = _replay_args(hostile_data, tiny_export, "--mode", "all", "--camera-trigger", trigger, "--json", str(tmp_path / "r.json"))
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "non-finite per-point time(s)" in result.output and "point(s) with a NaN / inf value" in result.output
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["modes"]["streaming"]["slices_total"] == 4 * 8  # rotations ending by 0.2 s
    for summary in doc["modes"].values():
        assert math.isfinite(summary["map_offline"]) and summary["slices_dropped"] == 0


def test_an_input_error_inside_streamdet_replay_is_one_line(hostile_data, tiny_export, monkeypatch, capsys):
    from streamdet.cli_utils import run_edge
    from streamdet.runtime_ort.detector import StreamingDetector

    original = StreamingDetector.update_images

    def corrupt(self, images, timestamp=None, **options):
        if timestamp is not None and timestamp > WARM_UP_BEFORE_S:  # not the warm-up's: the drive's own
            raise ValueError("a corrupt camera frame (test)")
        return original(self, images, timestamp, **options)

    monkeypatch.setattr(StreamingDetector, "update_images", corrupt)
    code = run_edge("streamdet.replay.cli", "streamdet-replay", args=_replay_args(hostile_data, tiny_export, "--mode", "streaming"))
    err = capsys.readouterr().err
    assert code == 1, err
    assert "Traceback" not in err and "RuntimeError" not in err
    (line,) = [x for x in err.splitlines() if "a corrupt camera frame (test)" in x]
    assert "streaming replay of " in line
