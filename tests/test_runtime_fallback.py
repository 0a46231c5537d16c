"""The LiDAR-only fallback (runtime_ort/fallback.py, DetectorConfig.fallback_export_dir): slices without camera
features run the LiDAR-only export's slice graph and give exactly its detections; slices with them run the fused
graph as before; bad fallbacks are refused with the reason."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, NoImageLaneError, StreamingDetector
from streamdet.runtime_ort.fallback import FALLBACK_GRAPH, needs_fallback

N_SLICES = 8


@pytest.fixture(scope="module")
def lidar_export(tiny_lidar_export) -> Path:
    return tiny_lidar_export  # conftest: a tiny LiDAR-only export of seeded weights


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _images(det: StreamingDetector, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}


def _same(a, b) -> bool:
    return np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores) and np.array_equal(a.labels, b.labels)


def test_slices_without_images_run_the_lidar_only_graph(tiny_export, lidar_export, sample):
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=lidar_export))
    lidar = StreamingDetector(lidar_export)
    assert FALLBACK_GRAPH in det.sessions
    slices = split_sweep(sample.points, N_SLICES)
    found = 0
    for k, pts in enumerate(slices):
        got = det.detect_slice(pts, k, timestamp=1.0)
        ref = lidar.detect_slice(pts, k, timestamp=1.0)
        assert got.fallback and got.image_timestamp is None and not ref.fallback
        assert _same(got.detections, ref.detections)
        found += len(got.detections.scores)
    assert found > 0
    assert det.stats.summary()[FALLBACK_GRAPH]["count"] > 0


def test_slices_with_images_run_the_fused_graph(tiny_export, lidar_export, sample):
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=lidar_export))
    plain = StreamingDetector(tiny_export)
    for d in (det, plain):
        d.update_images(_images(d), timestamp=1.0)
    for k, pts in enumerate(split_sweep(sample.points, N_SLICES)):
        got = det.detect_slice(pts, k, timestamp=1.05)
        ref = plain.detect_slice(pts, k, timestamp=1.05)
        assert not got.fallback and got.image_age_s == pytest.approx(0.05)
        assert _same(got.detections, ref.detections)


def test_old_images_fall_back_after_the_set_age(tiny_export, lidar_export, sample):
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=lidar_export, fallback_after_s=0.2))
    det.update_images(_images(det), timestamp=10.0)
    pts = split_sweep(sample.points, N_SLICES)[3]
    assert not det.detect_slice(pts, 3, timestamp=10.2).fallback  # as old as allowed
    late = det.detect_slice(pts, 3, timestamp=10.5)
    assert late.fallback and late.image_age_s == pytest.approx(0.5)


def test_the_newest_slice_of_a_coalesced_run_decides_its_fallback(tiny_export, lidar_export, sample):
    """detect_slices: one graph run for the run's slices, so one decision; the images' age at the newest slice
    decides (images too old at the moment of the run), even where the older slice alone would fuse them."""
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=lidar_export, fallback_after_s=0.2))
    lidar, fused = StreamingDetector(lidar_export), StreamingDetector(tiny_export)
    for d in (det, fused):
        d.update_images(_images(d), timestamp=10.0)
    slices = split_sweep(sample.points, N_SLICES)
    pts, ks = [slices[2], slices[3]], [2, 3]  # one quadrant's two slices (quadrants_of_sector)
    # ages 0.1 s and 0.3 s on both sides of 0.2 s: alone, the first would fuse the images, the second fall back
    assert not det.detect_slice(pts[0], 2, timestamp=10.1).fallback and det.detect_slice(pts[1], 3, timestamp=10.3).fallback
    got = det.detect_slices(pts, ks, [10.1, 10.3])
    ref = lidar.detect_slices(pts, ks, [10.1, 10.3])
    assert [r.fallback for r in got] == [True, True], [(r.fallback, r.image_age_s) for r in got]
    assert [r.image_age_s for r in got] == pytest.approx([0.1, 0.3])  # each result keeps its own age
    assert sum(len(r.detections.scores) for r in got) > 0
    for a, b in zip(got, ref, strict=True):
        assert _same(a.detections, b.detections)  # the LiDAR-only graph's detections, exactly
    # both within the age: the fused graph, as a detector without a fallback gives
    got = det.detect_slices(pts, ks, [10.05, 10.2])
    ref = fused.detect_slices(pts, ks, [10.05, 10.2])
    assert [r.fallback for r in got] == [False, False]
    for a, b in zip(got, ref, strict=True):
        assert _same(a.detections, b.detections)


def test_a_quadrant_without_images_falls_back(tiny_export, lidar_export, sample):
    """Slices reading a quadrant that was never lifted fall back; the others do not."""
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=lidar_export))
    det.update_images(_images(det), timestamp=1.0, quadrants=[0])
    results = [det.detect_slice(p, k, timestamp=1.0) for k, p in enumerate(split_sweep(sample.points, N_SLICES))]
    from streamdet.core.sectors import quadrants_of_sector

    for r in results:
        assert r.fallback == (quadrants_of_sector(r.slice_index, N_SLICES, 0.0) != (0,))


@pytest.mark.parametrize(
    ("has_all", "age", "after", "want"),
    [(True, 0.1, None, False), (False, 0.1, None, True), (True, None, None, True), (True, 0.3, 0.2, True),
     (True, 0.2, 0.2, False), (True, 0.0, 0.0, False),
     # an image stamped seconds after its slice: the clocks disagree, its age is unknown (it was fused for ever)
     (True, -2.0, 0.5, True), (True, -0.08, 0.0, False), (True, -0.9, 0.5, False), (True, -2.0, None, False)],
)  # fmt: skip
def test_needs_fallback(has_all, age, after, want):
    assert needs_fallback(has_all, age, after) is want


def test_a_fused_fallback_is_refused(tiny_export):
    with pytest.raises(ValueError, match="must be a LiDAR-only export"):
        StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=tiny_export))


def test_a_lidar_only_detector_takes_no_fallback(lidar_export):
    with pytest.raises(NoImageLaneError, match="needs no LiDAR-only fallback"):
        StreamingDetector(lidar_export, DetectorConfig(fallback_export_dir=lidar_export))


def test_a_fallback_of_another_grid_is_refused(tiny_export, lidar_export, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(lidar_export, other)
    path = other / "manifest.json"
    m = json.loads(path.read_text())
    m["grid"]["voxel_xy_m"] = m["grid"]["voxel_xy_m"] * 2
    path.write_text(json.dumps(m))
    with pytest.raises(ValueError, match="differs from the grid its preset was trained on"):  # an edit of one copy
        StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=other))
    m["preset"]["grid"]["voxel_xy_m"] = m["grid"]["voxel_xy_m"]  # a LiDAR-only export of another grid
    path.write_text(json.dumps(m))
    with pytest.raises(ValueError, match="another grid"):
        StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=other))


def test_a_missing_fallback_precision_is_refused(tiny_int8_export, lidar_export):
    with pytest.raises(ValueError, match="has no int8 graphs"):
        StreamingDetector(tiny_int8_export.path, DetectorConfig(precision="int8", fallback_export_dir=lidar_export))


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), True, "0.2"])
def test_fallback_after_s_must_be_a_finite_age(bad, lidar_export):
    with pytest.raises(ValueError, match="fallback_after_s"):
        DetectorConfig(fallback_export_dir=lidar_export, fallback_after_s=bad)


def test_fallback_after_s_needs_a_fallback():
    with pytest.raises(ValueError, match="needs a fallback_export_dir"):
        DetectorConfig(fallback_after_s=0.5)


def test_fallback_export_dir_must_be_a_path():
    with pytest.raises(ValueError, match="fallback_export_dir must be None or a path"):
        DetectorConfig(fallback_export_dir=3)
