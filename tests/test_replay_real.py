"""One real replay: a few hundred ms of a tiny synthetic scene through a tiny export, in every mode, on the wall clock."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.data.synth_trajectories import load_trajectories
from streamdet.replay.truth import INTERPOLATED, TRAJECTORIES, load_ground_truth

SUMMARY_KEYS = {"map_streaming", "map_offline", "nds_streaming", "latency_ms", "slices_dropped", "slices_total", "image_age_ms"}


@pytest.fixture(scope="module")
def drive_data(tiny_drive_data):
    return tiny_drive_data  # one key frame with ten 20 Hz sweeps before it at 160x90 (conftest)


def test_replay_cli_plays_every_mode_and_writes_the_issue_json(drive_data, tiny_export, tmp_path):
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.3",
            "--time-scale", "2", "--json", str(tmp_path / "r.json"), "--out", str(tmp_path / "out")]  # fmt: skip
    pytest.importorskip("matplotlib")
    args += ["--plot", str(tmp_path / "r.png")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "| streaming |" in result.output and "ground truth at emission time: trajectories" in result.output
    doc = json.loads((tmp_path / "r.json").read_text())
    assert set(doc) == {"config", "modes"} and set(doc["modes"]) == {"streaming", "full_sweep", "sequential"}
    assert doc["config"]["time_scale"] == 2.0 and doc["config"]["cpu"]["threads"] >= 1
    for mode, summary in doc["modes"].items():
        assert set(summary) == SUMMARY_KEYS, mode
        assert set(summary["latency_ms"]) == {"p50", "p95", "p99", "max"}
        assert set(summary["image_age_ms"]) == {"p50", "p95"}
    assert doc["modes"]["streaming"]["slices_total"] == 6 * 8  # rotations ending by 0.3 s, 8 slices each
    assert doc["modes"]["full_sweep"]["slices_total"] == 6
    details = json.loads((tmp_path / "out" / "replay.json").read_text())
    for mode in ("streaming", "full_sweep", "sequential"):
        (rec,) = details["modes"][mode]["recordings"]
        for s in rec["slices"]:
            assert s["dropped"] or s["emit_s"] >= s["release_s"] >= s["scan_end_s"] - 1e-9  # every slice accounted for
        assert details["modes"][mode]["stages"]["slice_head"]["gflop_per_s"] > 0
    assert (tmp_path / "r.png").stat().st_size > 10_000


def test_replay_cli_says_when_the_split_holds_fewer_scenes_than_asked(drive_data, tiny_export):
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.1",
            "--mode", "streaming", "--scenes", "50"]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "note: --scenes 50, but split 'all' holds 1 scene(s): all of them were played" in result.output


def test_replay_with_a_lidar_only_fallback_counts_its_slices(drive_data, tiny_export, tiny_lidar_export, tmp_path):
    """Images older than 1 ms at every slice: the fallback's graph runs them, and the report counts them."""
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.2",
            "--mode", "streaming", "--time-scale", "2", "--fallback-export", str(tiny_lidar_export),
            "--fallback-after-ms", "1", "--out", str(tmp_path / "out")]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert f"LiDAR-only fallback {tiny_lidar_export}" in result.output and "older than 1 ms" in result.output
    details = json.loads((tmp_path / "out" / "replay.json").read_text())
    summary = details["modes"]["streaming"]
    (rec,) = summary["recordings"]
    emitted = [s for s in rec["slices"] if not s["dropped"]]
    assert summary["slices_fallback"] == sum(s["fallback"] for s in emitted) > 0
    assert details["config"]["fallback_export_dir"] == str(tiny_lidar_export) and details["config"]["fallback_after_s"] == 0.001


def test_replay_cli_refuses_a_fused_fallback(drive_data, tiny_export):
    from streamdet.replay.cli import main

    result = CliRunner().invoke(main, ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export),
                                       "--fallback-export", str(tiny_export), "--max-seconds", "0.1"])  # fmt: skip
    assert result.exit_code != 0 and "must be a LiDAR-only export" in result.output and "Traceback" not in result.output


def test_replay_cli_refuses_a_missing_export(drive_data, tmp_path):
    from streamdet.replay.cli import main

    result = CliRunner().invoke(main, ["--data", str(drive_data), "--export-dir", str(tmp_path)])
    assert result.exit_code != 0 and "manifest.json" in result.output and "Traceback" not in result.output


def test_replay_cli_refuses_an_unknown_split(drive_data, tiny_export):
    from streamdet.replay.cli import main

    result = CliRunner().invoke(main, ["--data", str(drive_data), "--export-dir", str(tiny_export), "--split", "nope"])
    assert result.exit_code != 0 and "nope" in result.output


def test_key_frames_interpolated_agree_with_the_trajectories(tiny_synth_data):
    from streamdet.replay.nuscenes_source import DatasetTables

    tables = DatasetTables(tiny_synth_data, "v1.0-synth")
    scene = tables.scene_names()[0]
    exact = load_ground_truth(tiny_synth_data, "v1.0-synth", scene)
    interpolated = load_ground_truth(tiny_synth_data, "v1.0-synth", scene, prefer_trajectories=False)
    assert exact.source == TRAJECTORIES and interpolated.source == INTERPOLATED
    samples = [tables.sample(t)["timestamp"] for t in tables.sample_tokens(tables.scene(scene))]
    t_us = 0.5 * (samples[0] + samples[1])  # between the two key frames
    a, b = exact.at(t_us), interpolated.at(t_us)
    # straight tracks (same velocity at both key frames) interpolate exactly; a turning one only approximately
    va, vb = exact.at(samples[0]).boxes[:, 7:9], exact.at(samples[1]).boxes[:, 7:9]
    straight = np.all(np.abs(va - vb) < 1e-9, axis=1)
    checked = 0
    for box, name in zip(b.boxes, b.names):
        d = np.linalg.norm(a.boxes[:, :2] - box[:2], axis=1)
        j = int(np.argmin(d))
        if straight[j]:
            assert d[j] < 1e-6 and a.names[j] == name
            np.testing.assert_allclose(a.boxes[j, 7:9], box[7:9], atol=1e-6)
            checked += 1
    assert checked > 0
    assert load_trajectories(tiny_synth_data, "no-such-scene") is None


@pytest.mark.parametrize("lidar_hz, sweeps", [(20.0, 10), (10.0, 5)])
def test_drive_from_tables_keeps_one_sweep_per_rotation(drive_data, lidar_hz, sweeps):
    from streamdet.data.nuscenes import CAMERA_CHANNELS
    from streamdet.replay.nuscenes_source import TRIGGER_MATCH_S, DatasetTables, load_drive

    tables = DatasetTables(drive_data, "v1.0-synth")
    drive = load_drive(tables, tables.scene_names()[0], (64, 36), lidar_hz=lidar_hz, camera_hz=12.0, camera_trigger="simultaneous")
    assert len(drive.sweeps) == sweeps
    assert drive.sweeps[0].start_s == pytest.approx(0.0) and all(s.point_time_s is not None for s in drive.sweeps)
    np.testing.assert_allclose(np.diff([s.end_s for s in drive.sweeps]), 1.0 / lidar_hz, atol=1e-6)
    # triggers from drive time 0; those before the cameras' first frame (the key frame's) deliver nothing
    triggers = np.arange(int(drive.sweeps[-1].end_s * 12.0 + 1e-9) + 1) / 12.0
    scene = tables.scene(tables.scene_names()[0])
    first_frame_s = min(int(r["timestamp"]) for c in CAMERA_CHANNELS for r in tables.channel_data(scene, c)) * 1e-6 - drive.t0_us * 1e-6
    assert len(drive.image_sets) == int(np.sum(triggers + TRIGGER_MATCH_S >= first_frame_s)) < len(triggers)
    assert all(s.recorded_s <= s.capture_s for s in drive.image_sets)  # never an image from the future
    assert all(im.shape == (36, 64, 3) for s in drive.image_sets for im in s.images.values())
    assert any("delivered nothing" in note and "held" not in note for note in drive.notes)  # 12 Hz cameras, as recorded


def test_drive_of_an_unknown_scene_is_refused(drive_data):
    from streamdet.replay.nuscenes_source import DatasetTables, load_drive

    with pytest.raises(ValueError, match="no-such-scene"):
        load_drive(DatasetTables(drive_data, "v1.0-synth"), "no-such-scene", None)


def test_replay_coalesces_slices_when_the_lane_falls_behind(drive_data, tiny_export, tmp_path):
    """At 1/50 of real time one slice worker cannot keep up: waiting slices of a quadrant run together, every
    slice is emitted or dropped, and the report and records say which ran together."""
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.2",
            "--mode", "streaming", "--time-scale", "0.02", "--slice-workers", "1", "--queue-size", "64",
            "--coalesce-slices", "2", "--out", str(tmp_path / "out")]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "up to 2 waiting slices coalesced per run" in result.output
    details = json.loads((tmp_path / "out" / "replay.json").read_text())
    summary = details["modes"]["streaming"]
    (rec,) = summary["recordings"]
    emitted = [s for s in rec["slices"] if not s["dropped"]]
    assert summary["slices_dropped"] == 0 and len(emitted) == summary["slices_total"]
    assert summary["slices_coalesced"] == sum(s["coalesced"] > 1 for s in emitted) > 0
    assert all(s["coalesced"] in (1, 2) for s in emitted)
    assert details["config"]["coalesce_slices"] == 2


def _linked_copy(src, dst):
    """The dataset with its tables copied (the tests edit them) and its data files hard-linked."""
    import os
    import shutil

    shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns("v1.0-*"))
    shutil.copytree(src / "v1.0-synth", dst / "v1.0-synth")
    return dst


@pytest.mark.parametrize(
    "table, field, value, match",
    [
        ("sample_data", "filename", "../../etc/hostname", r"field 'filename': file '\.\./\.\./etc/hostname' must be a relative path"),
        ("ego_pose", "rotation", [1.0, 0.0], r"'ego_pose'.*field 'rotation' must be a unit quaternion"),
        ("sample", "timestamp", "soon", r"'sample'.*field 'timestamp'"),
        ("sample_annotation", "size", {}, r"'sample_annotation'.*field 'size'"),
    ],
)
def test_the_player_reads_the_tables_through_the_checked_reader(tiny_synth_data, tmp_path, table, field, value, match):
    """A malformed row reaches the player as a ValueError naming table, row and field (data/nuscenes.py), never a
    KeyError or TypeError; a file name leaving the dataset is refused."""
    import json

    from streamdet.replay.nuscenes_source import DatasetTables, load_drive

    root = _linked_copy(tiny_synth_data, tmp_path / "ds")
    path = root / "v1.0-synth" / f"{table}.json"
    rows = json.loads(path.read_text())
    for row in rows:  # every row: whichever the player reads first is bad
        row[field] = value
    path.write_text(json.dumps(rows))
    with pytest.raises(ValueError, match=match):
        tables = DatasetTables(root, "v1.0-synth")
        scene = tables.scene_names()[0]
        load_drive(tables, scene, (64, 36), camera_trigger="simultaneous")
        load_ground_truth(root, "v1.0-synth", scene, prefer_trajectories=False, reader=tables.reader)


@pytest.mark.parametrize("per_quadrant", [False, True])
def test_warm_up_leaves_no_picture_for_the_first_slices(drive_data, tiny_export, per_quadrant):
    """The warm-up runs the drive's first image set, captured after the drive's first slices: it is dropped again, so
    slices before the first real update read no image (and the warm-up's runs are not counted)."""
    from streamdet.replay.nuscenes_source import DatasetTables, load_drive
    from streamdet.replay.run import warm_up
    from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

    tables = DatasetTables(drive_data, "v1.0-synth")
    with StreamingDetector(tiny_export, DetectorConfig(start_deg=180.0, clockwise=True)) as det:
        drive = load_drive(tables, tables.scene_names()[0], (det.image.width, det.image.height), max_seconds=0.2)
        assert drive.image_sets
        warm_up(det, drive, det.num_slices, per_quadrant=per_quadrant)
        assert det.image_timestamp is None and det.image_timestamps == (None,) * 4
        first = _first_slice(drive, det)
        assert det.detect_slice(first.points, first.slice_index, 0.01).image_timestamp is None
        det.update_images(drive.image_sets[0].images, timestamp=drive.image_sets[0].capture_s)
        assert det.image_timestamp == drive.image_sets[0].capture_s


def _first_slice(drive, det):
    from streamdet.replay.schedule import slice_sweep

    return slice_sweep(drive.sweeps[0], det.num_slices, det.config.start_deg, det.config.clockwise)[0]


def test_warm_up_runs_the_fallback_graph_too(drive_data, tiny_export, tiny_lidar_export):
    """The drive's first slices, with no image yet, run the LiDAR-only fallback where one is configured: the warm-up
    runs it once too, so that its slow first runs are not the drive's."""
    from streamdet.replay.nuscenes_source import DatasetTables, load_drive
    from streamdet.replay.run import warm_up
    from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
    from streamdet.runtime_ort.fallback import FALLBACK_GRAPH

    tables = DatasetTables(drive_data, "v1.0-synth")
    for fallback in (None, str(tiny_lidar_export)):
        config = DetectorConfig(start_deg=180.0, clockwise=True, fallback_export_dir=fallback)
        with StreamingDetector(tiny_export, config) as det:
            drive = load_drive(tables, tables.scene_names()[0], (det.image.width, det.image.height), max_seconds=0.2)
            with det.recording() as rec:
                warm_up(det, drive, det.num_slices)
            graphs = {run.graph for run in rec.runs}
            assert (FALLBACK_GRAPH in graphs) == (fallback is not None)
            assert det.image_timestamp is None and det.stats.summary() == {}
