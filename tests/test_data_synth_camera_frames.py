"""Camera sweeps of the synthetic world (``SynthConfig.camera_hz``): when the cameras expose between key frames
against a naive reference of the rule, what the tables and files hold, that key frames do not change, and that the
replay's lidar-synced triggers at that rate find a frame recorded at each trigger."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.data.nuscenes import CAMERA_CHANNELS, NuScenesReader
from streamdet.data.synth_camera_frames import camera_frames, camera_trigger_times_s
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import SynthConfig, generate_dataset, real_rig_records

RIG = real_rig_records((160, 90))
WORLD = WorldConfig(samples_per_scene=3)
SWEEP_S, INTERVAL_S = WORLD.sweep_duration_s, WORLD.sample_interval_s
KEY_TIMES = SWEEP_S + INTERVAL_S * np.arange(WORLD.samples_per_scene)


def _first_sweep_start(spp: int) -> float:
    return float(KEY_TIMES[0] - (spp - 1) * INTERVAL_S / spp - SWEEP_S)


def _naive_frames(name: str, camera_hz: float, spp: int) -> list[tuple[float, int, bool]]:
    """Every rotation's crossing, one at a time: a frame where it is the first crossing at or after a multiple of
    1 / camera_hz after the first sweep's start, or a key frame's own."""
    t0 = _first_sweep_start(spp)
    per = round(INTERVAL_S / SWEEP_S)
    crossings = []  # (time, key index, is key)
    for k, t_key in enumerate(KEY_TIMES):
        for back in range(per - 1, -1, -1) if k else range(per + 1, -1, -1):
            t = camera_trigger_times_s(RIG, float(t_key) - back * SWEEP_S, SWEEP_S)[name]
            if t >= t0 - 1e-9:
                crossings.append((t, k, back == 0))
    out = []
    i = 0
    for j, (t, k, key) in enumerate(crossings):
        nominal_hit = False
        while t0 + i / camera_hz <= t + 1e-9:
            nominal_hit = True
            i += 1
        if nominal_hit or key:
            out.append((t, k, key))
    return out


@pytest.mark.parametrize("camera_hz", [12.0, 20.0, 5.0, 1.0])
@pytest.mark.parametrize("spp", [10, 1, 2])
def test_frames_follow_the_rule(camera_hz, spp):
    frames = camera_frames(RIG, KEY_TIMES, INTERVAL_S, SWEEP_S, _first_sweep_start(spp), camera_hz)
    assert list(frames) == [m.name for m in RIG.models]
    for name, got in frames.items():
        want = _naive_frames(name, camera_hz, spp)
        assert [(f.key_index, f.is_key) for f in got] == [(k, key) for _, k, key in want]
        np.testing.assert_allclose([f.t_s for f in got], [t for t, _, _ in want], atol=1e-12)
        times = np.array([f.t_s for f in got])
        assert np.all(np.diff(times) > SWEEP_S - 1e-9)  # at most one exposure a rotation
        rotations = np.diff(times) / SWEEP_S
        np.testing.assert_allclose(rotations, np.round(rotations), atol=1e-9)  # whole rotations apart


def test_key_frames_only_is_one_exposure_per_key_frame():
    frames = camera_frames(RIG, KEY_TIMES, INTERVAL_S, SWEEP_S, _first_sweep_start(10), 0.0)
    for name, got in frames.items():
        assert [(f.key_index, f.is_key) for f in got] == [(k, True) for k in range(len(KEY_TIMES))]
        assert [f.t_s for f in got] == [camera_trigger_times_s(RIG, float(t), SWEEP_S)[name] for t in KEY_TIMES]


def test_twelve_hz_on_the_twenty_hz_lidar():
    frames = camera_frames(RIG, KEY_TIMES, INTERVAL_S, SWEEP_S, _first_sweep_start(10), 12.0)
    for name, got in frames.items():
        times = np.array([f.t_s for f in got])
        gaps_ms = np.round(np.diff(times) * 1e3, 6)
        assert set(gaps_ms.tolist()) <= {50.0, 100.0}
        span = times[-1] - times[0]
        assert 11.0 <= (len(times) - 1) / span <= 14.0  # about 12 Hz; the key frames come on top where the rules differ
        # each frame is filed under the first key frame at or after it
        key_times = {f.key_index: f.t_s for f in got if f.is_key}
        for f in got:
            assert f.t_s <= key_times[f.key_index] + 1e-12
            assert f.key_index == 0 or f.t_s > key_times[f.key_index - 1]


@pytest.mark.parametrize("bad", [-1.0, 20.5, float("nan"), float("inf"), True, "12"])
def test_bad_camera_rates_are_refused(bad):
    with pytest.raises(ValueError, match="camera_hz must be 0"):
        SynthConfig(camera_hz=bad)


def test_camera_rate_needs_whole_rotations_per_interval():
    with pytest.raises(ValueError, match="whole LiDAR rotations"):
        SynthConfig(camera_hz=12.0, world=WorldConfig(sample_interval_s=0.52))
    SynthConfig(camera_hz=0.0, world=WorldConfig(sample_interval_s=0.52))  # key frames only: any interval


def test_cli_refuses_a_rate_above_the_lidar(tmp_path):
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "d"), "--camera-hz", "25"])
    assert result.exit_code == 2 and "--camera-hz" in result.output and "25" in result.output
    assert not (tmp_path / "d").exists()


def _tables(root, config):
    return {n: json.loads((root / config.version / f"{n}.json").read_text()) for n in ("sample_data", "calibrated_sensor", "sensor")}


def _files(root, folder):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted((root / folder).rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory):
    base = dict(num_scenes=1, seed=5, resolution=(160, 90), sweeps_per_sample=10, world=WorldConfig(samples_per_scene=2))
    roots = {}
    for hz in (0.0, 12.0):
        roots[hz] = tmp_path_factory.mktemp(f"cams{int(hz)}")
        generate_dataset(roots[hz], SynthConfig(camera_hz=hz, **base))
    return roots, SynthConfig(**base)


def test_camera_sweeps_leave_the_key_frames_as_they_were(two_datasets):
    roots, config = two_datasets
    assert _files(roots[0.0], "samples") == _files(roots[12.0], "samples")  # images, masks, LiDAR: the same bytes
    plain, more = _tables(roots[0.0], config), _tables(roots[12.0], config)
    key = [{k: v for k, v in r.items() if k not in ("prev", "next")} for r in plain["sample_data"]]
    key_more = [{k: v for k, v in r.items() if k not in ("prev", "next")} for r in more["sample_data"] if r["is_key_frame"]
                or r["fileformat"] != "jpg"]  # fmt: skip
    assert sorted(key, key=lambda r: r["token"]) == sorted(key_more, key=lambda r: r["token"])
    assert not (roots[0.0] / "sweeps" / "CAM_FRONT").exists()
    assert json.loads((roots[12.0] / "world.json").read_text())["camera_hz"] == 12.0


def test_camera_sweeps_in_the_tables(two_datasets):
    roots, config = two_datasets
    root = roots[12.0]
    tables = _tables(root, config)
    sensor = {s["token"]: s["channel"] for s in tables["sensor"]}
    channel = {cs["token"]: sensor[cs["sensor_token"]] for cs in tables["calibrated_sensor"]}
    by_token = {r["token"]: r for r in tables["sample_data"]}
    for cam in CAMERA_CHANNELS:
        rows = [r for r in tables["sample_data"] if channel[r["calibrated_sensor_token"]] == cam]
        assert sum(r["is_key_frame"] for r in rows) == 2 and len(rows) > 10
        for r in rows:
            assert r["filename"].startswith("samples/" if r["is_key_frame"] else "sweeps/")
            assert (root / r["filename"]).is_file()
            assert (root / (r["filename"] + ".mask.npz")).is_file() == r["is_key_frame"]  # nothing annotates a sweep
        # one prev / next chain per camera through key frames and sweeps, in time order
        first = [r for r in rows if not r["prev"]]
        assert len(first) == 1
        chain = [first[0]]
        while chain[-1]["next"]:
            chain.append(by_token[chain[-1]["next"]])
        assert [r["token"] for r in chain] == [r["token"] for r in sorted(rows, key=lambda r: r["timestamp"])]
    reader = NuScenesReader(root, config.version)
    assert len(reader) == 2
    sample = reader.get(1)
    assert all(path.parts[-3] == "samples" for path in sample.image_paths.values())  # a sample is its key frame's


def test_replay_triggers_find_a_frame_recorded_at_each(two_datasets):
    from streamdet.replay.nuscenes_source import DatasetTables, load_drive

    roots, config = two_datasets
    tables = DatasetTables(roots[12.0], config.version)
    drive = load_drive(tables, tables.scene_names()[0], (64, 36), camera_hz=12.0, camera_trigger="lidar-synced")
    assert len(drive.image_sets) > 6 * 8
    lags_ms = np.array([(s.capture_s - s.recorded_s) * 1e3 for s in drive.image_sets])
    assert np.all(lags_ms >= 0) and np.all(lags_ms < 1.0)
    assert any("records them at 1" in note and "held" not in note for note in drive.notes)
    held = load_drive(DatasetTables(roots[0.0], config.version), tables.scene_names()[0], (64, 36), camera_hz=12.0)
    assert np.median([s.capture_s - s.recorded_s for s in held.image_sets]) > 0.04  # key frames only: images held
