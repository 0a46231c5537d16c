"""Camera outages in a replay (replay/outages.py, streamdet-replay --camera-outage): parsing, what they remove from
a drive (against a naive filter), the camera names checked against the export, and a phase-locked replay in which a
camera out for the rest of the drive is timed out (--camera-timeout-ms) or fused on (0)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.replay import cli as replay_cli
from streamdet.replay.cost import synthetic_drive
from streamdet.replay.outages import CameraOutage, apply_outages, check_outage_cameras


@pytest.mark.parametrize("spec, want", [
    ("CAM_FRONT@3-8", CameraOutage("CAM_FRONT", 3.0, 8.0)),
    ("CAM_BACK@0.5-", CameraOutage("CAM_BACK", 0.5, math.inf)),
    (" CAM_1@0-1e1 ", CameraOutage("CAM_1", 0.0, 10.0)),
])  # fmt: skip
def test_an_outage_is_parsed_and_printed_back(spec, want):
    outage = CameraOutage.parse(spec)
    assert outage == want and CameraOutage.parse(str(outage)) == outage


@pytest.mark.parametrize("spec, message", [
    ("CAM_FRONT", "CAM@START-END"), ("CAM_FRONT@", "CAM@START-END"), ("@1-2", "CAM@START-END"),
    ("CAM_FRONT@x-2", "CAM@START-END"), ("CAM_FRONT@-1-2", "CAM@START-END"), ("CAM_FRONT@2-1", "end after it starts"),
    ("CAM_FRONT@1-1", "end after it starts"), ("CAM_FRONT@nan-2", "seconds >= 0"), ("CAM_FRONT@inf-", "end after it starts"),
])  # fmt: skip
def test_a_bad_outage_is_refused(spec, message):
    with pytest.raises(ValueError, match=message):
        CameraOutage.parse(spec)


@pytest.mark.parametrize("seed", range(3))
def test_outages_remove_exactly_the_frames_in_their_windows(seed):
    rng = np.random.default_rng(seed)
    drive = synthetic_drive(2.0, image_size=(8, 4))
    cams = list(drive.image_sets[0].images)
    outages = [CameraOutage(str(rng.choice(cams)), float(a), float(a + rng.uniform(0.1, 1.5))) for a in rng.uniform(0, 1.5, 3)]
    out = apply_outages(drive, outages)
    want = []
    for s in drive.image_sets:  # naive: every frame, every outage
        kept = [c for c in s.images if not any(o.camera == c and o.start_s <= s.capture_s < o.end_s for o in outages)]
        if kept:
            want.append((s.capture_s, kept))
    assert [(s.capture_s, list(s.images)) for s in out.image_sets] == want
    assert out.notes[-1].startswith("camera outages: ") and apply_outages(drive, []) is drive


def test_an_outage_that_takes_out_nothing_is_said():
    drive = synthetic_drive(0.5, image_size=(8, 4))
    cam = list(drive.image_sets[0].images)[0]
    out = apply_outages(drive, [CameraOutage(cam, 100.0, 200.0), CameraOutage(cam, 0.0)])
    n = sum(cam in s.images for s in drive.image_sets)
    last = max(s.capture_s for s in drive.image_sets)
    assert out.notes[-1] == (f"camera outages: {cam}@100-200 (no frame in it; the drive's images end at {last:.2f} s), "
                             f"{cam}@0- ({n} frames)")  # fmt: skip


def test_an_outage_of_an_unknown_camera_is_refused():
    with pytest.raises(ValueError, match=r"--camera-outage names \['CAM_X'\]"):
        check_outage_cameras([CameraOutage("CAM_X", 0.0)], ("CAM_FRONT", "CAM_BACK"))


@pytest.mark.parametrize("timeout_ms, timed_out", [("100", True), ("0", False)])
def test_a_phase_locked_replay_times_a_camera_out(tiny_drive_data, tiny_export, tmp_path, timeout_ms, timed_out):
    out = tmp_path / "out"
    args = ["--data", str(tiny_drive_data), "--split", "all", "--export-dir", str(tiny_export), "--mode", "streaming",
            "--schedule", "phase-locked", "--camera-outage", "CAM_FRONT@0.1-", "--camera-timeout-ms", timeout_ms,
            "--out", str(out)]  # fmt: skip
    result = CliRunner().invoke(replay_cli.main, args)
    assert result.exit_code == 0, result.output
    record = json.loads((out / "replay.json").read_text())
    assert record["config"]["camera_outages"] == ["CAM_FRONT@0.1-"]
    assert record["config"]["camera_timeout_s"] == (0.1 if timed_out else None)
    assert "camera outages: CAM_FRONT@0.1-" in (out / "report.md").read_text()
    text = json.dumps(record)
    assert ('"cameras_timed_out": 0' not in text) is timed_out


def test_an_outage_of_a_camera_the_export_lacks_is_one_line(tiny_drive_data, tiny_export, tmp_path):
    args = ["--data", str(tiny_drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.1",
            "--camera-outage", "CAM_X@0-1"]  # fmt: skip
    result = CliRunner().invoke(replay_cli.main, args)
    assert result.exit_code == 1 and "--camera-outage names ['CAM_X']" in result.output
