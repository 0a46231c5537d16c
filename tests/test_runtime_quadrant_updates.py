"""Per-quadrant image updates: the cameras that see a quadrant, its rows of the LUT, its own timestamp; the same BEV
as the full update (fp32), with the export format unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.calibration.lut import CameraMovedWarning
from streamdet.calibration.perturb import perturb_rig
from streamdet.calibration.quadrant_lut import quadrant_lut, quadrant_luts
from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector

N_SLICES = 8


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture(scope="module")
def detector(tiny_export) -> StreamingDetector:
    return StreamingDetector(tiny_export)


def _images(det: StreamingDetector, seed: int, names=None) -> dict[str, np.ndarray]:
    img = det.image
    rng = np.random.default_rng(seed)
    names = det.camera_names if names is None else names
    return {n: rng.integers(0, 256, (img.height, img.width, 3), dtype=np.uint8) for n in names}


def _naive_gather(features: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Reference of the lifter's gather: sum_k weight * table[index], table = maps as rows + one zero row."""
    j, c, hf, wf = features.shape
    table = np.concatenate([features.transpose(0, 2, 3, 1).reshape(j * hf * wf, c), np.zeros((1, c), np.float32)])
    return (table[index] * weight[..., None]).sum(axis=1)  # (Q, Z, Yq, Xq, C)


@pytest.mark.parametrize("quadrant", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_quadrant_lut_gathers_what_the_full_lut_gathers(detector, quadrant, seed):
    lut = detector.lut
    rng = np.random.default_rng(seed)
    features = rng.standard_normal((lut.num_cameras, 3, lut.feature_height, lut.feature_width)).astype(np.float32)
    qlut = quadrant_lut(lut, quadrant)
    full = _naive_gather(features, lut.index[quadrant : quadrant + 1], lut.weight[quadrant : quadrant + 1])
    sub = features[list(qlut.camera_indices)] if qlut.camera_indices else np.zeros_like(features[:1])
    part = _naive_gather(sub, qlut.index, qlut.weight)
    np.testing.assert_array_equal(part, full)
    assert qlut.index.shape[1] <= lut.num_slots and qlut.index.dtype == np.int32 and qlut.weight.dtype == np.float32
    assert qlut.index.max() == qlut.num_feature_maps * lut.feature_height * lut.feature_width  # the sentinel is used


def test_quadrant_luts_name_the_cameras_the_lut_reads(detector):
    lut = detector.lut
    cells = lut.feature_height * lut.feature_width
    for q, qlut in enumerate(quadrant_luts(lut)):
        rows = lut.index[q][lut.index[q] != lut.sentinel]
        assert qlut.camera_indices == tuple(int(j) for j in np.unique(rows // cells))
        assert 0 < len(qlut.camera_names) < lut.num_cameras  # each quadrant of the bundled rig: some cameras, not all
    with pytest.raises(ValueError, match="quadrant must be an int in 0..3, got 4"):
        quadrant_lut(lut, 4)


def test_a_quadrant_no_camera_sees_lifts_zeros_like_the_full_lut(detector):
    lut = detector.lut
    blind = type(lut)(
        index=np.where(np.arange(4)[:, None, None, None, None] == 2, lut.sentinel, lut.index).astype(np.int32),
        weight=np.where(np.arange(4)[:, None, None, None, None] == 2, 0.0, lut.weight).astype(np.float32),
        grid=lut.grid, feature_stride=lut.feature_stride, image_width=lut.image_width, image_height=lut.image_height,
        camera_names=lut.camera_names, calibration_sha256=lut.calibration_sha256, min_depth_m=lut.min_depth_m,
    )  # fmt: skip
    qlut = quadrant_lut(blind, 2)
    assert qlut.camera_names == () and qlut.num_feature_maps == 1 and qlut.index.shape[1] == 1
    assert np.all(qlut.weight == 0) and np.all(qlut.index == lut.feature_height * lut.feature_width)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("given", ["all", "some"])
def test_four_quadrant_updates_equal_one_full_update(tiny_export, seed, given):
    full = StreamingDetector(tiny_export)
    # missing cameras are zeros in both; a quadrant none of whose cameras is given is cleared in both
    names = full.camera_names if given == "all" else full.camera_names[::2]
    images = _images(full, seed, names)
    whole = full.update_images(images, timestamp=1.0)
    parts = StreamingDetector(tiny_export)
    cleared = []
    for q in (2, 0, 3, 1):  # any order
        update = parts.update_images(images, timestamp=1.0, quadrants=[q])
        assert update.quadrants + update.cleared == (q,) and not update.superseded
        assert set(update.cameras_used) <= set(parts.quadrant_cameras([q]))
        cleared += update.cleared
    assert tuple(sorted(cleared)) == whole.cleared
    assert whole.quadrants == tuple(q for q in range(4) if q not in whole.cleared)
    for a, b in zip(parts.image_state.quadrants, full.image_state.quadrants):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_allclose(a.bev, b.bev, rtol=0, atol=1e-6)
    for k, pts in enumerate(split_sweep(load_bundled_sample().points, N_SLICES)):
        a = full.detect_slice(pts, k, timestamp=2.0)
        b = parts.detect_slice(pts, k, timestamp=2.0)
        np.testing.assert_allclose(a.detections.boxes, b.detections.boxes, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(a.detections.labels, b.detections.labels)


def test_two_quadrants_at_once_equal_the_full_update(tiny_export):
    full = StreamingDetector(tiny_export)
    images = _images(full, 3)
    full.update_images(images, timestamp=1.0)
    parts = StreamingDetector(tiny_export)
    parts.update_images(images, timestamp=1.0, quadrants=(0, 1))
    parts.update_images(images, timestamp=1.0, quadrants=[2, 3])
    np.testing.assert_allclose(parts.image_state.bev, full.image_state.bev, rtol=0, atol=1e-6)


def test_a_quadrant_update_encodes_only_the_cameras_that_see_it(tiny_export):
    det = StreamingDetector(tiny_export)
    for q in range(4):
        det.stats.reset()
        update = det.update_images(_images(det, q), timestamp=float(q), quadrants=[q])
        assert update.cameras_used == det.quadrant_cameras([q]) and update.cameras_missing == ()
        s = det.stats.summary()
        assert s["image_encoder"]["count"] == 1 and s["volumetric_lifter"]["count"] == 1
        # the executed GMAC follow the run's sizes: that quadrant's cameras, one quadrant
        enc = det.manifest.graph("image_encoder", det.config.image_precision)
        assert s["image_encoder"]["gmac_total"] == pytest.approx(enc.gmac * len(update.cameras_used) / enc.gmac_at["J"])


def test_each_quadrant_keeps_its_own_timestamp_and_slices_report_the_age_of_theirs(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    assert det.image_timestamps == (None, None, None, None) and det.image_timestamp is None
    det.update_images(_images(det, 0), timestamp=10.0)
    det.update_images(_images(det, 1), timestamp=12.0, quadrants=[1])
    assert det.image_timestamps == (10.0, 12.0, 10.0, 10.0) and det.image_timestamp == 10.0
    slices = split_sweep(sample.points, N_SLICES)
    for k, pts in enumerate(slices):
        r = det.detect_slice(pts, k, timestamp=12.5)
        (q,) = quadrants_of_sector(k, N_SLICES)  # 8 slices: one quadrant each
        assert r.image_timestamp == det.image_timestamps[q]
        assert r.image_age_s == pytest.approx(12.5 - det.image_timestamps[q])
    whole = det.detect_slice(split_sweep(sample.points, 1)[0], 0, timestamp=13.0, num_slices=1)
    assert whole.image_timestamp == 10.0 and whole.image_age_s == pytest.approx(3.0)  # four quadrants: the oldest


def test_before_any_image_a_slice_has_no_image_age(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    r = det.detect_slice(split_sweep(sample.points, N_SLICES)[0], 0, timestamp=1.0)
    assert r.image_timestamp is None and r.image_age_s is None
    det.update_images(_images(det, 0), timestamp=1.0, quadrants=[3])  # quadrant 0 still has none
    r = det.detect_slice(split_sweep(sample.points, N_SLICES)[0], 0, timestamp=2.0)
    assert r.image_timestamp is None and r.image_age_s is None


def test_an_older_quadrant_update_never_replaces_a_newer_one(tiny_export):
    det = StreamingDetector(tiny_export)
    det.update_images(_images(det, 0), timestamp=5.0)  # seq 1
    state = det.image_state
    # a later call (seq 2) for quadrant 0 installs; the cache of the other quadrants is the same objects
    det.update_images(_images(det, 1), timestamp=4.0, quadrants=[0])  # timestamps are labels: call order decides
    assert det.image_timestamps == (4.0, 5.0, 5.0, 5.0)
    assert all(a is b for a, b in zip(det.image_state.quadrants[1:], state.quadrants[1:]))


def test_calibration_swap_relifts_quadrant_updates_like_a_full_update(tiny_export, sample):
    img_det = StreamingDetector(tiny_export)
    rig = perturb_rig(sample.rig, 1.0, 0.1, seed=0).resized(img_det.image.width, img_det.image.height)
    images = _images(img_det, 4)
    full = StreamingDetector(tiny_export)
    full.update_images(images, timestamp=1.0)
    full.set_calibration(rig)
    parts = StreamingDetector(tiny_export)
    for q in range(4):
        parts.update_images(images, timestamp=1.0, quadrants=[q])
    parts.set_calibration(rig)
    assert parts.image_state.lut is parts.lut
    # a camera the new LUT reads in a quadrant but the update did not encode is zeros there: equal only where
    # each quadrant's cameras are unchanged
    same = [q for q in range(4) if parts.quadrant_cameras([q]) == StreamingDetector(tiny_export).quadrant_cameras([q])]
    for q in same:
        np.testing.assert_allclose(parts.image_state.quadrants[q].bev, full.image_state.bev[q : q + 1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("bad", [[], [4], [1, 0], [0, 0], [True], "0", [0.0], (-1,)])
def test_malformed_quadrants_are_refused_before_anything_changes(detector, bad):
    before = detector.image_state
    with pytest.raises(ValueError, match="quadrants must be a non-empty strictly increasing list of 0..3"):
        detector.update_images(_images(detector, 0), timestamp=1.0, quadrants=bad)
    assert detector.image_state is before


def test_a_quadrant_whose_cameras_are_not_given_is_cleared(tiny_export):
    det = StreamingDetector(tiny_export)
    det.update_images(_images(det, 1), timestamp=0.5)  # an older BEV everywhere
    seeing = set(det.quadrant_cameras([0]))
    others = [n for n in det.camera_names if n not in seeing]
    update = det.update_images(_images(det, 0, others), timestamp=1.0, quadrants=[0])
    assert update.cameras_used == () and update.cameras_missing == det.quadrant_cameras([0])
    assert update.quadrants == () and update.cleared == (0,) and not update.superseded
    assert det.image_state.quadrants[0] is None and det.image_timestamps[1:] == (0.5, 0.5, 0.5)
    ref = StreamingDetector(tiny_export)
    whole = ref.update_images(_images(ref, 0, others), timestamp=1.0)  # the full update with the same cameras missing
    assert 0 in whole.cleared and ref.image_state.quadrants[0] is None


def test_encoded_feature_maps_are_used_instead_of_encoding_again(tiny_export):
    det = StreamingDetector(tiny_export)
    images = _images(det, 5)
    encoded = det.encode_images(images)
    assert set(encoded) == set(det.camera_names) and all(f.dtype == np.float32 and f.ndim == 3 for f in encoded.values())
    ref = StreamingDetector(tiny_export)
    ref.update_images(images, timestamp=1.0)
    det.stats.reset()
    for q in range(4):
        cams = det.quadrant_cameras([q])
        det.update_images({n: images[n] for n in cams}, 1.0, quadrants=[q], encoded={n: encoded[n] for n in cams})
    assert "image_encoder" not in det.stats.summary()  # nothing encoded twice
    np.testing.assert_allclose(det.image_state.bev, ref.image_state.bev, rtol=0, atol=1e-6)


@pytest.mark.parametrize("bad, match", [
    ({"CAM_FRONT": np.zeros((1, 2, 3), np.float32)}, "must be a float32 feature map of shape"),
    ({"CAM_FRONT": "x"}, "must be a float32 feature map"),
    ({"NOPE": np.zeros((1,), np.float32)}, "whose image this update was not given"),
    ([1], "encoded must be None or a dict"),
])  # fmt: skip
def test_malformed_encoded_maps_are_refused(detector, bad, match):
    before = detector.image_state
    with pytest.raises(ValueError, match=match):
        detector.update_images(_images(detector, 0), timestamp=1.0, quadrants=[0], encoded=bad)
    assert detector.image_state is before


@pytest.mark.parametrize("quadrants", [None, [1], [0, 2]])
def test_camera_timestamps_make_each_quadrant_as_old_as_its_oldest_camera(tiny_export, quadrants):
    det = StreamingDetector(tiny_export)
    stamps = {n: 10.0 + 0.01 * j for j, n in enumerate(det.camera_names)}  # cameras fired one after the other
    before = det.image_timestamps
    det.update_images(_images(det, 0), timestamp=9.0, quadrants=quadrants, camera_timestamps=stamps)
    for q, got in enumerate(det.image_timestamps):
        if quadrants is not None and q not in quadrants:
            assert got == before[q]
            continue
        seen = [stamps[n] for n in det.quadrant_cameras([q])]
        assert got == (min(seen) if seen else 9.0)  # a quadrant no camera sees keeps the update's timestamp
    plain = StreamingDetector(tiny_export)
    plain.update_images(_images(plain, 0), timestamp=9.0, quadrants=quadrants)
    np.testing.assert_array_equal(det.image_state.bev, plain.image_state.bev)  # the times change nothing else


@pytest.mark.parametrize("bad, match", [
    ({"NO_SUCH_CAM": 1.0}, "not given"), ({"CAM_FRONT": float("nan")}, "finite"), ({"CAM_FRONT": True}, "finite"),
    ([1.0], "dict"),
])  # fmt: skip
def test_malformed_camera_timestamps_are_refused(detector, bad, match):
    with pytest.raises(ValueError, match=match):
        detector.update_images(_images(detector, 0), timestamp=1.0, camera_timestamps=bad)


def _naive_quadrant_cameras(det: StreamingDetector, quadrants) -> tuple[str, ...]:
    seen = {n for q in quadrants for n in quadrant_lut(det.lut, q).camera_names}
    return tuple(n for n in det.camera_names if n in seen)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_quadrant_cameras_follow_a_calibration_swap(tiny_export, sample, seed):
    """quadrant_cameras keeps its answers per LUT: after a swap it names the new LUT's cameras, never the old one's."""
    det = StreamingDetector(tiny_export)
    subsets = [(0,), (1,), (2,), (3,), (0, 1), (1, 2, 3), (0, 1, 2, 3)]
    for _ in range(2):  # the second pass reads the kept answers
        assert [det.quadrant_cameras(list(qs)) for qs in subsets] == [_naive_quadrant_cameras(det, qs) for qs in subsets]
    old = [det.quadrant_cameras([q]) for q in range(4)]
    rig = perturb_rig(sample.rig, 60.0, 0.5, seed=seed).resized(det.image.width, det.image.height)
    with pytest.warns(CameraMovedWarning):  # a swap this large moves what the cameras see: the point of the test
        det.set_calibration(rig)
    assert any(det.quadrant_cameras([q]) != before for q, before in enumerate(old))
    for _ in range(2):
        assert [det.quadrant_cameras(qs) for qs in subsets] == [_naive_quadrant_cameras(det, qs) for qs in subsets]
    assert det.quadrant_cameras([np.int64(2)]) == _naive_quadrant_cameras(det, (2,))


@pytest.mark.parametrize("bad", [[], [4], [1, 0], [True], (True,), [1.0], "1"])
def test_quadrant_cameras_refuses_malformed_quadrants_after_valid_ones(detector, bad):
    for q in range(4):
        detector.quadrant_cameras([q])  # kept: a bool or float equal to a kept key must still be refused
    with pytest.raises(ValueError, match="quadrants must be a non-empty strictly increasing list of 0..3"):
        detector.quadrant_cameras(bad)
