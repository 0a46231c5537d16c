"""The contracts issue 16 found unwritten, as decided and documented in the docstrings: timestamps, dtypes,
points outside the slice, buffer copies, burst dropping, close(timeout), config and input types, calibration
refusals and blind cameras, file permissions, and the one edge every command-line tool runs behind."""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.lut import BlindCameraWarning
from streamdet.calibration.perturb import perturb_rig
from streamdet.cli_utils import EXIT_INTERRUPTED, run_edge
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.lanes import LaneConfig, RunnerClosed, SliceDropped, StreamingRunner

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture(scope="module")
def det(tiny_export) -> StreamingDetector:
    return StreamingDetector(tiny_export)


def _images(det, sample):
    arr = sample.load_images((det.image.width, det.image.height))
    return {n: arr[sample.rig.names.index(n)] for n in det.camera_names}


# ---- timestamps --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, True, "1.0", 1j])
def test_a_timestamp_must_be_finite(det, sample, bad):
    pts = split_sweep(sample.points, 8)[0]
    with pytest.raises(ValueError, match="timestamp must be None or a finite number"):
        det.detect_slice(pts, 0, timestamp=bad)
    before = det.image_state
    with pytest.raises(ValueError, match="timestamp must be None or a finite number"):
        det.update_images(_images(det, sample), timestamp=bad)
    assert det.image_state is before  # a refusal changes no cache


def test_timestamps_may_go_backwards_and_none_is_the_call_time(det, sample):
    det.update_images(_images(det, sample), timestamp=5.0)
    det.update_images(_images(det, sample), timestamp=1.0)  # a stepped driver clock: still the newest set
    assert det.image_timestamp == 1.0
    t0 = time.monotonic()
    res = det.detect_slice(split_sweep(sample.points, 8)[1], 1)
    assert t0 <= res.timestamp <= time.monotonic()


# ---- dtypes and points outside the slice -------------------------------------------------------------------------
def test_detect_slice_takes_float32_only_and_detect_sweep_converts_real_numbers(det, sample):
    pts = split_sweep(sample.points, 8)[0]
    with pytest.raises(ValueError, match="points must be float32, got float64"):
        det.detect_slice(pts.astype(np.float64), 0)
    ref = det.detect_sweep(sample.points, timestamp=1.0)
    as64 = det.detect_sweep(sample.points.astype(np.float64), timestamp=1.0)
    assert np.array_equal(ref.boxes, as64.boxes)
    det.detect_sweep(np.round(sample.points).astype(np.int32), timestamp=1.0)
    for bad in (sample.points.astype(bool), sample.points.astype(complex), sample.points.astype(object)):
        with pytest.raises(ValueError, match="sweep must hold real numbers"):
            det.detect_sweep(bad)


def test_points_outside_the_slices_quadrant_are_counted(det, sample):
    slices = split_sweep(sample.points, 8)
    own, other = slices[0], slices[4]  # slice 4 of 8 lies in the opposite quadrant
    res = det.detect_slice(np.concatenate([own, other]), 0, timestamp=0.0)
    alone = det.detect_slice(own, 0, timestamp=0.0)
    assert res.num_outside_dropped == alone.num_outside_dropped + len(other)
    assert res.num_pillars == alone.num_pillars


# ---- the runner: copies, submit-time stamps, bursts, close ---------------------------------------------------------
class _Recorder:
    """A stand-in detector: records what each job was given, optionally waiting for `go` first."""

    uses_images = True

    def __init__(self, wait: bool = False) -> None:
        self.go = threading.Event()
        if not wait:
            self.go.set()
        self.calls: list[tuple[np.ndarray, int, float]] = []

    def detect_slice(self, points, slice_index, timestamp=None):
        assert self.go.wait(30)
        self.calls.append((points, slice_index, timestamp))
        return slice_index

    def update_images(self, images, timestamp=None):
        assert self.go.wait(30)
        self.calls.append((images, -1, timestamp))
        return timestamp


def test_submit_copies_the_buffers_and_stamps_the_submit_time():
    rec = _Recorder(wait=True)
    runner = StreamingRunner(rec, LaneConfig(max_in_flight=1, queue_size=4))
    buf = np.ones((3, 6), np.float32)
    image = np.zeros((2, 2, 3), np.uint8)
    t0 = time.monotonic()
    f = runner.submit_slice(buf, 0)
    g = runner.submit_images({"CAM": image})
    t1 = time.monotonic()
    buf[:] = 7  # the driver refills its buffers at once
    image[:] = 9
    time.sleep(0.05)
    rec.go.set()
    f.result(30), g.result(30)
    (points, _, stamp), (images, _, image_stamp) = sorted(rec.calls, key=lambda c: c[1], reverse=True)
    assert np.all(points == 1) and np.all(images["CAM"] == 0)
    assert t0 <= stamp <= t1 and t0 <= image_stamp <= t1  # submit time, not run time
    assert runner.close(timeout=30)


def test_a_burst_to_idle_workers_drops_only_slices_that_would_wait():
    rec = _Recorder(wait=True)
    runner = StreamingRunner(rec, LaneConfig(max_in_flight=2, queue_size=8))
    futures = [runner.submit_slice(np.zeros((1, 6), np.float32), k % 8) for k in range(20)]
    rec.go.set()
    outcome = []
    for f in futures:
        try:
            f.result(30)
            outcome.append("ok")
        except SliceDropped:
            outcome.append("dropped")
    assert outcome == ["ok"] * 2 + ["dropped"] * 10 + ["ok"] * 8  # the two the idle workers take are never dropped
    assert runner.slices_dropped == 10
    runner.close()


def test_close_with_a_timeout_cancels_what_has_not_started():
    rec = _Recorder(wait=True)
    runner = StreamingRunner(rec, LaneConfig(max_in_flight=1, queue_size=4))
    running = runner.submit_slice(np.zeros((1, 6), np.float32), 0)
    waiting = [runner.submit_slice(np.zeros((1, 6), np.float32), k) for k in (1, 2)]
    t0 = time.monotonic()
    assert runner.close(timeout=0.2) is False
    assert time.monotonic() - t0 < 5
    assert all(f.cancelled() for f in waiting)
    with pytest.raises(RunnerClosed):
        runner.submit_slice(np.zeros((1, 6), np.float32), 3)
    rec.go.set()
    assert running.result(30) == 0  # the job that had started still finishes
    with pytest.raises(ValueError, match="close\\(timeout=...\\)"):
        runner.close(timeout=-1)


@pytest.mark.parametrize(
    "kwargs", [{"max_in_flight": 1.5}, {"queue_size": "8"}, {"max_in_flight": True}, {"queue_size": 0}, {"max_in_flight": 10**6}]
)
def test_lane_config_names_itself(kwargs):
    with pytest.raises(ValueError, match=r"LaneConfig\.(max_in_flight|queue_size) must be an int in 1..1024"):
        LaneConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs,field",
    [({"image_lane_threads": -1}, "image_lane_threads"), ({"slice_lane_threads": 1.5}, "slice_lane_threads"),
     ({"start_deg": math.nan}, "start_deg"), ({"start_deg": 45}, "start_deg"), ({"score_threshold": 2.0}, "score_threshold"),
     ({"verify_sha256": 1}, "verify_sha256"), ({"providers": "CPUExecutionProvider"}, "providers"), ({"nms": {}}, "nms")],
)  # fmt: skip
def test_detector_config_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"DetectorConfig.{field}"):
        DetectorConfig(**kwargs)


# ---- images and calibration: refusals change nothing ---------------------------------------------------------------
@pytest.mark.parametrize("bad", [None, [], np.zeros((6, 72, 128, 3), np.uint8), "CAM_FRONT", 3])
def test_images_must_be_a_dict(det, bad):
    before = det.image_state
    with pytest.raises(ValueError, match="update_images takes a dict"):
        det.update_images(bad)
    assert det.image_state is before


def test_set_calibration_inputs(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    lut = det.lut
    for bad in (None, 3, np.zeros(3), [1, 2]):
        with pytest.raises(CalibrationError, match="set_calibration takes a Rig, a Lut"):
            det.set_calibration(bad)
    with pytest.raises(CalibrationError, match=r"aspect .* resizing would distort them"):
        det.set_calibration(sample.rig.resized(1200, 900))  # a 4:3 rig for a 16:9 export
    with pytest.raises(CalibrationError, match="do not match the export's"):
        det.set_calibration(sample.rig.without("CAM_BACK"))
    assert det.lut is lut  # every refusal kept the LUT in use
    doc = json.loads((ROOT / "data" / "nuscenes_sample" / "calibration.json").read_text())
    det.set_calibration(doc)  # a parsed calibration.json is accepted
    assert det.lut.calibration_sha256 == Rig.from_calibration_json(doc).sha256()


def test_a_camera_that_sees_no_voxel_is_a_warning_naming_it(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    cams = list(sample.rig.cameras)
    moved = cams[3].lidar2cam.copy()
    moved[:3, 3] -= moved[:3, :3] @ np.array([0.0, 0.0, 1000.0])  # the camera 1 km up: p_cam = R (p - up) + t
    cams[3] = dataclasses.replace(cams[3], lidar2cam=moved)
    rig = Rig(tuple(cams), sample.rig.lidar2ego, sample.rig.ego2global)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        det.set_calibration(rig)
    msgs = [str(w.message) for w in caught if issubclass(w.category, BlindCameraWarning)]
    assert msgs == [f"camera {cams[3].name} sees no voxel of the grid (0 LUT slots): its images will not reach the BEV"]
    assert det.lut.slots_per_camera()[cams[3].name] == 0


def test_manifest_json_has_the_permissions_of_the_graphs(tiny_export):
    assert (tiny_export / "manifest.json").stat().st_mode == (tiny_export / "slice_head.onnx").stat().st_mode


def test_streamdet_eval_refuses_a_ground_truth_without_boxes(tmp_path):
    from streamdet.evaluation.cli import main as eval_main

    empty = tmp_path / "gt.json"
    empty.write_text(json.dumps({"meta": {}, "results": {}}))
    result = CliRunner().invoke(eval_main, ["--gt", str(empty), "--results", str(empty)])
    assert result.exit_code != 0 and "holds no box" in result.output


# ---- the edge of every tool ----------------------------------------------------------------------------------------
def _tool(tmp_path, monkeypatch, body: str) -> str:
    """A throwaway module whose click command runs ``body``; returns its module name."""
    (tmp_path / "edge_tool.py").write_text(
        "import click\nfrom streamdet.runtime_ort.manifest import ManifestError\n"
        f"@click.command()\n@click.option('--x', type=int, default=0)\ndef main(x):\n    {body}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    import sys

    sys.modules.pop("edge_tool", None)
    return "edge_tool"


@pytest.mark.parametrize(
    "body,rc,line",
    [
        ("raise ManifestError('/e/manifest.json: bad field')", 1, "streamdet-x: error: /e/manifest.json: bad field\n"),
        ("open('/nonexistent/lut.npz')", 1, "streamdet-x: error: /nonexistent/lut.npz: No such file or directory\n"),
        ("b'\\xff'.decode('utf-8')", 1, "streamdet-x: error: cannot decode the input as utf-8 text at byte 0 (a binary or corrupted file?)\n"),
        ("raise click.ClickException('one line')", 1, "Error: one line\n"),
        ("raise KeyboardInterrupt", EXIT_INTERRUPTED, "streamdet-x: interrupted\n"),
        ("return None", 0, ""),
    ],
)
def test_run_edge_prints_one_line(tmp_path, monkeypatch, capsys, body, rc, line):
    assert run_edge(_tool(tmp_path, monkeypatch, body), "streamdet-x", args=[]) == rc
    assert capsys.readouterr().err == line


def test_run_edge_usage_error_and_bugs(tmp_path, monkeypatch, capsys):
    name = _tool(tmp_path, monkeypatch, "raise KeyError('a bug')")
    assert run_edge(name, "streamdet-x", args=["--x", "notanint"]) == 2  # click's usage error
    assert "Invalid value for '--x'" in capsys.readouterr().err
    with pytest.raises(KeyError):  # a bug keeps its traceback
        run_edge(name, "streamdet-x", args=[])


def test_run_edge_on_a_real_tool_with_a_broken_export(tiny_export, tmp_path, capsys):
    import shutil

    broken = tmp_path / "exp"
    shutil.copytree(tiny_export, broken)
    (broken / "slice_head.onnx").write_bytes(b"")
    rc = run_edge("streamdet.evaluation.run_cli", "streamdet-run", args=["--export-dir", str(broken), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "slice_head.onnx" in err and "sha256" in err


def test_every_console_script_runs_behind_the_edge():
    import importlib.util
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
        import tomli as tomllib

    import streamdet.cli_utils as cli_utils

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    tools = ["export", "bench", "run", "calib", "synth", "train", "eval", "study", "train-image", "bag", "replay"]
    assert sorted(f"streamdet-{t}" for t in tools) == sorted(scripts)  # a new tool goes behind the edge too
    for tool in tools:
        target = scripts[f"streamdet-{tool}"]
        tool = tool.replace("-", "_")
        assert target == f"streamdet.cli_utils:{tool}_main"
        entry = getattr(cli_utils, f"{tool}_main")
        module = entry.__doc__.split(": ", 1)[1].split(".main", 1)[0]
        assert importlib.util.find_spec(module) is not None, module


def test_streamdet_calib_warns_about_a_camera_turned_around(tiny_export, tmp_path):
    import shutil

    from streamdet.runtime_ort.calib_cli import main as calib_main

    exp = tmp_path / "exp"
    shutil.copytree(tiny_export, exp)
    doc = json.loads((ROOT / "data" / "nuscenes_sample" / "calibration.json").read_text())
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])  # 180 deg about the LiDAR's vertical axis
    cam = doc["cameras"][0]
    cam["lidar2cam"]["matrix"] = (np.array(cam["lidar2cam"]["matrix"]) @ turn).tolist()
    (tmp_path / "turned.json").write_text(json.dumps(doc))
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(tmp_path / "turned.json"), "--export-dir", str(exp)])
    assert result.exit_code == 0, result.output
    assert f"warning: camera {cam['name']} now sees other voxels than with the previous LUT" in result.output
    assert result.output.count("now sees other voxels") == 1
    again = CliRunner().invoke(calib_main, ["lut", "--calibration", str(tmp_path / "turned.json"), "--export-dir", str(exp)])
    assert again.exit_code == 0 and "now sees other voxels" not in again.output  # same calibration: no warning


def test_set_calibration_warns_about_a_camera_turned_around(tiny_export, sample):
    from streamdet.calibration.lut import CameraMovedWarning

    det = StreamingDetector(tiny_export)
    cams = list(sample.rig.cameras)
    cams[1] = dataclasses.replace(cams[1], lidar2cam=cams[1].lidar2cam @ np.diag([-1.0, -1.0, 1.0, 1.0]))  # 180 deg
    def moved_warnings(rig) -> list[str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            det.set_calibration(rig)
        return [str(w.message) for w in caught if issubclass(w.category, CameraMovedWarning)]

    assert moved_warnings(perturb_rig(sample.rig, 0.2, 0.02, seed=0)) == []  # an ordinary recalibration
    turned = moved_warnings(Rig(tuple(cams), sample.rig.lidar2ego, sample.rig.ego2global))
    assert len(turned) == 1 and turned[0].startswith(f"camera {cams[1].name} now sees other voxels")
    assert len(moved_warnings(sample.rig)) == 1  # and back


def test_an_oversized_calibration_file_is_refused_without_reading_it_whole(tmp_path):
    from streamdet.calibration.camera import MAX_CALIBRATION_BYTES

    big = tmp_path / "calibration.json"
    big.write_bytes(b" " * (MAX_CALIBRATION_BYTES + 1))
    with pytest.raises(CalibrationError, match="too large to be a calibration file"):
        Rig.from_calibration_json(big)
    ok = tmp_path / "ok.json"  # at the limit, padding with whitespace still parses
    doc = json.dumps(load_bundled_sample().rig.to_dict())
    ok.write_text(doc + " " * (MAX_CALIBRATION_BYTES - len(doc.encode())))
    assert Rig.from_calibration_json(ok) == Rig.from_calibration_json(json.loads(doc))
