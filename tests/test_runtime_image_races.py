"""The image lane's races with the caller's other threads, made deterministic by hooking the moment between an
update's encoding and its install: a drop (forget_images, set_calibration(relift=False)) is never undone by an update
already under way; warm_up drops only its own dummy images; a calibration swap re-stamps re-lifted quadrants from the
cameras the new LUT reads, encodes a camera a racing per-quadrant update was given but had not planned for, and builds
the new LUT's per-quadrant tables in the caller's thread; close() releases the LiDAR-only fallback's session."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from streamdet.calibration.perturb import perturb_rig
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort import detector as detector_module
from streamdet.runtime_ort import lut_views
from streamdet.runtime_ort.detector import DetectorClosed, DetectorConfig, StreamingDetector

# A rig under which quadrant 3 of the tiny grid reads one camera more than under the bundled one (found by search,
# asserted below: the tests' premise).
WIDER_RIG_SEED = 1


@pytest.fixture(scope="module")
def rigs():
    rig = load_bundled_sample().rig
    return rig, perturb_rig(rig, 0.8, 1.0, seed=WIDER_RIG_SEED)


def _images(det: StreamingDetector, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}


def _detector(export_dir, rig=None) -> StreamingDetector:
    det = StreamingDetector(export_dir)
    if rig is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # CameraMovedWarning, BlindCameraWarning
            det.set_calibration(rig)
    return det


def _before_install(det: StreamingDetector, action, times: int = 1) -> None:
    """Run ``action`` once an update has encoded, just before it lifts and installs (the first ``times`` updates)."""
    install = det._install
    left = [times]

    def hooked(*args, **kwargs):
        if left[0] > 0:
            left[0] -= 1
            action()
        return install(*args, **kwargs)

    det._install = hooked


@pytest.mark.parametrize("quadrants", [None, [1]])
def test_forget_during_an_update_is_not_undone(tiny_export, quadrants):
    det = _detector(tiny_export)
    _before_install(det, det.forget_images)
    update = det.update_images(_images(det, 0), 1.0, quadrants=quadrants)
    assert update.superseded and det.image_state is None
    later = det.update_images(_images(det, 1), 2.0, quadrants=quadrants)  # the next update installs as ever
    assert not later.superseded and later.seq == update.seq + 1 and det.image_state.seq == later.seq


def test_calibration_without_relift_during_an_update_drops_it(tiny_export, rigs):
    det = _detector(tiny_export, rigs[0])
    other = det._build_lut(rigs[1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _before_install(det, lambda: det.set_calibration(other, relift=False))
        update = det.update_images(_images(det, 0), 1.0)
    assert update.superseded and det.image_state is None  # its images are of the old rig: never lifted with the new LUT
    assert det.lut is other


def test_forget_through_keeps_newer_sets(tiny_export):
    det = _detector(tiny_export)
    first = det.update_images(_images(det, 0), 1.0)
    second = det.update_images(_images(det, 1), 2.0, quadrants=[2])
    det.forget_images(through=first.seq)
    kept = det.image_state.quadrants
    assert kept[2] is not None and kept[2].seq == second.seq and all(kept[q] is None for q in (0, 1, 3))
    det.forget_images(through=second.seq)
    assert det.image_state is None
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="forget_images through"):
            det.forget_images(through=bad)


def test_warm_up_keeps_a_real_set_that_came_meanwhile(tiny_export):
    det = _detector(tiny_export)
    real = _images(det, 3)
    sweep = det.detect_sweep
    came: list = []

    def sweep_then_real(*args, **kwargs):  # warm_up's last step before it forgets: a runner's images arrive
        out = sweep(*args, **kwargs)
        came.append(det.update_images(real, 5.0))
        return out

    det.detect_sweep = sweep_then_real
    det.warm_up(rounds=1)
    assert len(came) == 1 and not came[0].superseded
    assert det.image_state is not None and det.image_state.seq == came[0].seq and det.image_timestamp == 5.0


def test_warm_up_says_when_a_real_set_was_lost_to_its_black_images(tiny_export):
    det = _detector(tiny_export)
    sweep = det.detect_sweep
    came: list = []

    def sweep_then_real(*args, **kwargs):  # a lane's images between warm_up's rounds: the next round replaces them
        if not came:
            came.append(det.update_images(_images(det, 3), 5.0))
        return sweep(*args, **kwargs)

    det.detect_sweep = sweep_then_real
    with pytest.warns(RuntimeWarning, match="1 update_images call.* during warm_up"):
        det.warm_up(rounds=2)
    assert det.image_state is None


def test_relift_restamps_from_the_new_luts_cameras(tiny_export, rigs):
    rig_a, rig_b = rigs
    det = _detector(tiny_export, rig_a)
    before = det.quadrant_cameras([3])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fresh = _detector(tiny_export, rig_b)
    added = [n for n in fresh.quadrant_cameras([3]) if n not in before]
    assert added, "premise: rig B widens quadrant 3's view"
    images = _images(det, 0)
    stamps = {n: 10.0 for n in det.camera_names}
    stamps[added[0]] = 9.5  # the camera quadrant 3 reads under rig B only fired earlier
    det.update_images(images, 10.0, camera_timestamps=stamps)
    assert det.image_timestamps[3] == 10.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        det.set_calibration(rig_b)
    fresh.update_images(images, 10.0, camera_timestamps=stamps)
    assert det.image_timestamps == fresh.image_timestamps and det.image_timestamps[3] == 9.5
    assert np.array_equal(det.image_state.bev, fresh.image_state.bev)


def test_per_quadrant_update_racing_a_swap_encodes_the_camera_it_was_given(tiny_export, rigs):
    rig_a, rig_b = rigs
    det = _detector(tiny_export, rig_a)
    lut_b = det._build_lut(rig_b)
    planned = det.quadrant_cameras([3])
    images = _images(det, 0)
    stamps = {n: 10.0 - 0.1 * i for i, n in enumerate(det.camera_names)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _before_install(det, lambda: det.set_calibration(lut_b))
        update = det.update_images(images, 10.0, quadrants=[3], camera_timestamps=stamps)
        fresh = _detector(tiny_export, rig_b)
    wider = fresh.quadrant_cameras([3])
    assert set(wider) > set(planned), "premise: rig B widens quadrant 3's view"
    assert update.cameras_used == wider and update.cameras_missing == () and not update.superseded
    fresh.update_images(images, 10.0, quadrants=[3], camera_timestamps=stamps)
    ours, theirs = det.image_state.quadrants[3], fresh.image_state.quadrants[3]
    assert ours.feature_cameras == theirs.feature_cameras and ours.timestamp == theirs.timestamp
    assert np.array_equal(ours.bev, theirs.bev)


@pytest.mark.parametrize("quadrants", [None, [3]])
def test_an_update_gives_up_when_the_calibration_is_swapped_during_every_lift(tiny_export, rigs, quadrants, caplog):
    """A caller swapping calibrations faster than one lift: the update lifts again at most MAX_RELIFTS_PER_UPDATE
    times, then installs nothing and says so (it lifted for ever before); the cache keeps no old calibration's BEV."""
    det = _detector(tiny_export, rigs[0])
    luts = [det._build_lut(rig) for rig in rigs]
    lift = det._lift_quadrants
    lifts = [0]

    def swapping(*args, **kwargs):
        lifts[0] += 1
        out = lift(*args, **kwargs)
        det.set_calibration(luts[lifts[0] % 2])  # no images yet: nothing to re-lift
        return out

    det._lift_quadrants = swapping
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        update = det.update_images(_images(det, 0), 1.0, quadrants=quadrants)
    assert update.superseded
    assert det.image_state is None or all(s is None for s in det.image_state.quadrants)
    assert 1 <= lifts[0] <= detector_module.MAX_RELIFTS_PER_UPDATE + 1
    assert "given up" in caplog.text
    det._lift_quadrants = lift  # swaps stop: the next update lands
    assert not det.update_images(_images(det, 1), 2.0, quadrants=quadrants).superseded


def test_set_calibration_builds_the_quadrant_tables_in_the_callers_thread(tiny_export, rigs, monkeypatch):
    det = _detector(tiny_export, rigs[0])
    det.update_images(_images(det, 0), 1.0, quadrants=[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        det.set_calibration(rigs[1])
    built: list = []
    monkeypatch.setattr(lut_views, "quadrant_luts", lambda lut: built.append(lut))  # would fail if called
    for q in range(4):
        det.quadrant_cameras([q])
    det.update_images(_images(det, 1), 2.0, quadrants=[1])
    assert built == []


def test_close_releases_the_fallback_session(tiny_export, tiny_lidar_export):
    det = StreamingDetector(tiny_export, DetectorConfig(fallback_export_dir=tiny_lidar_export))
    assert det._fallback.session is not None
    det.close()
    assert det._fallback.session is None
    with pytest.raises(DetectorClosed):
        det.detect_slice(split_sweep(load_bundled_sample().points, 8)[0], 0)  # no images: the fallback's graph


def test_a_relift_that_widens_a_quadrant_says_the_camera_it_did_not_encode_is_missing(tiny_export, rigs):
    """A per-quadrant update kept only the cameras the old LUT read there: re-lifted with a LUT that reads one more,
    that camera is zeros, and its slices say so (they said nothing missing)."""
    rig_a, rig_b = rigs
    det = _detector(tiny_export, rig_a)
    before = det.quadrant_cameras([3])
    det.update_images(_images(det, 0), 1.0, quadrants=[3])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        det.set_calibration(rig_b)
    added = tuple(n for n in det.quadrant_cameras([3]) if n not in before)
    assert added, "premise: rig B widens quadrant 3's view"
    assert det.image_state.quadrants[3].cameras_missing == added
    full = _detector(tiny_export, rig_a)
    full.update_images(_images(full, 0), 1.0)  # a full update holds every camera's map: nothing missing after a swap
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full.set_calibration(rig_b)
    assert all(s.cameras_missing == () for s in full.image_state.quadrants)


def _hold_lut_builds(det: StreamingDetector, first_only: bool = True):
    """(started, release) events: the first set_calibration's LUT build waits for ``release`` once it started."""
    import threading

    started, release, build = threading.Event(), threading.Event(), det._build_lut
    calls = [0]

    def held(rig):
        calls[0] += 1
        if calls[0] == 1 or not first_only:
            started.set()
            assert release.wait(30)
        return build(rig)

    det._build_lut = held
    return started, release


def _in_thread(fn):
    import threading

    out: dict = {}

    def run():
        try:
            out["result"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the test
            out["error"] = e

    t = threading.Thread(target=run)
    t.start()
    return t, out


def _held_swap(export_dir, rigs):
    """(detector on rig A with an image set, its LUT, the thread of a swap to rig B whose LUT build is held, that
    thread's outcome, the event releasing the build)."""
    rig_a, rig_b = rigs
    det = _detector(export_dir, rig_a)
    lut_a = det.lut
    det.update_images(_images(det, 0), 1.0)
    started, release = _hold_lut_builds(det)
    swap, out = _in_thread(lambda: det.set_calibration(rig_b))
    assert started.wait(30)
    return det, lut_a, swap, out, release


@pytest.mark.parametrize("later", ["another rig", "the rig in use again", "a Lut"])
def test_the_calibration_call_started_last_wins(tiny_export, rigs, later):
    """Two threads swapping: a call started earlier whose LUT build ends later installed last, over the newer one."""
    rig_a = rigs[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        det, lut_of_a, slow, out, release = _held_swap(tiny_export, rigs)  # started first, its build held
        newer = {"another rig": perturb_rig(rig_a, 0.5, 0.5, seed=7), "the rig in use again": rig_a,
                 "a Lut": det._build_lut(rig_a)}[later]  # fmt: skip
        det.set_calibration(newer)
        in_use = det.lut
        release.set()
        slow.join(30)
    assert "error" not in out
    assert det.lut is in_use  # the older call installed nothing
    if later == "the rig in use again":
        assert det.lut is lut_of_a
    assert all(s.lut is det.lut for s in det.image_state.quadrants)


def test_a_calibration_swap_racing_close_installs_nothing_and_a_closed_detector_keeps_nothing(tiny_export, rigs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        det, lut_a, swap, out, release = _held_swap(tiny_export, rigs)
        det.close()
        release.set()
        swap.join(30)
    assert isinstance(out.get("error"), DetectorClosed) and det.lut is lut_a
    with pytest.raises(DetectorClosed):
        det.update_images(_images(det, 1), 2.0, quadrants=[3])  # it made the views it needed before it failed
    views = det._views
    assert views._quadrant_luts == {} and views._cameras is None and views._feeds == {}


def test_a_failed_relift_drops_the_old_bev_rather_than_keep_it_under_the_new_lut(tiny_export, rigs):
    rig_a, rig_b = rigs
    det = _detector(tiny_export, rig_a)
    det.update_images(_images(det, 0), 1.0)
    lift = det._lift_quadrants

    def failing(*args, **kwargs):
        raise RuntimeError("volumetric_lifter.onnx: onnxruntime failed (injected)")

    det._lift_quadrants = failing
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(RuntimeError, match="injected"):
            det.set_calibration(rig_b)
        lut_b = det.lut
        assert det.image_state is None  # not the old rig's BEV under the new LUT
        det._lift_quadrants = lift
        det.set_calibration(rig_b)  # the rig in use: nothing to do, and nothing stale left
    assert det.lut is lut_b and det.image_state is None
    det.update_images(_images(det, 1), 2.0)
    assert all(s.lut is lut_b for s in det.image_state.quadrants)
