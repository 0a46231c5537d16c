"""StreamingRunner.submit_calibration: a calibration swap off the caller's thread, one at a time, a newer one replacing
one still waiting (a soak of the runtime found set_calibration spending a good part of a second in the caller's
thread)."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from streamdet.calibration.camera import CalibrationError
from streamdet.runtime_ort import CalibrationSuperseded, NoImageLaneError, RunnerClosed
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.export_settings import export_rig
from streamdet.runtime_ort.lanes import StreamingRunner

WAIT_S = 30.0


def _moved(rig, scale: float):
    focal = rig.cameras[0].K.copy()
    focal[:2, :2] *= scale
    return dataclasses.replace(rig, cameras=(dataclasses.replace(rig.cameras[0], K=focal), *rig.cameras[1:]))


@pytest.fixture
def det(tiny_export):
    d = StreamingDetector(tiny_export, DetectorConfig())
    yield d
    d.close()


def test_a_submitted_calibration_swaps_off_the_callers_thread(det):
    rig = _moved(export_rig(det.manifest, det.export_dir), 1.001)
    threads = []
    real = det.set_calibration
    det.set_calibration = lambda c, relift=True: threads.append(threading.current_thread()) or real(c, relift)
    with StreamingRunner(det) as runner:
        assert runner.submit_calibration(rig).result(WAIT_S) is None
    assert det.lut.calibration_sha256 == rig.sha256()
    assert threads and threads[0] is not threading.current_thread()


def test_a_newer_calibration_replaces_one_waiting(det):
    base = export_rig(det.manifest, det.export_dir)
    gate, started = threading.Event(), threading.Event()
    real = det.set_calibration

    def slow(c, relift=True):
        started.set()
        assert gate.wait(WAIT_S)
        return real(c, relift)

    det.set_calibration = slow
    with StreamingRunner(det) as runner:
        first = runner.submit_calibration(_moved(base, 1.001))
        assert started.wait(WAIT_S)
        waiting = runner.submit_calibration(_moved(base, 1.002))
        newest = runner.submit_calibration(_moved(base, 1.003))
        gate.set()
        assert first.result(WAIT_S) is None and newest.result(WAIT_S) is None
        with pytest.raises(CalibrationSuperseded):
            waiting.result(WAIT_S)
    assert det.lut.calibration_sha256 == _moved(base, 1.003).sha256()


def test_a_bad_calibration_fails_its_future_and_the_lut_stays(det, tmp_path):
    lut = det.lut
    with StreamingRunner(det) as runner:
        with pytest.raises(CalibrationError):
            runner.submit_calibration({"cameras": "none"})  # a dict is read here, in the caller's thread
        missing = runner.submit_calibration(tmp_path / "missing.json")  # a path is read in the lane
        with pytest.raises((CalibrationError, OSError)):
            missing.result(WAIT_S)
    assert det.lut is lut


def test_a_dict_is_read_at_submit_so_the_caller_may_reuse_it(det):
    base = export_rig(det.manifest, det.export_dir)
    doc = _moved(base, 1.001).to_dict()
    with StreamingRunner(det) as runner:
        future = runner.submit_calibration(doc)
        doc.clear()
        assert future.result(WAIT_S) is None
    assert det.lut.calibration_sha256 == _moved(base, 1.001).sha256()


def test_lidar_only_and_closed_runners_refuse(tiny_lidar_export, det):
    with StreamingDetector(tiny_lidar_export) as lidar, StreamingRunner(lidar) as runner:
        with pytest.raises(NoImageLaneError):
            runner.submit_calibration(export_rig(det.manifest, det.export_dir))
    runner = StreamingRunner(det)
    assert runner.close(WAIT_S)
    with pytest.raises(RunnerClosed):
        runner.submit_calibration(export_rig(det.manifest, det.export_dir))


def test_slices_keep_running_while_a_calibration_swaps(det):
    from streamdet.core.slicing import split_sweep
    from streamdet.data.sample import load_bundled_sample

    slices = split_sweep(load_bundled_sample().points, det.num_slices)
    with StreamingRunner(det) as runner:
        img = det.image
        runner.submit_images({c: np.full((img.height, img.width, 3), 90, np.uint8) for c in det.camera_names}, 0.0).result(WAIT_S)
        swap = runner.submit_calibration(_moved(export_rig(det.manifest, det.export_dir), 1.001))
        results = [runner.submit_slice(p, k, 0.01 * k).result(WAIT_S) for k, p in enumerate(slices)]
        assert swap.result(WAIT_S) is None
    assert len(results) == det.num_slices
