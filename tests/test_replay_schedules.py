"""The replay with either image-lane schedule (LaneConfig.schedule): the staleness added by processing and the
image lane's CPU per rotation are recorded and reported, and the schedule is named."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.replay.record import ImageRecord, Recording, SliceRecord, staleness_by_recent_images


@pytest.fixture(scope="module")
def drive_data(tiny_drive_data):
    return tiny_drive_data  # one key frame with ten 20 Hz sweeps before it at 160x90 (conftest)


def _slice(image_capture_s: float, newest_capture_s: float, emitted: bool = True) -> SliceRecord:
    rec = SliceRecord(0, 0, 8, 0.1, 10, image_capture_s=image_capture_s, newest_capture_s=newest_capture_s)
    rec.emit_s = 0.2 if emitted else math.nan
    return rec


def test_staleness_is_the_newest_capture_by_scan_start_minus_the_fused_one():
    slices = (_slice(0.10, 0.15), _slice(0.15, 0.15), _slice(0.20, 0.15), _slice(math.nan, 0.15), _slice(0.1, 0.2, False))
    rec = Recording("streaming", "s", 1.0, slices, (), 1.0, 0.0, 0.0)
    np.testing.assert_allclose(rec.staleness_ms(), [50.0, 0.0, -50.0])  # no image, or not emitted: not counted
    assert math.isnan(rec.image_lane_cpu_s) and rec.to_dict()["image_lane_cpu_s"] is None


def _naive_by_recent_images(recordings, period_s, threshold_ms):
    out = {}
    for rec in recordings:
        for s in rec.slices:
            if not (s.emitted and math.isfinite(s.image_capture_s) and math.isfinite(s.newest_capture_s)):
                continue
            start = s.scan_end_s - period_s / s.num_slices
            n = sum(1 for i in rec.images if start - period_s <= i.release_s < start)
            stale, total = out.get(n, (0, 0))
            out[n] = (stale + ((s.newest_capture_s - s.image_capture_s) * 1e3 > threshold_ms), total + 1)
    return dict(sorted(out.items()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stale_slices_by_the_image_sets_of_the_rotation_before_match_a_naive_count(seed):
    rng = np.random.default_rng(seed)
    recordings = []
    for _ in range(2):
        slices = []
        for k in range(int(rng.integers(0, 60))):
            rec = _slice(float(rng.uniform(0, 1)), float(rng.uniform(0, 1)), emitted=bool(rng.random() > 0.1))
            rec.scan_end_s = 0.05 * (k + 1) / 8 + 0.1
            if rng.random() < 0.1:
                rec.image_capture_s = math.nan  # fused before the first image set: not counted
            slices.append(rec)
        releases = rng.uniform(0, 1, int(rng.integers(0, 40)))
        images = tuple(ImageRecord(i, float(t) - 0.01, release_s=float(t) if rng.random() > 0.1 else math.nan)
                       for i, t in enumerate(releases))  # fmt: skip
        recordings.append(Recording("streaming", "s", 1.0, tuple(slices), images, 1.0, 0.0, 0.0))
    for threshold in (0.0, 25.0, 200.0):
        assert staleness_by_recent_images(recordings, 0.05, threshold) == _naive_by_recent_images(recordings, 0.05, threshold)


def test_a_recording_read_back_from_its_dict_is_the_same_but_for_detections():
    s = _slice(0.1, 0.15)
    dropped = _slice(math.nan, math.nan, emitted=False)
    dropped.dropped = True
    images = (ImageRecord(0, 0.1, release_s=0.1, start_s=0.11, end_s=0.12, emit_s=0.12), ImageRecord(1, 0.2, superseded=True))
    rec = Recording("streaming", "d", 2.0, (s, dropped), images, 1.5, 0.01, 1.2, image_lane_cpu_s=0.4, rotations=30,
                    phase_lock={"quadrant_lifts": 3}, gc_pauses=None, slices_held=7, slice_runs_at_top_k=2)  # fmt: skip
    d = json.loads(json.dumps(rec.to_dict()))  # as replay.json holds it: nan as null
    back = Recording.from_dict(d)
    assert back.to_dict() == d
    assert back.slices[1].dropped and math.isnan(back.slices[1].emit_s) and back.images[1].superseded
    assert back.slices_held == 7 and back.slice_runs_at_top_k == 2
    old = {k: v for k, v in d.items()
           if k not in ("rotations", "phase_lock", "gc_pauses", "image_lane_cpu_s", "slices_held", "slice_runs_at_top_k")}
    assert Recording.from_dict(old).rotations == 0 and math.isnan(Recording.from_dict(old).image_lane_cpu_s)
    assert Recording.from_dict(old).slices_held == 0 and Recording.from_dict(old).slice_runs_at_top_k == 0
    newer = {**d, "a_later_field": 1, "slices": [{**x, "a_later_field": 2} for x in d["slices"]]}
    assert Recording.from_dict(newer).to_dict() == d  # keys a later version writes are ignored


@pytest.mark.parametrize("change, said", [
    (lambda d: d["slices"][0].update(emit_s="soon"), r"SliceRecord.emit_s must be a JSON float, got 'soon'"),
    (lambda d: d["slices"][0].update(dropped=1), r"SliceRecord.dropped must be a JSON bool, got 1"),
    (lambda d: d["images"][0].update(index=True), r"ImageRecord.index must be a JSON int, got True"),
    (lambda d: d.update(time_scale=[1]), r"Recording.time_scale must be a JSON float"),
    (lambda d: d.update(slices=5), r"'slices' must be a JSON list of records, got 5"),
    (lambda d: d["slices"].__setitem__(0, "x"), r"a SliceRecord record must be a JSON object, got 'x'"),
])  # fmt: skip
def test_a_recording_with_fields_of_the_wrong_type_is_named(change, said):
    rec = Recording("streaming", "d", 2.0, (_slice(0.1, 0.15),), (ImageRecord(0, 0.1),), 1.5, 0.01, 1.2)
    d = json.loads(json.dumps(rec.to_dict()))
    change(d)
    with pytest.raises(ValueError, match=said):
        Recording.from_dict(d)


def test_stale_slices_by_recent_images_count_the_rotation_before_the_scan_start_only():
    s = _slice(0.0, 0.1)  # staleness added 100 ms
    s.scan_end_s = 0.25625  # scan start 0.25 at 20 Hz x 8
    images = tuple(ImageRecord(i, t, release_s=t) for i, t in enumerate((0.19, 0.2, 0.22, 0.2499, 0.25, 0.3)))
    rec = Recording("streaming", "s", 1.0, (s,), images, 1.0, 0.0, 0.0)
    assert staleness_by_recent_images([rec], 0.05) == {3: (1, 1)}  # [0.2, 0.25): 0.2, 0.22, 0.2499
    assert staleness_by_recent_images([rec], 0.05, threshold_ms=100.0) == {3: (0, 1)}  # above, not at, the line
    assert staleness_by_recent_images([], 0.05) == {}
    for bad in (0, -0.05, math.nan, math.inf, "0.05", True):
        with pytest.raises(ValueError, match="period_s"):
            staleness_by_recent_images([rec], bad)


def test_the_image_lanes_cpu_share_is_the_runners_own_count_where_it_has_one():
    from streamdet.replay.record import ImageRecord
    from streamdet.replay.report import _cpu_share
    from streamdet.replay.run import ModeResult

    # the phase-locked lane charges frames encoded ahead and a frame's later lifts to no image set
    images = (ImageRecord(0, 0.0, cpu_s=0.1), ImageRecord(1, 0.1, cpu_s=0.1))
    own = Recording("streaming", "s", 1.0, (), images, 2.0, 0.0, 0.0, image_lane_cpu_s=0.6)
    sets_only = Recording("streaming", "s", 1.0, (), images, 2.0, 0.0, 0.0)  # no count of its own: the sets' sum
    assert _cpu_share(ModeResult((own, own), None, {}))["image_lane"] == pytest.approx(0.3)
    assert _cpu_share(ModeResult((sets_only,), None, {}))["image_lane"] == pytest.approx(0.1)
    assert _cpu_share(ModeResult((own, sets_only), None, {}))["image_lane"] == pytest.approx(0.1)  # not mixed


@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
def test_a_replay_reports_staleness_and_image_lane_cpu_for_each_schedule(drive_data, tiny_export, tmp_path, schedule):
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.3",
            "--mode", "streaming", "--schedule", schedule, "--json", str(tmp_path / "r.json"), "--out", str(tmp_path / "out")]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert f"image lane, schedule '{schedule}'" in result.output and "staleness added" in result.output
    assert "by image sets released in the rotation before the scan start" in result.output
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["config"]["schedule"] == schedule
    details = json.loads((tmp_path / "out" / "replay.json").read_text())["modes"]["streaming"]
    assert details["image_lane_cpu_ms_per_rotation"] > 0
    assert set(details["staleness_ms"]) == {"p50", "p95", "p99", "max"}
    (rec,) = details["recordings"]
    assert details["cpu_share"]["image_lane"] == pytest.approx(rec["image_lane_cpu_s"] / rec["wall_s"])
    assert (rec["phase_lock"] is None) == (schedule == "full")
    if schedule == "phase-locked":
        assert rec["phase_lock"]["quadrant_lifts"] + rec["phase_lock"]["full_updates"] > 0
    fused = [s for s in rec["slices"] if s["image_capture_s"] is not None and s["newest_capture_s"] is not None]
    assert fused  # (a slice scanned before the first image set has no newest capture: no staleness counted)
    for s in fused:  # the newest set released by the scan start, at or after the first set
        assert s["newest_capture_s"] <= s["scan_end_s"]


def _replay(drive_data, tiny_export, tmp_path, *options: str, bad: tuple[str, ...]):
    """streamdet-replay's streaming mode for 0.3 s with ``options``: (its output, its JSON's config, the output of the
    same run with ``bad`` options instead, which must fail)."""
    from streamdet.replay.cli import main

    args = ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.3",
            "--mode", "streaming", *options]  # fmt: skip
    result = CliRunner().invoke(main, [*args, "--json", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    failed = CliRunner().invoke(main, [*args, *bad])
    assert failed.exit_code != 0
    return result.output, json.loads((tmp_path / "r.json").read_text())["config"], failed.output


def test_a_replay_with_a_camera_delivery_delay_says_so_and_records_it(drive_data, tiny_export, tmp_path):
    output, config, bad = _replay(drive_data, tiny_export, tmp_path, "--camera-delivery-ms", "20", bad=("--camera-delivery-ms", "-5"))
    assert "delivered 20 ms after capture" in output
    assert config["camera_delivery_ms"] == 20.0
    assert "camera-delivery-ms" in bad


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_replay_with_a_niced_image_lane_says_so_and_records_it(drive_data, tiny_export, tmp_path):
    output, config, bad = _replay(drive_data, tiny_export, tmp_path, "--schedule", "phase-locked", "--image-lane-nice", "5",
                                  bad=("--image-lane-nice", "20"))  # fmt: skip
    assert "image lane at nice +5" in output
    assert config["image_lane_nice"] == 5
    assert "image-lane-nice" in bad


def test_a_replay_whose_image_lane_yields_to_slices_says_so_and_records_it(drive_data, tiny_export, tmp_path):
    output, config, bad = _replay(drive_data, tiny_export, tmp_path, "--schedule", "phase-locked", "--image-lane-yield", "2",
                                  bad=("--schedule", "full"))  # fmt: skip
    assert "image lane yields at 2 waiting slice(s)" in output
    assert config["image_lane_yield_slices"] == 2
    assert "--image-lane-yield 2 needs --schedule phase-locked" in bad  # the full schedule cannot hold back between quadrants


def test_a_replay_freezes_the_heap_by_default_and_reports_the_collectors_pauses(drive_data, tiny_export, tmp_path):
    output, config, bad = _replay(drive_data, tiny_export, tmp_path, "--no-freeze-heap", bad=("--freeze-heap", "--slices", "0"))
    assert "garbage collector (heap not frozen): full collections during the drives: streaming" in output
    assert config["freeze_heap"] is False
    rec = json.loads((tmp_path / "r.json").read_text())
    from streamdet.replay.run import ReplayConfig

    assert ReplayConfig(data=drive_data, export_dir=tiny_export).freeze_heap is True
    out = tmp_path / "out"
    from streamdet.replay.cli import main

    result = CliRunner().invoke(main, ["--data", str(drive_data), "--split", "all", "--export-dir", str(tiny_export),
                                       "--max-seconds", "0.2", "--mode", "streaming", "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "garbage collector (heap frozen at each drive's start)" in result.output
    played = json.loads((out / "replay.json").read_text())["modes"]["streaming"]["recordings"][0]
    assert set(played["gc_pauses"]) == {"gen0", "gen1", "gen2"} and rec["config"]["freeze_heap"] is False


def test_a_replay_with_its_own_image_lane_threads_says_so_and_records_it(drive_data, tiny_export, tmp_path):
    from streamdet.replay.run import ReplayConfig, open_detector

    output, config, bad = _replay(drive_data, tiny_export, tmp_path, "--image-lane-threads", "2", bad=("--image-lane-threads", "0"))
    assert "1 thread(s) per session (2 in the image lane's)" in output
    assert config["image_lane_threads"] == 2
    assert "image-lane-threads" in bad
    det = open_detector(ReplayConfig(data=drive_data, export_dir=tiny_export, image_lane_threads=2))
    assert det.config.image_lane_threads == 2 and det.config.slice_lane_threads == 1
    for threads in (0, 1.5, True):
        with pytest.raises(ValueError, match="image_lane_threads"):
            ReplayConfig(data=drive_data, export_dir=tiny_export, image_lane_threads=threads)


@pytest.mark.parametrize("time_scale, ok", [(0.01, False), (0.2, True), (1.0, True), (40.0, True), (100.0, False)])
def test_a_phase_locked_replay_needs_a_time_scale_that_gives_a_lidar_rate(tmp_path, time_scale, ok):
    """20 Hz over the time scale is the rate the lane is told; outside LIDAR_HZ_RANGE it is refused at the config,
    naming the time scales that fit, not minutes later by the lane."""
    from streamdet.replay.run import ReplayConfig
    from streamdet.runtime_ort.lanes import LaneConfig

    lanes = LaneConfig(schedule="phase-locked")
    make = lambda: ReplayConfig(data=tmp_path, export_dir=tmp_path, time_scale=time_scale, lanes=lanes)  # noqa: E731
    if ok:
        assert make().time_scale == time_scale
    else:
        with pytest.raises(ValueError, match=r"time scale .* outside 0.5..100 Hz .*use a time scale in 0.2..40 for a 20 Hz drive"):
            make()
