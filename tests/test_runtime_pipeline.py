"""runtime_ort/pipeline.py: one sample through the detector equals feeding it by hand (images with the sample's own
calibration, then the sweep), for a camera + LiDAR export."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streamdet.calibration.perturb import perturb_rig
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.pipeline import detect_sample, feed_images, sample_images, sample_time_s


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _same(a, b) -> bool:
    return np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores) and np.array_equal(a.labels, b.labels)


def test_detect_sample_equals_feeding_by_hand(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    run = detect_sample(det, sample)
    ref = StreamingDetector(tiny_export)
    images = sample.load_images((ref.image.width, ref.image.height))  # (J, H, W, 3) in rig order
    ts = sample.timestamp_us * 1e-6
    ref.update_images(dict(zip(sample.rig.names, images)), timestamp=ts)
    assert _same(run.detections, ref.detect_sweep(sample.points, timestamp=ts))
    assert run.images.cameras_missing == () and run.images.timestamp == ts == sample_time_s(sample)
    assert all(r.image_timestamp == ts and r.timestamp == ts for r in run.sweep.slices)
    for got, want in zip(run.sweep.points, split_sweep(sample.points, det.num_slices), strict=True):
        assert np.array_equal(got, want)


@pytest.mark.parametrize("num_slices", [1, 4])
def test_detect_sample_at_another_slice_count_and_without_images(tiny_export, sample, num_slices):
    det = StreamingDetector(tiny_export)
    run = detect_sample(det, sample, num_slices=num_slices, images=False)
    assert run.images is None and len(run.sweep.slices) == num_slices
    assert all(r.image_timestamp is None for r in run.sweep.slices)  # no image ever fed: zeros


@pytest.mark.parametrize("fixture", ["tiny_export", "tiny_lidar_export"])
def test_a_sample_of_an_empty_sweep_detects_nothing(fixture, request, sample):
    """The per-sample call on a sample whose sweep holds no point: its images still go in, no slice finds anything."""
    det = StreamingDetector(request.getfixturevalue(fixture))
    empty = dataclasses.replace(sample, points=np.zeros((0, 5), np.float32), point_time_s=None)
    run = detect_sample(det, empty)
    assert len(run.detections) == 0 and len(run.sweep.slices) == det.num_slices
    assert all(r.num_points == 0 and r.num_pillars == 0 for r in run.sweep.slices)
    if det.uses_images:
        assert run.images is not None and run.images.cameras_missing == ()
        assert all(r.image_timestamp == sample_time_s(sample) for r in run.sweep.slices)
    else:
        assert run.images is None


def test_another_rig_rebuilds_the_lut_once(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    moved = perturb_rig(sample.rig, 2.0, 0.2, seed=3)
    other = type(sample)(**{**{f: getattr(sample, f) for f in sample.__dataclass_fields__}, "rig": moved})
    before = det.lut.calibration_sha256
    images = sample_images(det, other)
    assert det.lut.calibration_sha256 == moved.sha256() != before
    assert sorted(images) == sorted(det.camera_names)
    assert all(a.shape == (det.image.height, det.image.width, 3) and a.dtype == np.uint8 for a in images.values())
    lut = det.lut
    feed_images(det, other)
    assert det.lut is lut  # the same rig again: no rebuild


def _with_rig(sample, rig):
    return type(sample)(**{**{f: getattr(sample, f) for f in sample.__dataclass_fields__}, "rig": rig})


def test_samples_of_changing_rigs_detect_as_with_the_relift(tiny_export, sample):
    """The pipeline drops the cached BEV on a rig swap instead of lifting it again: the detections of a run of
    samples, each with its own rig, are those of swapping with the re-lift (set_calibration's default) by hand."""
    det, ref = StreamingDetector(tiny_export), StreamingDetector(tiny_export)
    for seed in range(3):
        other = _with_rig(sample, perturb_rig(sample.rig, 1.0, 0.1, seed=seed))
        run = detect_sample(det, other)
        ts = sample_time_s(other)
        ref.set_calibration(other.rig)  # relift=True: the previous images lifted under the new LUT, then replaced
        ref.update_images(sample_images(ref, other), timestamp=ts)
        assert det.lut.calibration_sha256 == ref.lut.calibration_sha256 == other.rig.sha256()
        assert _same(run.detections, ref.detect_sweep(other.points, timestamp=ts))


def test_set_calibration_without_relift_drops_the_cached_bev(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    feed_images(det, sample)
    assert det.image_state is not None
    det.set_calibration(perturb_rig(sample.rig, 1.0, 0.1, seed=7), relift=False)
    assert det.image_state is None and det.image_timestamps == (None,) * 4
    result = det.detect_slice(split_sweep(sample.points, det.num_slices)[0], 0, timestamp=1.0)
    assert result.image_timestamp is None  # no image until the next update
    feed_images(det, _with_rig(sample, perturb_rig(sample.rig, 1.0, 0.1, seed=7)))
    assert det.image_state is not None and det.image_state.lut is det.lut


@pytest.mark.parametrize("bad", [0, 1, "no", None])
def test_set_calibration_relift_must_be_a_bool(tiny_export, sample, bad):
    det = StreamingDetector(tiny_export)
    with pytest.raises(ValueError, match="relift must be a bool"):
        det.set_calibration(sample.rig, relift=bad)


def test_a_sample_whose_rig_the_export_cannot_take_is_named(tiny_export, sample):
    """A hand-made dataset of another aspect: the runtime's refusal names the sample (eval, study), not only the camera."""
    import dataclasses

    from streamdet.calibration.camera import CalibrationError

    det = StreamingDetector(tiny_export)
    cam = sample.rig.cameras[0]
    other = dataclasses.replace(sample, rig=sample.rig.resized(cam.width, cam.width * 3 // 4))  # 4:3
    with pytest.raises(CalibrationError, match=rf"^sample {other.token} \(.*\): calibration camera {cam.name} is"):
        feed_images(det, other)
    det.close()
