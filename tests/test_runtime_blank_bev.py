"""A quadrant without camera features: its slices read the camera-less BEV (the lift of zero feature maps, made once
per detector), not an all-zero map; an image update given none of a quadrant's cameras clears that quadrant instead
of lifting zeros stamped as fresh, so that its slices report no image age and the LiDAR-only fallback takes them
(docs/replay.md, "A quadrant without cameras": the measurement behind both)."""

from __future__ import annotations

import warnings

import numpy as np
import onnxruntime as ort
import pytest

from streamdet.calibration.perturb import perturb_rig
from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorClosed, DetectorConfig, NoImageLaneError, StreamingDetector

from test_camera_terms import export_dir  # noqa: F401  # a flat-lifter export (per-camera terms), a fixture

N_SLICES = 8
WIDER_RIG_SEED = 1  # as tests/test_runtime_image_races.py: quadrant 3 reads one camera more under this rig


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _images(det: StreamingDetector, seed: int, names=None) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    names = det.camera_names if names is None else names
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in names}


def _same(a, b) -> bool:
    return np.array_equal(a.boxes, b.boxes) and np.array_equal(a.scores, b.scores) and np.array_equal(a.labels, b.labels)


def _slice_in(quadrant: int, points: np.ndarray) -> tuple[int, np.ndarray]:
    """A slice of the bundled sweep that lies in ``quadrant`` alone."""
    for k, pts in enumerate(split_sweep(points, N_SLICES)):
        if quadrants_of_sector(k, N_SLICES, 0.0) == (quadrant,):
            return k, pts
    raise AssertionError(f"no slice in quadrant {quadrant}")


def _lifter_on_zeros(export_path, det: StreamingDetector, quadrant: int) -> np.ndarray:
    """The reference: the export's fp32 lifter graph, in an onnxruntime session of its own, on zero feature maps of
    the cameras that see ``quadrant``, with that quadrant's rows of the LUT (fed as the runtime feeds them)."""
    session = ort.InferenceSession(str(export_path / "volumetric_lifter.onnx"), providers=["CPUExecutionProvider"])
    img = det.image
    qlut = det._luts_of(det.lut)[quadrant]
    channels = int(det.manifest.preset["channels"])
    maps = np.zeros((max(1, len(qlut.camera_names)), channels, img.feature_height, img.feature_width), np.float32)
    return session.run(None, {"features": maps, **det._lut_feeds(qlut, maps)})[0]  # (1, C, Yq, Xq)


@pytest.mark.parametrize(("export", "camera_terms"), [("tiny_export", None), ("export_dir", True), ("export_dir", False)])
def test_the_blank_bev_is_the_lifter_on_zero_features_in_every_quadrant(request, export, camera_terms):
    export_path = request.getfixturevalue(export)  # the volume lifter; the flat lifter through terms and through its graph
    det = StreamingDetector(export_path, DetectorConfig(camera_terms=camera_terms))
    blank = det.blank_image_bev
    assert blank.dtype == np.float32 and not blank.flags.writeable
    assert np.ptp(blank) > 0  # the lifter's biases: not an all-zero map
    for q in range(4):
        want = _lifter_on_zeros(export_path, det, q)
        assert blank.shape == want.shape
        np.testing.assert_allclose(blank, want, rtol=0, atol=1e-5 * max(float(np.ptp(want)), 1e-6))
    summary = det.stats.summary()
    assert "volumetric_lifter" not in summary and "lifter_tail" not in summary  # its run is not counted


def test_a_slice_before_any_image_reads_what_a_cleared_quadrant_reads(tiny_export, sample):
    fresh = StreamingDetector(tiny_export)
    cleared = StreamingDetector(tiny_export)
    q = 2
    others = [n for n in cleared.camera_names if n not in cleared.quadrant_cameras([q])]
    cleared.update_images(_images(cleared, 0), timestamp=0.5)  # every quadrant lifted, then q cleared
    update = cleared.update_images(_images(cleared, 1, others), timestamp=1.0)
    assert q in update.cleared and q not in update.quadrants and not update.superseded
    k, pts = _slice_in(q, sample.points)
    a = fresh.detect_slice(pts, k, timestamp=1.1)
    b = cleared.detect_slice(pts, k, timestamp=1.1)
    assert a.image_age_s is None and b.image_age_s is None and not a.fallback and not b.fallback
    assert _same(a.detections, b.detections)


def test_a_full_update_missing_a_quadrants_cameras_hands_its_slices_to_the_fallback(tiny_export, tiny_lidar_export, sample):
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=tiny_lidar_export))
    lidar = StreamingDetector(tiny_lidar_export)
    q = 3
    others = [n for n in det.camera_names if n not in det.quadrant_cameras([q])]
    update = det.update_images(_images(det, 0, others), timestamp=1.0)
    assert update.cleared == (q,) or q in update.cleared
    for k, pts in enumerate(split_sweep(sample.points, N_SLICES)):
        got = det.detect_slice(pts, k, timestamp=1.2)
        if q in quadrants_of_sector(k, N_SLICES, 0.0):  # fell back: no image age, the LiDAR-only graph's boxes
            assert got.fallback and got.image_age_s is None
            assert _same(got.detections, lidar.detect_slice(pts, k, timestamp=1.2).detections)
        elif not set(quadrants_of_sector(k, N_SLICES, 0.0)) & set(update.cleared):
            assert not got.fallback and got.image_age_s == pytest.approx(0.2)


def test_an_older_update_under_way_installs_nothing_in_a_quadrant_a_newer_one_cleared(tiny_export):
    det = StreamingDetector(tiny_export)
    q = 1
    others = [n for n in det.camera_names if n not in det.quadrant_cameras([q])]
    install = det._install
    newer = []

    def hooked(*args, **kwargs):  # the older update has encoded; the newer, given none of q's cameras, runs first
        det._install = install
        newer.append(det.update_images(_images(det, 1, others), timestamp=2.0))
        return install(*args, **kwargs)

    det._install = hooked
    older = det.update_images(_images(det, 0), timestamp=1.0)
    assert q in newer[0].cleared and newer[0].seq == older.seq + 1
    states = det.image_state.quadrants
    assert states[q] is None  # the older set is not installed where the newer one cleared
    for p in newer[0].quadrants:
        assert states[p].seq == newer[0].seq  # and never over the newer set elsewhere
    later = det.update_images(_images(det, 2), timestamp=3.0)  # a later update with q's cameras lifts it again
    assert q in later.quadrants and det.image_state.quadrants[q].timestamp == 3.0


def test_a_calibration_swap_during_a_clearing_update_plans_it_again(tiny_export):
    rig = load_bundled_sample().rig
    det = StreamingDetector(tiny_export)
    wider = det._build_lut(perturb_rig(rig, 0.8, 1.0, seed=WIDER_RIG_SEED))
    before = set(det.quadrant_cameras([3]))
    extra = [n for n in det._cameras_under(wider, (3,)) if n not in before]
    assert extra, "the premise: the wider rig's quadrant 3 reads a camera the bundled rig's does not"
    clear = det._clear_blind

    def swap_first(*args):  # the swap lands after the update planned quadrant 3 as blind
        det._clear_blind = clear
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # CameraMovedWarning, BlindCameraWarning
            det.set_calibration(wider)
        return clear(*args)

    det._clear_blind = swap_first
    update = det.update_images(_images(det, 0, extra[:1]), timestamp=1.0, quadrants=[3])
    assert update.quadrants == (3,) and update.cleared == () and not update.superseded
    assert det.image_state.quadrants[3] is not None and det.lut is wider


def test_close_lets_go_of_the_blank_bev_and_a_lidar_only_export_has_none(tiny_export, tiny_lidar_export):
    det = StreamingDetector(tiny_export)
    assert det.blank_image_bev is not None
    det.close()
    with pytest.raises(DetectorClosed):
        det.blank_image_bev
    with pytest.raises(NoImageLaneError):
        StreamingDetector(tiny_lidar_export).blank_image_bev


def test_an_update_that_gives_up_reports_the_quadrants_it_cleared(tiny_export):
    """A calibration swap during every attempt's lift: the update gives up installing, but the quadrant an attempt
    cleared is cleared, and the result says so (audit of the thirty-second session)."""
    det = StreamingDetector(tiny_export)
    q = 2
    det.update_images(_images(det, 0), timestamp=0.5)
    others = [n for n in det.camera_names if n not in det.quadrant_cameras([q])]
    luts = [det.lut, det._build_lut(perturb_rig(load_bundled_sample().rig, 0.01, 0.001, seed=3))]
    install = det._install
    swaps = []

    def swapping(*args, **kwargs):  # a calibration swap lands during every attempt's lift
        swaps.append(1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # CameraMovedWarning
            det.set_calibration(luts[len(swaps) % 2])
        return install(*args, **kwargs)

    det._install = swapping
    update = det.update_images(_images(det, 1, others), timestamp=1.0)
    det._install = install
    assert len(swaps) > 1 and update.superseded
    assert q in update.cleared and q not in update.quadrants
    assert det.image_state.quadrants[q] is None


def test_a_cleared_quadrants_slices_name_its_cameras_missing(tiny_export, sample):
    """A quadrant cleared because none of its cameras was given names them in cameras_missing (in the export's camera
    order); a quadrant without images for any other reason (none yet, forget_images) names none."""
    det = StreamingDetector(tiny_export)
    q = 2
    cams = det.quadrant_cameras([q])
    k, pts = _slice_in(q, sample.points)
    assert det.detect_slice(pts, k, timestamp=0.1).cameras_missing == ()  # no image yet: no camera is out
    others = [n for n in det.camera_names if n not in cams]
    det.update_images(_images(det, 0, others), timestamp=1.0)
    got = det.detect_slice(pts, k, timestamp=1.1)
    assert got.cameras_missing == cams and got.image_age_s is None
    det.update_images(_images(det, 1), timestamp=2.0)  # every camera again: nothing missing
    assert det.detect_slice(pts, k, timestamp=2.1).cameras_missing == ()
    det.forget_images(quadrants=[q])  # dropped, not out
    assert det.detect_slice(pts, k, timestamp=2.2).cameras_missing == ()
    det.forget_images(quadrants=[q], cameras_out=True)  # empty already, and now its cameras are out: named
    assert det.detect_slice(pts, k, timestamp=2.25).cameras_missing == cams
    det.update_images(_images(det, 3), timestamp=2.26)
    det.forget_images(quadrants=[q], cameras_out=True)  # the phase-locked lane: every camera of q timed out
    assert det.detect_slice(pts, k, timestamp=2.3).cameras_missing == cams
    det.forget_images()
    assert det.detect_slice(pts, k, timestamp=2.4).cameras_missing == ()
    # another quadrant's slice is untouched by q's record
    k0, pts0 = _slice_in(0, sample.points)
    det.update_images(_images(det, 2, others), timestamp=3.0)
    assert det.detect_slice(pts0, k0, timestamp=3.1).cameras_missing == tuple(c for c in det.camera_names
                                                                              if c in det.quadrant_cameras([0]) and c in cams)  # fmt: skip


@pytest.mark.parametrize("bad", [1, None, "yes"])
def test_forget_images_refuses_a_cameras_out_that_is_no_bool(tiny_export, bad):
    det = StreamingDetector(tiny_export)
    with pytest.raises(ValueError, match="cameras_out must be True or False"):
        det.forget_images(cameras_out=bad)


def test_an_older_drop_neither_names_nor_clears_the_cameras_out(tiny_export, sample):
    """Why a quadrant is empty is said by the newest drop there: an update cut off by forget_images() that clears the
    quadrant afterwards names no camera, and a forget of older image sets (warm_up's dummies) keeps the cameras a
    newer clear named."""
    det = StreamingDetector(tiny_export)
    q = 2
    cams = det.quadrant_cameras([q])
    others = [n for n in det.camera_names if n not in cams]
    k, pts = _slice_in(q, sample.points)
    old = det.update_images(_images(det, 0), timestamp=0.5)  # seq 1: every camera
    cleared = det.update_images(_images(det, 1, others), timestamp=1.0)  # seq 2 clears q
    assert q in cleared.cleared
    det.forget_images(through=old.seq)  # older than the clear: q's cameras stay named
    assert det.detect_slice(pts, k, timestamp=1.1).cameras_missing == cams
    det.forget_images()  # newer: q is empty because of it now
    assert det.detect_slice(pts, k, timestamp=1.2).cameras_missing == ()
    with det._lock:  # an update begun before that forget clearing q only now (as _clear_blind would, late)
        det._drop_images_locked(cleared.seq - 1, (q,), cameras_out=True)
    assert det.detect_slice(pts, k, timestamp=1.3).cameras_missing == ()


def test_a_full_schedule_runner_counts_the_quadrants_its_updates_cleared(tiny_export):
    from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner

    det = StreamingDetector(tiny_export)
    q = 2
    others = [n for n in det.camera_names if n not in det.quadrant_cameras([q])]
    with StreamingRunner(det, LaneConfig()) as runner:
        assert runner.quadrants_cleared == 0
        runner.submit_images(_images(det, 0), timestamp=1.0).result(timeout=60)
        assert runner.quadrants_cleared == 0
        update = runner.submit_images(_images(det, 1, others), timestamp=2.0).result(timeout=60)
        assert q in update.cleared and runner.quadrants_cleared == len(update.cleared)
