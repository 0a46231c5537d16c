"""Robustness studies on a tiny export and a tiny synthetic dataset, each paired with a naive reference:
the plain one-variant evaluation (``evaluate_dataset`` + ``OnnxSweepDetector``) or a detector built for the case."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from streamdet.calibration.lut import Lut
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.perturb import perturb_rig
from streamdet.data.nuscenes import NuScenesReader
from streamdet import studies as st
from streamdet.evaluation.dataset_eval import OnnxSweepDetector, evaluate_dataset
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

N_SAMPLES = 2


@pytest.fixture(scope="module")
def export_dir(tiny_export_fp32) -> Path:
    return tiny_export_fp32  # fp32 graphs alone, 8 slices (conftest)


@pytest.fixture(scope="module")
def data_dir(tiny_synth_data) -> Path:
    return tiny_synth_data  # one scene of N_SAMPLES samples at 160x90 (conftest)


@pytest.fixture(scope="module")
def data(data_dir) -> st.StudyData:
    return st.StudyData(data_dir, split=None)  # one scene: its val split is empty


@pytest.fixture(scope="module")
def samples(data_dir):
    reader = NuScenesReader(data_dir, "v1.0-synth")
    return [reader.get(t) for t in reader.sample_tokens]


def _plain_map(export_dir, data, num_slices=None) -> float:
    return evaluate_dataset(OnnxSweepDetector(export_dir, num_slices=num_slices), data.root, split=None).metrics.mean_ap


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---- the runtime hooks the studies rely on -----------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 4, 32])
def test_per_call_slice_count_equals_a_detector_built_for_it(export_dir, samples, n):
    shared = StreamingDetector(export_dir)  # the export's 8 slices
    own = StreamingDetector(export_dir, DetectorConfig(num_slices=n))
    sample = samples[0]
    for det in (shared, own):
        det.set_calibration(sample.rig)
        imgs = sample.load_images((det.image.width, det.image.height))
        det.update_images(dict(zip(sample.rig.names, imgs)), timestamp=0.0)
    a = shared.detect_sweep(sample.points, timestamp=1.0, num_slices=n)
    b = own.detect_sweep(sample.points, timestamp=1.0)
    assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores) and np.array_equal(a.labels, b.labels)
    with pytest.raises(ValueError, match="num_slices"):
        shared.detect_sweep(sample.points, num_slices=3)


@pytest.mark.parametrize("size", [(256, 144), (190, 107)])
def test_image_size_override_builds_the_lut_for_that_size(export_dir, samples, size):
    det = StreamingDetector(export_dir, DetectorConfig(image_size=size))
    assert (det.image.width, det.image.height) == size
    assert (det.image.feature_width, det.image.feature_height) == (-(-size[0] // 4), -(-size[1] // 4))
    m = det.manifest
    from streamdet.export.exporter import load_rig

    rig, _ = load_rig(None)  # the export's (bundled) calibration
    ref = build_lut(rig, det.grid, m.image.feature_stride, size)
    assert np.array_equal(det.lut.index, ref.index) and np.array_equal(det.lut.weight, ref.weight)
    sample = samples[0]
    with pytest.raises(ValueError, match="for this detector"):
        exported = sample.load_images((m.image.width, m.image.height))
        det.update_images(dict(zip(sample.rig.names, exported)))
    imgs = sample.load_images(size)
    update = det.update_images(dict(zip(sample.rig.names, imgs)), timestamp=5.0)
    assert update.cameras_missing == () and set(update.cameras_used) == set(det.camera_names)
    sweep = det.detect_sweep_slices(sample.points)
    assert all(r.image_timestamp == 5.0 for r in sweep.slices)  # every slice read the BEV of these images
    d = sweep.detections
    assert d.boxes.shape == (len(d.scores), 9) and np.isfinite(d.boxes).all()


def test_image_size_of_the_export_keeps_its_lut(export_dir):
    det = StreamingDetector(export_dir, DetectorConfig(image_size=(128, 72)))
    saved = Lut.load(export_dir / "lut.npz")
    assert np.array_equal(det.lut.index, saved.index)
    with pytest.raises(ValueError, match="image_size"):
        DetectorConfig(image_size=(0, 72))


# ---- studies vs the plain evaluation -----------------------------------------------------------------------


def test_slices_match_the_plain_evaluation_at_every_count(export_dir, data):
    counts = (1, 8, 32)
    result = st.slices_study(st.OnnxSlicedDetector(export_dir), data, counts)
    assert result.slice_counts == counts and result.baseline is None and result.notes
    assert result.num_samples == N_SAMPLES
    for n, score in zip(counts, result.fused):
        assert score.mean_ap == pytest.approx(_plain_map(export_dir, data, n), abs=1e-12)
    d = result.to_dict()
    assert set(d["fused"]) == {"1", "8", "32"} and d["baseline"] is None
    assert "fused column only" in result.format_table()


def test_slices_baseline_column(export_dir, data):
    result = st.slices_study(st.OnnxSlicedDetector(export_dir), data, (4, 8), baseline=st.OnnxSlicedDetector(export_dir, label="twin"))
    assert [s.mean_ap for s in result.baseline] == [s.mean_ap for s in result.fused]  # same model: same figures
    assert result.baseline_source == "twin" and "LiDAR-only baseline" in result.format_table()


def test_drop_camera_equals_withholding_its_images(export_dir, data):
    result = st.drop_camera_study(export_dir, data, ["CAM_BACK", "CAM_FRONT"])
    assert result.cameras == ("CAM_BACK", "CAM_FRONT")
    assert result.all_cameras.mean_ap == pytest.approx(_plain_map(export_dir, data), abs=1e-12)
    det = StreamingDetector(export_dir)

    def without_front(sample):  # the naive reference: the sample's images, CAM_FRONT never given
        det.set_calibration(sample.rig)
        imgs = sample.load_images((det.image.width, det.image.height))
        det.update_images({n: a for n, a in zip(sample.rig.names, imgs) if n != "CAM_FRONT"})
        return det.detect_sweep(sample.points)

    ref = evaluate_dataset(without_front, data.root, split=None).metrics.mean_ap
    assert result.without[1].mean_ap == pytest.approx(ref, abs=1e-12)
    d = result.to_dict()
    assert d["dropped_cameras"] == ["CAM_BACK", "CAM_FRONT"] and set(d["without"]) == {"CAM_BACK", "CAM_FRONT"}
    assert "without CAM_BACK" in result.format_table()


def test_no_cameras_equals_a_detector_without_image_updates(export_dir, data):
    result = st.drop_camera_study(export_dir, data, ["CAM_BACK"], no_cameras=True)
    blind = StreamingDetector(export_dir)  # the naive reference: never an image, so the image BEV stays zeros
    ref = evaluate_dataset(lambda sample: blind.detect_sweep(sample.points), data.root, split=None).metrics.mean_ap
    assert result.no_cameras.mean_ap == pytest.approx(ref, abs=1e-12)
    assert result.to_dict()["no_cameras"]["mAP"] == result.no_cameras.mean_ap
    assert "without every camera" in result.format_table()
    assert st.drop_camera_study(export_dir, data, ["CAM_BACK"]).to_dict()["no_cameras"] is None


@pytest.mark.parametrize("bad", [["CAM_NOPE"], [], ["CAM_BACK", "CAM_BACK"]])
def test_drop_camera_refuses_bad_names(export_dir, data, bad):
    with pytest.raises(st.StudyError, match="camera"):
        st.drop_camera_study(export_dir, data, bad)


def test_calib_noise_zero_equals_reference_and_graphs_stay(export_dir, data):
    before = {g.file: _sha(export_dir / g.file) for g in read_manifest(export_dir).graphs}
    lut_before = _sha(export_dir / "lut.npz")
    result = st.calib_noise_study(export_dir, data, levels=[(0.0, 0.0), (2.0, 0.2)], seeds=2)
    zero, noisy = result.levels
    assert [s.mean_ap for s in zero.scores] == [result.reference.mean_ap] * 2  # exactly, not approximately
    assert zero.lut_changed_fraction == 0.0 and zero.std_ap == 0.0
    assert noisy.lut_changed_fraction > 0.01  # the LUT moved ...
    assert result.graphs_untouched and result.graphs_sha256 == before  # ... the graphs did not
    assert _sha(export_dir / "lut.npz") == lut_before  # nor the export's own LUT file
    assert result.reference.mean_ap == pytest.approx(_plain_map(export_dir, data), abs=1e-12)
    d = result.to_dict()
    assert d["levels"][1]["max_angle_deg"] == 2.0 and len(d["levels"][1]["mAP_per_seed"]) == 2


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_noisy_variant_equals_a_detector_on_the_perturbed_rig(export_dir, data, samples, seed):
    """One noisy level and seed against the naive route: a fresh detector whose LUT is the perturbed rig's."""
    result = st.calib_noise_study(export_dir, data, levels=[(1.0, 0.1)], seeds=[seed])
    det = StreamingDetector(export_dir)
    index = {s.token: i for i, s in enumerate(samples)}

    def noisy(sample):
        det.set_calibration(perturb_rig(sample.rig, 1.0, 0.1, st.noise_seed(seed, index[sample.token])))
        imgs = sample.load_images((det.image.width, det.image.height))
        det.update_images(dict(zip(sample.rig.names, imgs)))
        return det.detect_sweep(sample.points)

    ref = evaluate_dataset(noisy, data.root, split=None).metrics.mean_ap
    assert result.levels[0].scores[0].mean_ap == pytest.approx(ref, abs=1e-12)


def test_noise_seed_is_fresh_per_sample_and_reproducible():
    seeds = {st.noise_seed(s, i) for s in range(5) for i in range(50)}
    assert len(seeds) == 250 and st.noise_seed(3, 4) == st.noise_seed(3, 4)


@pytest.mark.parametrize("kwargs", [{"seeds": 0}, {"seeds": [-1]}, {"levels": [(200.0, 0.1)]}, {"levels": [(1.0, -0.1)]}])
def test_calib_noise_refuses_bad_levels_and_seeds(export_dir, data, kwargs):
    with pytest.raises(st.StudyError):
        st.calib_noise_study(export_dir, data, **kwargs)


def test_resolution_rows_latency_and_upsampling(export_dir, data):
    result = st.resolution_study(export_dir, data, [(256, 144), (128, 72)])
    big, native = result.rows
    assert (big.width, big.height, big.upsampled) == (256, 144, True)  # the dataset's images are 160x90
    assert (native.width, native.height, native.upsampled) == (128, 72, False)
    assert result.dataset_sizes == ((160, 90),) and result.export_size == (128, 72)
    assert native.score.mean_ap == pytest.approx(_plain_map(export_dir, data), abs=1e-12)
    for r in result.rows:
        assert r.image_lane_count == N_SAMPLES and r.image_lane_p50_ms > 0 and r.encoder_p50_ms > 0
    assert "upsampled" in result.format_table()
    with pytest.raises(st.StudyError):
        st.resolution_study(export_dir, data, [(8, 8)])


def test_empty_and_malformed_inputs(export_dir, data_dir, data):
    with pytest.raises(ValueError, match="holds no samples"):
        st.slices_study(st.OnnxSlicedDetector(export_dir), st.StudyData(data_dir, split="val"))
    with pytest.raises(st.StudyError, match="slice count"):
        st.slices_study(st.OnnxSlicedDetector(export_dir), data, (3,))
    with pytest.raises(st.StudyError, match="empty"):
        st.slices_study(st.OnnxSlicedDetector(export_dir), data, ())
    with pytest.raises(st.StudyError, match="max_samples"):
        st.StudyData(data_dir, max_samples=0)
    with pytest.raises(st.StudyError, match="int8"):
        st.open_detector(export_dir, st.RuntimeOptions(precision="int8"))
    one = st.drop_camera_study(export_dir, st.StudyData(data_dir, split=None, max_samples=1))
    assert one.num_samples == 1


def test_studies_score_as_the_dataset_evaluation_does_racks_included(export_dir, data, monkeypatch):
    """score_variants builds the ground truth and applies the devkit's bike-rack rule as evaluate_dataset does: the
    same figures, NDS included, with and without racks (a rack over the whole scene here, as the synthetic world
    has none)."""
    import streamdet.evaluation.dataset_eval as dataset_eval
    import streamdet.studies.common as common

    det = OnnxSweepDetector(export_dir)

    def run() -> tuple[dict, dict]:
        plain = evaluate_dataset(det, data.root, split=None).metrics.to_dict()
        scores, _ = common.score_variants(data, lambda i, sample: {"plain": det(sample)})
        return plain, scores["plain"].metrics.to_dict()

    plain, study = run()
    assert study == plain

    asked = []

    def everything_racked(sample):  # one rack, 200 m wide, centred on the ego: every bicycle lies in it
        asked.append(sample.token)
        centre = sample.ego2global[:3, 3]
        return np.array([[*centre, 200.0, 200.0, 50.0, 1.0, 0.0, 0.0, 0.0]])

    monkeypatch.setattr(dataset_eval, "bike_racks_of", everything_racked)
    monkeypatch.setattr(common, "bike_racks_of", everything_racked)
    racked_plain, racked_study = run()
    assert racked_study == racked_plain
    assert len(asked) == 2 * N_SAMPLES  # both paths asked for every sample's racks
