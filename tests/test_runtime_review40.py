"""Review 40 (embedding the runtime in a vehicle process): onnxruntime failures in the per-camera lifts raise
GraphRunError (M1), calibration.json's two forms of one transform must agree and a camera's lidar2img that is not
K @ lidar2cam is said (M2), recordings hold the term and tail runs (L1), a sweep's points without an azimuth are
counted (L2), lanes on different clocks are said once (L3), a slice-index column that is not its slice's feature is
said once (L4a), and frozen_heap nests (L4b)."""

from __future__ import annotations

import copy
import dataclasses
import gc
import json
import logging
import re
import threading
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner
from onnxruntime.capi import onnxruntime_pybind11_state as ort_state

from streamdet.calibration.camera import TRANSFORM_FORMS_ATOL, CalibrationError, Rig
from streamdet.core.slicing import feature_index, split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.export.cli import main as export_main
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.camera_terms import TAIL_GRAPH, TERM_GRAPH
from streamdet.runtime_ort.detector import DetectorConfig, GraphRunError, StreamingDetector
from streamdet.runtime_ort.fallback import CLOCKS_APART_S, IMPLAUSIBLE_IMAGE_AGE_S
from streamdet.runtime_ort.heap import frozen_heap
from streamdet.runtime_ort.lifter_split import first_conv, term_graph
from streamdet.runtime_ort.sessions import ort_session
from streamdet.training.checkpoint import save_weights

SAMPLE_CALIBRATION = Path(__file__).resolve().parents[1] / "data" / "nuscenes_sample" / "calibration.json"
DETECTOR_LOG = "streamdet.runtime_ort.detector"
CAMERA_LOG = "streamdet.calibration.camera"


@pytest.fixture(scope="module")
def flat_export(tmp_path_factory) -> Path:
    """A tiny flat-lifter export (fp32, seeded untrained weights): its image updates run per-camera terms."""
    preset = dataclasses.replace(get_preset("tiny"), lifter=dataclasses.replace(get_preset("tiny").lifter, form="flat"))
    torch.manual_seed(3)
    root = tmp_path_factory.mktemp("review40")
    save_weights(root / "flat.pt", preset, build_detector(preset).eval())
    out = root / "flat"
    result = CliRunner().invoke(export_main, ["--checkpoint", str(root / "flat.pt"), "--slices", "8", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _images(det: StreamingDetector, sample) -> dict[str, np.ndarray]:
    img = det.image
    return dict(zip(sample.rig.names, sample.load_images((img.width, img.height))))


class _Failing:
    """An onnxruntime session whose runs fail as a CUDA out-of-memory does: onnxruntime's own Fail."""

    def __init__(self, real) -> None:
        self.real = real

    def run(self, *args, **kwargs):
        raise ort_state.Fail("[ONNXRuntimeError] : 1 : FAIL : simulated CUDA failure: out of memory")

    run_with_ort_values = run

    def __getattr__(self, name):
        return getattr(self.real, name)


# ---- M1: the per-camera lifts' failures are GraphRunError ----------------------------------------------------------

@pytest.mark.parametrize("attr, graph", [("_term_graph", TERM_GRAPH), ("_tail", TAIL_GRAPH)])
@pytest.mark.parametrize("quadrants", [None, [1]], ids=["full", "quadrant"])
def test_a_failing_term_or_tail_run_raises_graph_run_error(flat_export, sample, attr, graph, quadrants):
    with StreamingDetector(flat_export, DetectorConfig(camera_terms=True)) as det:
        images = _images(det, sample)
        real = getattr(det._terms, attr)
        setattr(det._terms, attr, _Failing(real))
        try:
            with pytest.raises(GraphRunError) as info:
                det.update_images(images, timestamp=1.0, quadrants=quadrants)
        finally:
            setattr(det._terms, attr, real)
        # GraphSession.run's words: the graph, "onnxruntime failed", onnxruntime's message without its prefix
        assert str(info.value).startswith(f"{graph} (volumetric_lifter split")
        assert str(info.value).endswith(": onnxruntime failed: simulated CUDA failure: out of memory")
        assert det.image_state is None  # nothing installed; the next update works
        assert not det.update_images(images, timestamp=2.0, quadrants=quadrants).superseded


def test_graph_session_and_terms_share_the_message(flat_export, sample):
    with StreamingDetector(flat_export, DetectorConfig(camera_terms=True)) as det:
        images = _images(det, sample)
        session = det._sessions["image_encoder"]
        real = session.session
        session.session = _Failing(real)
        try:
            with pytest.raises(GraphRunError, match=r"^image_encoder\.onnx: onnxruntime failed: simulated CUDA failure: out of memory$"):
                det.update_images(images, timestamp=1.0)
        finally:
            session.session = real


# ---- L1: recordings hold the term and tail runs -------------------------------------------------------------------

def test_a_recording_holds_the_term_and_tail_runs_under_their_own_names(flat_export, sample):
    with StreamingDetector(flat_export, DetectorConfig(camera_terms=True)) as det:
        images = _images(det, sample)
        det.stats.reset()
        with det.recording() as rec:
            det.update_images(images, timestamp=0.0)
            det.update_images(images, timestamp=0.1, quadrants=[2])  # new arrays: its cameras' terms again
        counts = {name: v["count"] for name, v in det.stats.summary().items()}
        assert 0 < len(rec.of(TERM_GRAPH)) <= counts["lifter_partial"]  # a camera that reads no cell runs none
        assert len(rec.of(TAIL_GRAPH)) == counts["lifter_tail"] == 5  # four quadrants, then one
        assert rec.of("volumetric_lifter") == []
        names = [r.graph for r in rec.runs]
        assert names.index("image_encoder") < names.index(TERM_GRAPH) < names.index(TAIL_GRAPH)

        # the recorded feeds are the runs': the tail's through a tail session, the term's through the dense term graph
        for run in rec.of(TAIL_GRAPH):
            (again,) = det._terms._tail.run(None, run.feeds)
            np.testing.assert_array_equal(again, run.outputs[0])
        lifter = onnx.load(str(flat_export / det.manifest.graph("volumetric_lifter", "fp32").file))
        _, weight, _ = first_conv(lifter)
        heights = int(det.lut.index.shape[2])
        dense = ort_session(term_graph(weight, det._terms.channels, det._terms.feature_hw, heights, sparse=False).SerializeToString())
        for run in rec.of(TERM_GRAPH):
            assert set(run.feeds) == {"features", "slots", "weights"}
            (again,) = dense.run(None, run.feeds)
            np.testing.assert_allclose(again, run.outputs[0], rtol=1e-4, atol=1e-4)  # sparse or dense: float order
        with det.recording() as after:  # a block opened later records none of them
            pass
        assert len(after) == 0


def test_without_terms_a_recording_is_unchanged(flat_export, sample):
    with StreamingDetector(flat_export, DetectorConfig(camera_terms=False)) as det:
        with det.recording() as rec:
            det.update_images(_images(det, sample), timestamp=0.0)
        assert [r.graph for r in rec.runs] == ["image_encoder", "volumetric_lifter"]


# ---- L2: sweep points without an azimuth are counted --------------------------------------------------------------

def test_sweep_points_with_nan_x_or_y_are_counted_in_the_first_slice(flat_export, sample):
    sweep = np.array(sample.points, dtype=np.float32)
    n = len(sweep)
    nan_x, nan_y, nan_z, inf_x = (np.arange(k, n, 97)[:50] for k in (0, 1, 2, 3))
    sweep[nan_x, 0] = np.nan
    sweep[nan_y, 1] = np.nan
    sweep[nan_z, 2] = np.nan
    sweep[inf_x, 0] = np.inf  # has an azimuth: in its slice, counted there
    with StreamingDetector(flat_export) as det:
        clean = det.detect_sweep_slices(np.delete(sweep, np.r_[nan_x, nan_y], axis=0), timestamp=0.0)
        got = det.detect_sweep_slices(sweep, timestamp=0.0)
    assert sum(r.num_points for r in got.slices) == n - 100
    assert sum(r.num_nonfinite_dropped for r in got.slices) == 200
    assert got.slices[0].num_nonfinite_dropped == clean.slices[0].num_nonfinite_dropped + 100
    assert [r.num_nonfinite_dropped for r in got.slices[1:]] == [r.num_nonfinite_dropped for r in clean.slices[1:]]


# ---- L3: lanes on different clocks are said once ------------------------------------------------------------------

def _clock_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "same clock" in r.getMessage()]


@pytest.mark.parametrize("image_ts, slice_ts", [
    (1_699_929_865.25, 4_321.5),  # images at header stamps (epoch), slices timestamp=None (time.monotonic())
    (4_321.5, 1_699_929_865.25),  # the other way round
    (0.0, 1.7e18),  # slices in nanoseconds, images in seconds
], ids=["image-epoch", "slice-epoch", "ns-vs-s"])
def test_lanes_on_different_clocks_are_said_once(flat_export, sample, caplog, image_ts, slice_ts):
    slices = split_sweep(sample.points, 8)
    with StreamingDetector(flat_export) as det:
        det.update_images(_images(det, sample), timestamp=image_ts)
        with caplog.at_level(logging.WARNING, logger=DETECTOR_LOG):
            for k in (0, 1, 2):
                res = det.detect_slice(slices[k], k, timestamp=slice_ts)
        assert res.image_age_s == slice_ts - image_ts
    said = _clock_warnings(caplog)
    assert len(said) == 1
    assert f"{slice_ts:.17g}" in said[0] and f"{image_ts:.17g}" in said[0] and "in seconds" in said[0]


def test_plausible_image_ages_are_not_said(flat_export, sample, caplog):
    slices = split_sweep(sample.points, 8)
    with StreamingDetector(flat_export) as det:
        det.update_images(_images(det, sample), timestamp=100.0)
        with caplog.at_level(logging.WARNING, logger=DETECTOR_LOG):
            # a frame newer than the scan by under CLOCKS_APART_S, an image lane stalled for minutes
            for k, ts in enumerate((100.0 - 0.9 * CLOCKS_APART_S, 100.05, 100.0 + 0.9 * IMPLAUSIBLE_IMAGE_AGE_S)):
                det.detect_slice(slices[k], k, timestamp=ts)
    assert _clock_warnings(caplog) == []


# ---- L4a: a slice-index column that is not its slice's feature ----------------------------------------------------

def _index_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "slice-index column" in r.getMessage()]


def test_a_slice_index_column_numbered_in_scan_order_is_said_once(flat_export, sample, caplog):
    config = DetectorConfig(start_deg=180.0, clockwise=True)  # nuScenes' layout: features 3, 2, 1, 0, 7, 6, 5, 4
    slices = split_sweep(sample.points, 8, 180.0, clockwise=True)
    with StreamingDetector(flat_export, config) as det:
        with caplog.at_level(logging.WARNING, logger=DETECTOR_LOG):
            for k, pts in enumerate(slices):  # as split_sweep numbers them: nothing to say
                det.detect_slice(pts, k, timestamp=0.0)
            assert _index_warnings(caplog) == []
            for k in (1, 2):
                wrong = slices[k].copy()
                wrong[:, 5] = k  # the scan order, not the sector's feature
                det.detect_slice(wrong, k, timestamp=0.0)
    said = _index_warnings(caplog)
    assert len(said) == 1
    want = feature_index(1, 8, 180.0, True)
    assert want != 1 and "slice 1 of 8 has 1 in its slice-index column" in said[0] and f"being {want}" in said[0]


def test_a_coalesced_run_checks_each_slice(flat_export, sample, caplog):
    slices = split_sweep(sample.points, 8)
    with StreamingDetector(flat_export) as det:
        with caplog.at_level(logging.WARNING, logger=DETECTOR_LOG):
            det.detect_slices((slices[0], slices[1]), (0, 1), (0.0, 0.0))
            assert _index_warnings(caplog) == []
            late = slices[1].copy()
            late[-1, 5] = 0  # its last point numbered as the slice before
            det.detect_slices((slices[0], late), (0, 1), (0.0, 0.0))
    assert len(_index_warnings(caplog)) == 1


# ---- L4b: frozen_heap nests ---------------------------------------------------------------------------------------

def test_an_inner_frozen_heap_leaves_the_outer_frozen():
    assert gc.get_freeze_count() == 0
    with frozen_heap():
        outer = gc.get_freeze_count()
        with frozen_heap():
            with frozen_heap(enabled=False):
                pass
        assert gc.get_freeze_count() >= outer > 0  # the inner exit thawed nothing
        with pytest.raises(RuntimeError, match="inner"):
            with frozen_heap():
                raise RuntimeError("inner")
        assert gc.get_freeze_count() >= outer
    assert gc.get_freeze_count() == 0


def test_blocks_overlapping_in_threads_thaw_with_the_last():
    assert gc.get_freeze_count() == 0
    entered, leave, counts = threading.Event(), threading.Event(), []

    def other() -> None:
        with frozen_heap():
            entered.set()
            leave.wait(10)
        counts.append(gc.get_freeze_count())

    with frozen_heap():
        worker = threading.Thread(target=other)
        worker.start()
        assert entered.wait(10)
    assert gc.get_freeze_count() > 0  # the thread's block is still open
    leave.set()
    worker.join(10)
    assert counts == [0] and gc.get_freeze_count() == 0

    def many() -> None:
        for _ in range(20):
            with frozen_heap():
                with frozen_heap():
                    pass

    workers = [threading.Thread(target=many) for _ in range(4)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(60)
    assert gc.get_freeze_count() == 0


# ---- M2: calibration.json ---------------------------------------------------------------------------------------

@pytest.fixture
def doc() -> dict:
    return json.loads(SAMPLE_CALIBRATION.read_text())


def test_the_sample_loads_without_a_word(doc, caplog):
    with caplog.at_level(logging.WARNING, logger=CAMERA_LOG):
        rig = Rig.from_calibration_json(doc)
        Rig.from_calibration_json(SAMPLE_CALIBRATION)
    assert len(rig) == 6 and caplog.records == []


@pytest.mark.parametrize("path, key, value, at", [
    (("cameras", 0, "lidar2cam"), "rotation_wxyz", [0.0, 1.0, 0.0, 0.0], "cameras[0].lidar2cam"),  # the review's edit
    (("lidar", "sensor2ego"), "translation", [0.9437, 0.0, 1.8402 + 0.01], "lidar.sensor2ego"),  # 1 cm up, the matrix not
    (("lidar", "ego2global"), "rotation_wxyz", [1.0, 0.0, 0.0, 0.0], "lidar.ego2global"),
])
def test_a_transform_whose_two_forms_disagree_is_refused(doc, path, key, value, at):
    bad = copy.deepcopy(doc)
    entry = bad
    for p in path:
        entry = entry[p]
    entry[key] = value
    pattern = rf"^calibration: {re.escape(at)}: matrix and {key} disagree \(max \|diff\| [0-9.e+-]+, over {TRANSFORM_FORMS_ATOL:g}"
    with pytest.raises(CalibrationError, match=pattern):
        Rig.from_calibration_json(bad)


def test_forms_that_agree_to_float32_rounding_are_read(doc):
    ok = copy.deepcopy(doc)
    pose = ok["lidar"]["ego2global"]
    big = [654_321.123456, 5_432_109.87654, 12.5]  # a UTM pose: float32 rounds these by centimetres
    pose["translation"] = big
    pose["matrix"] = [row[:3] + [float(np.float32(t))] for row, t in zip(pose["matrix"][:3], big)] + [pose["matrix"][3]]
    rig = Rig.from_calibration_json(ok)
    np.testing.assert_array_equal(rig.ego2global[:3, 3], np.float32(big).astype(np.float64))  # the matrix is read
    del ok["lidar"]["ego2global"]["translation"]  # a rotation alone beside the matrix: compared too, and agrees
    Rig.from_calibration_json(ok)


def test_a_lidar2img_that_is_not_k_times_lidar2cam_is_said_once(doc, caplog):
    edited = copy.deepcopy(doc)
    edited["cameras"][2]["lidar2img"]["matrix"][0][3] += 123.25  # an edit made in the field that is not read
    rig = Rig.from_calibration_json(doc)
    with caplog.at_level(logging.WARNING, logger=CAMERA_LOG):
        assert Rig.from_calibration_json(edited) == rig  # read as before: lidar2img is not the projection
        Rig.from_calibration_json(edited)  # republished: said once
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1
    name = doc["cameras"][2]["name"]
    assert f"cameras[2].lidar2img of camera {name} differs from K @ lidar2cam by up to 123.25" in said[0]

    rounded = copy.deepcopy(doc)  # float32 rounding of the whole matrix: nothing to say
    rounded["cameras"][1]["lidar2img"]["matrix"] = np.float32(rounded["cameras"][1]["lidar2img"]["matrix"]).astype(float).tolist()
    odd = copy.deepcopy(doc)  # not a matrix at all: informational, not compared
    odd["cameras"][3]["lidar2img"] = {"note": "see K and lidar2cam"}
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=CAMERA_LOG):
        Rig.from_calibration_json(rounded)
        Rig.from_calibration_json(odd)
    assert caplog.records == []
