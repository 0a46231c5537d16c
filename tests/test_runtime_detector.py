"""The torch-free streaming detector on a tiny export: detections, bad input, calibration swaps, threads, soak."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.perturb import perturb_rig
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.lanes import LaneConfig, SliceDropped, StreamingRunner
from streamdet.runtime_ort.manifest import ManifestError, graph_file_name

N_SLICES = 8


@pytest.fixture(scope="module")
def export_dir(tiny_export) -> Path:
    return tiny_export  # fp32 + fp16, N_SLICES slices (conftest)


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture(scope="module")
def detector(export_dir) -> StreamingDetector:
    return StreamingDetector(export_dir)


def _images(det: StreamingDetector, sample, names=None) -> dict[str, np.ndarray]:
    img = det.manifest.image
    names = det.camera_names if names is None else names
    arr = sample.load_images((img.width, img.height))  # (J, H, W, 3)
    return {n: arr[sample.rig.names.index(n)] for n in names}


def _slices(sample, n=N_SLICES):
    return split_sweep(sample.points, n)


def _same(a, b) -> bool:
    return (
        a.boxes.shape == b.boxes.shape
        and np.array_equal(a.boxes, b.boxes)
        and np.array_equal(a.scores, b.scores)
        and np.array_equal(a.labels, b.labels)
    )


def test_detects_every_slice_of_the_real_sample(detector, sample):
    update = detector.update_images(_images(detector, sample), timestamp=1.0)
    assert update.cameras_missing == ()
    for k, pts in enumerate(_slices(sample)):
        res = detector.detect_slice(pts, k, timestamp=2.0)
        assert res.image_timestamp == 1.0
        assert res.num_points == len(pts) and res.num_pillars > 0
        d = res.detections
        assert d.boxes.shape[1] == 9 and d.boxes.dtype == np.float32
        assert np.all(np.isfinite(d.boxes)) and np.all(d.scores >= detector.postprocess.score_threshold)
    summary = detector.stats.summary()
    for stage in ("pre", "slice_head", "post", "slice_total", "image_encoder", "volumetric_lifter", "image_total"):
        assert summary[stage]["count"] >= 1 and summary[stage]["p95_ms"] >= summary[stage]["p50_ms"]


def test_sweep_equals_merged_slices(detector, sample):
    detector.update_images(_images(detector, sample), timestamp=1.0)
    sweep = detector.detect_sweep(sample.points)
    from streamdet.runtime_ort.postprocess import aggregate_sweep

    parts = [detector.detect_slice(p, k).detections for k, p in enumerate(_slices(sample))]
    assert _same(sweep, aggregate_sweep(parts, detector.config.nms))


def test_missing_cameras_are_zero_features_and_reported(detector, sample):
    update = detector.update_images(_images(detector, sample, names=("CAM_FRONT", "CAM_BACK")), timestamp=3.0)
    assert set(update.cameras_missing) == set(detector.camera_names) - {"CAM_FRONT", "CAM_BACK"}
    feats = detector.image_state.features
    for n in update.cameras_missing:
        assert not feats[detector.camera_names.index(n)].any()
    assert feats[detector.camera_names.index("CAM_FRONT")].any()


def test_before_any_image_the_slice_uses_zeros(export_dir, sample):
    det = StreamingDetector(export_dir)
    res = det.detect_slice(_slices(sample)[0], 0)
    assert res.image_timestamp is None


def test_the_image_state_and_postprocess_are_public_and_read_only(export_dir, sample):
    det = StreamingDetector(export_dir, DetectorConfig(score_threshold=0.25))
    assert det.image_state is None and det.postprocess.score_threshold == 0.25
    det.update_images(_images(det, sample), timestamp=2.0)
    state = det.image_state
    assert state.timestamp == 2.0 and state.seq == 1 and state.lut is det.lut and state is det.image_state
    det.detect_slice(_slices(sample)[0], 0)
    assert det.image_state is state  # a slice reads the cache, never replaces it
    det.update_images(_images(det, sample), timestamp=3.0)
    assert det.image_state is not state and det.image_state.seq == 2 and state.timestamp == 2.0
    for name in ("image_state", "postprocess"):
        with pytest.raises(AttributeError):
            setattr(det, name, None)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_precisions_run(export_dir, sample, precision):
    det = StreamingDetector(export_dir, DetectorConfig(precision=precision))
    assert det.precision_label == precision
    assert det.slice_head.path.name == graph_file_name("slice_head", precision)  # the precision's graphs are loaded
    assert det.image_encoder.path.name == graph_file_name("image_encoder", precision)
    det.update_images(_images(det, sample), timestamp=1.0)
    res = det.detect_slice(_slices(sample)[2], 2)
    assert res.image_timestamp == 1.0 and res.slice_index == 2 and res.num_pillars > 0
    d = res.detections
    assert d.boxes.shape == (len(d.scores), 9) and np.isfinite(d.boxes).all()
    assert ((d.labels >= 0) & (d.labels < len(CLASS_NAMES))).all() and ((d.scores > 0) & (d.scores <= 1)).all()


def test_nan_points_are_dropped_and_counted(detector, sample):
    pts = _slices(sample)[0].copy()
    pts[:5, 0] = np.nan
    pts[5:7, 2] = np.inf
    res = detector.detect_slice(pts, 0)
    assert res.num_nonfinite_dropped == 7


def test_empty_slice_gives_no_detections(detector):
    res = detector.detect_slice(np.zeros((0, 6), np.float32), 3)
    assert len(res.detections) == 0 and res.num_pillars == 0


@pytest.mark.parametrize("num_slices", [None, 4])
def test_an_empty_sweep_gives_no_detections(detector, num_slices):
    """A sweep of no point at all (a LiDAR that sent an empty frame): every slice runs empty, nothing is detected."""
    n = N_SLICES if num_slices is None else num_slices
    sweep = np.zeros((0, 5), np.float32)
    dets = detector.detect_sweep(sweep, timestamp=1.0, num_slices=num_slices)
    assert len(dets) == 0 and dets.boxes.shape == (0, 9) and dets.scores.shape == (0,) and dets.labels.shape == (0,)
    run = detector.detect_sweep_slices(sweep, timestamp=1.0, num_slices=num_slices)
    assert len(run.detections) == 0 and [r.slice_index for r in run.slices] == list(range(n))
    assert all(r.num_points == 0 and r.num_pillars == 0 and len(r.detections) == 0 and r.timestamp == 1.0 for r in run.slices)
    assert [p.shape for p in run.points] == [(0, 6)] * n


@pytest.mark.parametrize("method", ["update_images", "encode_images"])
def test_no_camera_image_is_refused_naming_the_cameras(detector, method):
    with pytest.raises(ValueError, match=r"no camera image given: at least one of \['CAM_"):
        getattr(detector, method)({})


@pytest.mark.parametrize(
    "points,k,match",
    [
        (np.zeros((10, 5), np.float32), 0, r"\(N, 6\)"),
        (np.zeros((10, 6), np.float64), 0, "float32"),
        (np.zeros(6, np.float32), 0, r"\(N, 6\)"),
        (np.zeros((10, 6), np.float32), N_SLICES, "slice_index"),
        (np.zeros((10, 6), np.float32), -1, "slice_index"),
        (np.zeros((10, 6), np.float32), 1.0, "slice_index"),
    ],
)
def test_bad_slice_input(detector, points, k, match):
    with pytest.raises(ValueError, match=match):
        detector.detect_slice(points, k)


def test_bad_images(detector, sample):
    good = _images(detector, sample)
    with pytest.raises(ValueError, match="unknown camera"):
        detector.update_images({"CAM_ROOF": good["CAM_FRONT"]})
    with pytest.raises(ValueError, match="CAM_FRONT.*uint8 RGB of shape"):
        detector.update_images({"CAM_FRONT": good["CAM_FRONT"][:-2]})
    with pytest.raises(ValueError, match="uint8"):
        detector.update_images({"CAM_FRONT": good["CAM_FRONT"].astype(np.float32)})
    with pytest.raises(ValueError, match="no camera image given: at least one of"):
        detector.update_images({})


def test_tampered_graph_is_refused(export_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(export_dir, bad)
    path = bad / "slice_head.onnx"
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ManifestError, match="sha256"):
        StreamingDetector(bad)


def test_missing_precision_is_refused(export_dir):
    with pytest.raises(ValueError, match="int8"):
        StreamingDetector(export_dir, DetectorConfig(precision="int8"))


def test_lut_that_does_not_fit_is_refused(detector, sample):
    img = detector.manifest.image
    wrong_size = build_lut(sample.rig.resized(img.width * 2, img.height * 2), detector.grid, img.feature_stride)
    with pytest.raises(ValueError, match="does not fit"):
        detector.set_calibration(wrong_size)
    with pytest.raises(ValueError, match="cameras"):
        detector.set_calibration(sample.rig.without(["CAM_BACK"]).resized(img.width, img.height))


def test_set_calibration_relifts_without_new_sessions(export_dir, sample):
    det = StreamingDetector(export_dir)
    det.update_images(_images(det, sample), timestamp=5.0)
    bev_before = det.image_state.bev.copy()
    sessions = (det.image_encoder.session, det.lifter.session, det.slice_head.session)
    lut_hash = det.lut.calibration_sha256
    img = det.manifest.image
    noisy = perturb_rig(sample.rig, max_angle_deg=1.0, max_translation_m=0.1, seed=0).resized(img.width, img.height)
    det.set_calibration(noisy)
    assert (det.image_encoder.session, det.lifter.session, det.slice_head.session) == sessions
    assert det.lut.calibration_sha256 != lut_hash
    assert not np.array_equal(det.image_state.bev, bev_before)
    assert det.image_state.timestamp == 5.0


def test_threads_give_the_same_detections_as_one_thread(export_dir, sample):
    det = StreamingDetector(export_dir)
    images = _images(det, sample)
    det.update_images(images, timestamp=0.0)
    slices = _slices(sample)
    reference = [det.detect_slice(p, k).detections for k, p in enumerate(slices)]
    errors: list[BaseException] = []
    mismatches: list[int] = []

    def slice_worker(seed: int) -> None:
        rng = np.random.default_rng(seed)
        try:
            for k in rng.integers(0, N_SLICES, size=20):
                got = det.detect_slice(slices[k], int(k)).detections
                if not _same(got, reference[k]):
                    mismatches.append(int(k))
        except BaseException as e:  # noqa: BLE001 - handed to the main thread
            errors.append(e)

    def image_worker() -> None:
        try:
            for _ in range(5):
                det.update_images(images, timestamp=0.0)  # same images: the BEV must not change
        except BaseException as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=slice_worker, args=(s,)) for s in range(4)] + [threading.Thread(target=image_worker)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert not mismatches


def test_runner_lanes_and_back_pressure(export_dir, sample):
    det = StreamingDetector(export_dir)
    slices = _slices(sample)
    with StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=2)) as runner:
        img_future = runner.submit_images(_images(det, sample), timestamp=1.0)
        futures = [runner.submit_slice(slices[k % N_SLICES], k % N_SLICES) for k in range(40)]
        img_future.result()
        done, dropped = 0, 0
        for f in futures:
            try:
                f.result()
                done += 1
            except SliceDropped:
                dropped += 1
        assert done >= 2 and done + dropped == 40  # the newest queue_size slices always survive
        assert runner.slices_dropped == dropped
        assert dropped > 0  # 40 slices at once into a queue of 2 cannot all wait


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="reads the resident set from Linux's /proc/self/statm")
def test_soak_thousands_of_slices_do_not_grow_memory(export_dir, sample):
    det = StreamingDetector(export_dir)
    det.update_images(_images(det, sample))
    slices = _slices(sample)
    small = [s[:300] for s in slices]
    for i in range(300):  # warm-up: arenas and caches settle
        det.detect_slice(small[i % N_SLICES], i % N_SLICES)
    before = _rss_mb()
    for i in range(3000):
        det.detect_slice(small[i % N_SLICES], i % N_SLICES)
    growth = _rss_mb() - before
    assert growth < 20.0, f"resident memory grew {growth:.1f} MB over 3000 slices"
    assert det.stats.summary()["slice_total"]["count"] == 3300


def test_detection_without_torch(export_dir):
    code = textwrap.dedent(
        f"""
        import sys
        class _Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "torch":
                    raise ImportError("torch is blocked")
        sys.meta_path.insert(0, _Block())
        import numpy as np
        from streamdet.runtime_ort.detector import StreamingDetector
        from streamdet.data.sample import load_bundled_sample
        from streamdet.data.slicing import split_sweep
        det = StreamingDetector({str(export_dir)!r})
        s = load_bundled_sample()
        img = det.manifest.image
        arr = s.load_images((img.width, img.height))
        det.update_images(dict(zip(s.rig.names, arr)))
        res = det.detect_slice(split_sweep(s.points, {N_SLICES})[1], 1)
        assert "torch" not in sys.modules
        print("ok", len(res.detections))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok")


def test_embedding_the_runtime_loads_no_dataset_reader():
    """A vehicle process imports the runtime (detector, lanes, warm-up, ROS adapters) without the dataset package:
    ``streamdet.data`` reads nuScenes tables and loads images from files, nothing the vehicle does."""
    code = (
        "import sys\n"
        "from streamdet.runtime_ort import StreamingDetector, StreamingRunner, DetectorConfig\n"
        "import streamdet.runtime_ort.warm_up, streamdet.runtime_ort.lanes, streamdet.runtime_ort.phase_locked_lane\n"
        "import streamdet.runtime_ort.ros.pointcloud2, streamdet.runtime_ort.ros.images\n"
        "loaded = sorted(m for m in sys.modules if m.startswith('streamdet.data') or m.split('.')[0] == 'torch')\n"
        "assert not loaded, loaded\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_run_cli_writes_results_and_picture(export_dir, tmp_path):
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(export_dir), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    doc = json.loads((tmp_path / "results_nusc.json").read_text())
    assert doc["meta"]["use_lidar"] and len(doc["results"]) == 1
    assert (tmp_path / "bev.png").stat().st_size > 1000
    assert "slice_total" in result.output


def test_run_cli_without_export_is_a_clear_error(tmp_path):
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(tmp_path / "nothing")])
    assert result.exit_code != 0 and "streamdet-export" in result.output
