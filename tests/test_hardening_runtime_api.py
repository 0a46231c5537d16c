"""The runtime API against a hostile or careless caller (audit 3, helper report on runtime_ort): feature maps with NaN
or refilled in place, configs past any real rig (start azimuth, thread counts), point arrays past any sensor or
masked, huge integer timestamps, graphs whose outputs are no slice graph's, warm_up over real images, use after
close, and calibration files that are FIFOs. Each refusal is a named error and changes no cached state."""

from __future__ import annotations

import logging
import math
import os
import shutil

import numpy as np
import pytest

from streamdet.calibration.camera import CalibrationError
from streamdet.core.points import MAX_SLICE_POINTS, MAX_SWEEP_POINTS
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorClosed, DetectorConfig, StreamingDetector
from streamdet.runtime_ort.detector_config import MAX_LANE_THREADS
from streamdet.runtime_ort.sessions import GraphRunError


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture
def det(tiny_export) -> StreamingDetector:
    return StreamingDetector(tiny_export)


def _images(det, sample):
    arr = sample.load_images((det.image.width, det.image.height))
    return {n: arr[sample.rig.names.index(n)] for n in det.camera_names}



# ---- feature maps handed to update_images ------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_feature_maps_are_refused(det, sample, bad):
    images = _images(det, sample)
    name = det.camera_names[0]
    maps = {name: np.array(det.encode_images({name: images[name]})[name])}  # the caller's own (writable) copy
    maps[name][0, 0, 0] = bad
    det.update_images(images, timestamp=1.0)
    before = det.image_state
    with pytest.raises(ValueError, match=rf"encoded\[{name!r}\] holds NaN or infinite values"):
        det.update_images(images, timestamp=2.0, encoded=maps)
    assert det.image_state is before


def test_a_feature_map_refilled_in_place_is_not_taken_for_the_old_frame(tiny_export, sample):
    """Per-camera terms are kept by map identity: a caller's buffer refilled for the next frame must not give the
    previous frame's BEV."""
    det = StreamingDetector(tiny_export, DetectorConfig(camera_terms=None))
    images = _images(det, sample)
    other = {n: np.ascontiguousarray(a[::-1]) for n, a in images.items()}  # another frame: upside down
    name = det.camera_names[0]
    buf = np.array(det.encode_images({name: images[name]})[name])
    det.update_images({name: images[name]}, timestamp=1.0, encoded={name: buf})
    buf[...] = det.encode_images({name: other[name]})[name]  # refilled in place
    det.update_images({name: other[name]}, timestamp=2.0, encoded={name: buf})
    got = [None if s is None else s.bev for s in det.image_state.quadrants]  # None: a quadrant the camera misses
    det.update_images({name: other[name]}, timestamp=3.0)  # encoded here: the truth
    want = [None if s is None else s.bev for s in det.image_state.quadrants]
    assert [g is None for g in got] == [w is None for w in want] and any(w is not None for w in want)
    for g, w in zip(got, want):
        if w is not None:
            np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)


def test_encode_images_maps_are_read_only_and_kept_by_identity(det, sample):
    images = _images(det, sample)
    maps = det.encode_images(images)
    assert all(not f.flags.writeable for f in maps.values())
    with pytest.raises(ValueError):
        next(iter(maps.values())).setflags(write=True)  # a view of a read-only array stays read-only
    assert det.prepare_terms(maps) >= (1 if det.camera_terms else 0)


# ---- configs past any rig ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("start_deg", [1e300, 1e17 * 90, 360, 450.0, -450])
def test_a_start_azimuth_outside_one_turn_is_refused(start_deg):
    with pytest.raises(ValueError, match=r"start_deg must be a multiple of 90 degrees in \[-360, 360\)"):
        DetectorConfig(start_deg=start_deg)


@pytest.mark.parametrize("start_deg", [-360, -90, 0, 90.0, 270])
def test_start_azimuths_within_one_turn_are_fine(start_deg):
    assert DetectorConfig(start_deg=start_deg).start_deg == start_deg


@pytest.mark.parametrize("threads", [MAX_LANE_THREADS + 1, 10**12, -1])
def test_thread_counts_are_bounded(threads):
    with pytest.raises(ValueError, match=rf"slice_lane_threads must be an int in 0..{MAX_LANE_THREADS}"):
        DetectorConfig(slice_lane_threads=threads)


def test_numpy_thread_counts_become_ints():
    config = DetectorConfig(image_lane_threads=np.int64(2), slice_lane_threads=np.uint8(0))
    assert type(config.image_lane_threads) is int and type(config.slice_lane_threads) is int


# ---- point arrays past any sensor --------------------------------------------------------------------------------
def test_a_slice_over_the_point_cap_is_refused_before_any_work(det):
    huge = np.broadcast_to(np.zeros((1, 6), np.float32), (MAX_SLICE_POINTS + 1, 6))  # 24 bytes declaring 100 MB
    with pytest.raises(ValueError, match=rf"a slice run holds {MAX_SLICE_POINTS + 1} points, over the {MAX_SLICE_POINTS}"):
        det.detect_slice(huge, 0, timestamp=0.0)
    half = np.broadcast_to(np.zeros((1, 6), np.float32), (MAX_SLICE_POINTS // 2 + 1, 6))
    with pytest.raises(ValueError, match="a slice run holds"):
        det.detect_slices([half, half], [0, 1], [0.0, 0.0])  # the run's points together


def test_a_sweep_over_the_point_cap_is_refused(det):
    huge = np.broadcast_to(np.zeros((1, 5), np.float32), (MAX_SWEEP_POINTS + 1, 5))
    with pytest.raises(ValueError, match=rf"sweep holds {MAX_SWEEP_POINTS + 1} points, over the {MAX_SWEEP_POINTS}"):
        det.detect_sweep(huge, timestamp=0.0)


def test_masked_points_are_refused(det, sample):
    pts = split_sweep(sample.points, 8)[0]
    masked = np.ma.masked_array(pts, mask=np.zeros_like(pts, bool))
    with pytest.raises(ValueError, match="masked array"):
        det.detect_slice(masked, 0, timestamp=0.0)
    with pytest.raises(ValueError, match="masked array"):
        det.detect_sweep(np.ma.masked_array(sample.points), timestamp=0.0)


# ---- timestamps past float range ---------------------------------------------------------------------------------
def test_integer_timestamps_past_float_range_are_value_errors(det, sample):
    pts = split_sweep(sample.points, 8)[0]
    with pytest.raises(ValueError, match="timestamp must be None or a finite number of seconds, got an integer of 401 digits"):
        det.detect_slice(pts, 0, timestamp=10**400)
    images = _images(det, sample)
    name = det.camera_names[0]
    with pytest.raises(ValueError, match=rf"camera_timestamps\[{name!r}\] must be a finite number"):
        det.update_images(images, timestamp=0.0, camera_timestamps={name: 10**400})
    assert det.detect_slice(pts, 0, timestamp=10**300).timestamp == 1e300  # within range: fine


# ---- graph outputs that no slice graph gives ---------------------------------------------------------------------
def _patch_slice_outputs(det, monkeypatch, change):
    real = det._run_graph

    def run(name, feeds):
        outs = real(name, feeds)
        return change(*outs) if name == "slice_head" else outs

    monkeypatch.setattr(det, "_run_graph", run)


def test_non_finite_output_rows_are_counted_and_logged_once(det, sample, monkeypatch, caplog):
    def poison(boxes, scores, labels):
        boxes, scores = boxes.copy(), scores.copy()
        boxes[0, :3, 0] = np.nan
        scores[0, 3] = np.inf
        return [boxes, scores, labels]

    _patch_slice_outputs(det, monkeypatch, poison)
    pts = split_sweep(sample.points, 8)
    with caplog.at_level(logging.WARNING, logger="streamdet.runtime_ort.detector"):
        results = [det.detect_slice(pts[k], k, timestamp=0.0) for k in (0, 1)]
    assert [r.num_nonfinite_outputs for r in results] == [4, 4]
    assert sum("num_nonfinite_outputs" in m for m in caplog.messages) == 1
    assert all(np.isfinite(r.detections.boxes).all() for r in results)


@pytest.mark.parametrize("change, said", [
    (lambda b, s, lab: [b, s, np.where(np.arange(lab.size).reshape(lab.shape) == 0, 12, lab)], r"det_labels holds 12, outside the 10 classes"),
    (lambda b, s, lab: [b, s, np.full_like(lab, -1)], r"det_labels holds -1"),
    (lambda b, s, lab: [b, s * 1e6 + 2.0, lab], r"det_scores holds .*outside \[0, 1\]"),
])  # fmt: skip
def test_outputs_outside_the_classes_or_scores_name_the_graph(det, sample, monkeypatch, change, said):
    _patch_slice_outputs(det, monkeypatch, change)
    with pytest.raises(GraphRunError, match=rf"slice_head.onnx: {said}"):
        det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)


def test_a_non_finite_image_bev_is_never_cached(det, sample, monkeypatch):
    det.update_images(_images(det, sample), timestamp=1.0)
    before = det.image_state
    real = det._lift_quadrants

    def nan_lift(*a, **k):
        bevs = [b.copy() for b in real(*a, **k)]
        bevs[-1][0, 0, 0, 0] = np.nan
        return bevs

    monkeypatch.setattr(det, "_lift_quadrants", nan_lift)
    with pytest.raises(GraphRunError, match=r"non-finite image BEV for quadrant 3 .* the cached BEV is kept"):
        det.update_images(_images(det, sample), timestamp=2.0)
    assert det.image_state is before


# ---- lifetime ----------------------------------------------------------------------------------------------------
def test_warm_up_refuses_to_wipe_real_images(det, sample):
    det.update_images(_images(det, sample), timestamp=5.0)
    before = det.image_state
    with pytest.raises(ValueError, match="warm_up runs before the first update_images"):
        det.warm_up()
    assert det.image_state is before


def test_close_releases_the_sessions(tiny_export, sample):
    with StreamingDetector(tiny_export) as det:
        det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)
    assert det.sessions == {} and det.close() == []
    with pytest.raises(DetectorClosed, match="the detector was closed"):
        det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)
    with pytest.raises(DetectorClosed):
        det.update_images(_images(det, sample), timestamp=0.0)


# ---- calibration files that would block --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["calibration.json", "lut.npz"])
def test_set_calibration_from_a_fifo_never_blocks(det, tmp_path, alarm, name):
    path = tmp_path / name
    os.mkfifo(path)
    before = det.lut
    with pytest.raises(CalibrationError, match="not a regular file"):
        det.set_calibration(path)
    assert det.lut is before


def test_profiles_go_to_the_profile_dir_never_the_export(tiny_export, sample, tmp_path):
    before = sorted(p.name for p in tiny_export.iterdir())
    det = StreamingDetector(tiny_export, DetectorConfig(enable_profiling=True, profile_dir=tmp_path / "prof"))
    det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)
    written = det.close()
    assert written and all(os.path.dirname(w) == str(tmp_path / "prof") for w in written)
    assert sorted(p.name for p in tiny_export.iterdir()) == before


@pytest.mark.parametrize("where", ["export", "inside", "cwd"])
def test_profiles_inside_the_export_are_refused(tiny_export, tmp_path, monkeypatch, where):
    """README and docs/trust.md: the runtime writes nothing into an export; profile_dir=<the export> (or a folder in
    it, or the default current directory while the process runs inside it) wrote three profile JSONs there."""
    export = tmp_path / "export"
    shutil.copytree(tiny_export, export)
    (export / "sub").mkdir()
    before = sorted(p.name for p in export.iterdir())
    if where == "cwd":
        monkeypatch.chdir(export / "sub")
        config, said = DetectorConfig(enable_profiling=True), "current directory"
    else:
        target = export if where == "export" else export / "sub" / "prof"
        config, said = DetectorConfig(enable_profiling=True, profile_dir=target), "DetectorConfig.profile_dir"
    with pytest.raises(ValueError, match=f"{said}.*lies inside the export"):
        StreamingDetector(export, config)
    assert sorted(p.name for p in export.iterdir()) == before
    StreamingDetector(export, DetectorConfig(profile_dir=export)).close()  # without profiling nothing is written


def test_a_slice_finishing_after_close_names_its_graph(det, sample, monkeypatch):
    """close() from another thread while a slice runs: the slice's output check still names the graph."""
    real = det._run_graph

    def run_then_close(name, feeds):
        out = real(name, feeds)
        if name == "slice_head":
            det.close()
        return out

    monkeypatch.setattr(det, "_run_graph", run_then_close)
    res = det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)  # this one finishes
    assert res.num_pillars > 0
    with pytest.raises(DetectorClosed):
        det.detect_slice(split_sweep(sample.points, 8)[0], 0, timestamp=0.0)

