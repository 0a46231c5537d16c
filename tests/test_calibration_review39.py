"""Review 39 of calibration/: a LUT of another kind than the export's is refused (export_open.check_lut), a Lut
given to a detector cannot be changed through the caller's arrays, and LUT builds refuse up front what they cannot
hold (more cameras than a uint8 counts, feature rows past int32, image sizes that are not whole pixels). Each op
next to a naive reference, and the malformed inputs."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import warnings

import numpy as np
import pytest

from streamdet.calibration import lut_build as lut_module
from streamdet.calibration.camera import CalibrationError, Camera, Rig, make_transform
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import CameraMovedWarning, Lut, LutFileError
from streamdet.calibration.lut_build import MAX_LUT_CAMERAS, build_lut
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.export_open import EXPORT_LUT_MIN_DEPTH_M, check_lut

TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)


@pytest.fixture(scope="module")
def detector(tiny_export):
    det = StreamingDetector(tiny_export, DetectorConfig(camera_terms=False))
    yield det
    det.close()


def _export_kind_lut(det: StreamingDetector, **kind) -> Lut:
    """The bundled rig's LUT for ``det``'s export, of the kind ``kind`` says (heights_per_voxel, min_depth_m)."""
    img = det.image
    return build_lut(load_bundled_sample(None).rig, det.grid, img.feature_stride, (img.width, img.height), **kind)


def _images(det: StreamingDetector, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}


# ---- M3: a LUT of another kind -----------------------------------------------------------------------------------

@pytest.mark.parametrize("kind, pattern", [
    ({"heights_per_voxel": 2}, r"heights per voxel 2 != the export's 1 \(manifest preset\.lifter\.lut_heights_per_voxel\)"),
    ({"heights_per_voxel": 8}, r"heights per voxel 8 != the export's 1"),
    ({"min_depth_m": 40.0}, r"min depth 40 m != the 0 m every export's LUT is built with"),
    ({"min_depth_m": 0.5, "heights_per_voxel": 3}, r"heights per voxel 3 != the export's 1 .*; min depth 0\.5 m != the 0 m"),
], ids=["heights-2", "heights-8", "min-depth-40", "both"])  # fmt: skip
def test_set_calibration_refuses_a_lut_of_another_kind(detector, tmp_path, kind, pattern):
    in_use = detector.lut
    other = _export_kind_lut(detector, **kind)
    with pytest.raises(CalibrationError, match=r"the LUT does not fit the graphs: .*" + pattern):
        detector.set_calibration(other)
    other.save(tmp_path / "lut.npz")
    with pytest.raises(CalibrationError, match=pattern):  # the same from a file
        detector.set_calibration(tmp_path / "lut.npz")
    assert detector.lut is in_use


def test_the_export_kind_is_accepted_and_the_check_reads_the_manifest(detector):
    same = _export_kind_lut(detector)
    assert (same.heights_per_voxel, same.min_depth_m) == (1, EXPORT_LUT_MIN_DEPTH_M) == (1, 0.0)
    m = detector.manifest
    assert check_lut(same, detector.image, detector.camera_names, detector.grid, detector.export_dir, m) is same
    lifter = m.preset.get("lifter", {})
    assert lifter.get("lut_heights_per_voxel", 1) == 1  # the tiny preset: absent, so the default 1
    # the manifest decides: one that says 2 heights refuses this LUT and takes a 2-height one
    two = dataclasses.replace(m, preset={**m.preset, "lifter": {**lifter, "lut_heights_per_voxel": 2}})
    with pytest.raises(CalibrationError, match=r"heights per voxel 1 != the export's 2"):
        check_lut(same, detector.image, detector.camera_names, detector.grid, detector.export_dir, two)
    tall = _export_kind_lut(detector, heights_per_voxel=2)
    assert check_lut(tall, detector.image, detector.camera_names, detector.grid, detector.export_dir, two) is tall


def test_an_export_whose_lut_file_is_of_another_kind_does_not_open(tiny_export, tmp_path):
    export = tmp_path / "export"
    shutil.copytree(tiny_export, export)
    det = StreamingDetector(export, DetectorConfig(camera_terms=False))
    _export_kind_lut(det, heights_per_voxel=2).save(export / "lut.npz")
    det.close()
    with pytest.raises(CalibrationError, match=r"heights per voxel 2 != the export's 1"):
        StreamingDetector(export, DetectorConfig(verify_sha256=False))  # unhashed: the kind check is what stops it


# ---- M2: the detector's LUT cannot change under it -----------------------------------------------------------------

def test_editing_the_callers_arrays_after_set_calibration_changes_nothing(tiny_export):
    det = StreamingDetector(tiny_export, DetectorConfig(camera_terms=False))
    built = _export_kind_lut(det)
    index, weight = built.index.copy(), built.weight.copy()  # the caller's writable buffers
    mine = Lut(index, weight, built.grid, built.feature_stride, built.image_width, built.image_height,
               built.camera_names, built.calibration_sha256)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CameraMovedWarning)
        det.set_calibration(mine)
    det.update_images(_images(det), timestamp=1.0)
    quadrant_cameras = [q.camera_names for q in det._luts_of(det.lut)]
    index[...] = np.int32(10**9)  # out of range: would reach the lifter's Gather unchecked
    weight[...] = 0.0
    assert det.lut is mine and np.array_equal(det.lut.index, built.index) and np.array_equal(det.lut.weight, built.weight)
    assert [q.camera_names for q in det._luts_of(det.lut)] == quadrant_cameras
    det.update_images(_images(det, 1), timestamp=2.0)  # lifts with the validated tables
    det.close()


# ---- L2: more cameras than a uint8 counts, feature rows past int32 -----------------------------------------------

def _front_copies(n: int, width: int = 64, height: int = 36) -> Rig:
    front = load_bundled_sample(None).rig.cameras[0].resized(width, height)
    cams = tuple(Camera(f"C{j}", front.K, front.lidar2cam, width, height) for j in range(n))
    return Rig(cams, np.eye(4), np.eye(4))


def test_255_cameras_count_without_wrapping_and_256_are_refused(monkeypatch):
    rig = _front_copies(MAX_LUT_CAMERAS)
    lut = build_lut(rig, TINY)
    one = build_lut(_front_copies(1), TINY)  # the naive reference: 255 copies see what one sees, each
    seen = one.index[:, 0] != one.sentinel  # (4, Z, Yq, Xq)
    assert seen.any() and not seen.all()
    assert lut.num_slots == MAX_LUT_CAMERAS == 255
    cells = lut.feature_height * lut.feature_width
    for j in (0, 1, 254):  # slot j reads copy j's row of the same cell
        assert np.array_equal(lut.index[:, j][seen], one.index[:, 0][seen] + j * cells)
    by_slot = lut.index.swapaxes(0, 1)  # (K, 4, Z, Yq, Xq)
    assert np.all(by_slot[:, ~seen] == lut.sentinel)
    np.testing.assert_allclose(lut.weight.swapaxes(0, 1)[:, seen], np.float32(1 / 255))
    monkeypatch.setattr(lut_module, "_project_camera", lambda *a, **k: pytest.fail("projected before refusing"))
    for heights in (1, 2):
        with pytest.raises(ValueError, match=r"a LUT takes at most 255 cameras \(MAX_LUT_CAMERAS\), the rig has 256"):
            build_lut(_front_copies(256), TINY, heights_per_voxel=heights)


def _giant_cameras(n: int, side: int = 65536) -> Rig:
    K = [[side / 2, 0, side / 2], [0, side / 2, side / 2], [0, 0, 1]]
    look_x = make_transform([[0, -1, 0], [0, 0, -1], [1, 0, 0]], [0, 0, 0])  # camera z along LiDAR x
    return Rig(tuple(Camera(f"G{j}", K, look_x, side, side) for j in range(n)), np.eye(4), np.eye(4))


def test_feature_rows_past_int32_are_refused_naming_cameras_size_and_stride(monkeypatch):
    rows = 8 * math.ceil(65536 / 4) ** 2
    assert rows == 2**31  # one past int32's largest
    project = lut_module._project_camera
    monkeypatch.setattr(lut_module, "_project_camera", lambda *a, **k: pytest.fail("projected before refusing"))
    with pytest.raises(ValueError, match=rf"8 cameras of 65536x65536 images at feature stride 4 make a feature table of {rows} "
                                         r"rows, past the int32 row indices of a LUT \(2147483647\)"):  # fmt: skip
        build_lut(_giant_cameras(8), TINY, 4)
    with pytest.raises(ValueError, match=r"8 cameras of 65536x65536 images at feature stride 4"):
        build_lut(_giant_cameras(8), TINY, 4, heights_per_voxel=2)
    monkeypatch.setattr(lut_module, "_project_camera", project)
    lut = build_lut(_giant_cameras(7), TINY, 4)  # 7 cameras: rows up to 7 * 2**28 - 1 fit
    assert lut.sentinel == 7 * 2**28 and lut.index.dtype == np.int32 and int(lut.index.max()) == lut.sentinel
    assert build_lut(_giant_cameras(8), TINY, 8).sentinel == 2**29  # a coarser stride fits too


# ---- L3: image sizes in whole pixels, .NPZ, camera names -----------------------------------------------------------

@pytest.mark.parametrize("image_size, pattern", [
    ((800.9, 450.9), r"image_size width: expected a positive integer pixel count up to 65536, got 800\.9"),
    ((np.float64(800.7), 450), r"image_size width: .*got np\.float64\(800\.7\)"),
    ((800, 450.0), r"image_size height: .*got 450\.0"),
    (("800", "450"), r"image_size width: .*got '800'"),
    ((True, 450), r"image_size width: .*got True"),
    ((0, 450), r"image_size width: .*got 0"),
    ((800, 65537), r"image_size height: .*got 65537"),
    ("80", r"image_size must be \(W, H\), got '80'"),
], ids=["floats", "np-float", "float-height", "strings", "bool", "zero", "too-big", "a-string"])  # fmt: skip
def test_image_size_must_be_whole_pixels(image_size, pattern):
    rig = load_bundled_sample(None).rig
    with pytest.raises(ValueError, match=pattern):
        build_lut(rig, TINY, image_size=image_size)
    with pytest.raises(ValueError, match=pattern):
        build_lut(rig, TINY, image_size=image_size, heights_per_voxel=2)


def test_integer_image_sizes_of_any_integer_type_build_the_same_lut():
    rig = load_bundled_sample(None).rig
    plain = build_lut(rig, TINY, image_size=(64, 36))
    for size in ((np.int64(64), np.int32(36)), [64, 36], np.array([64, 36])):
        lut = build_lut(rig, TINY, image_size=size)
        assert (lut.image_width, lut.image_height) == (64, 36) and type(lut.image_width) is int
        assert np.array_equal(lut.index, plain.index) and np.array_equal(lut.weight, plain.weight)


def test_set_calibration_reads_an_upper_case_npz_suffix_as_a_lut(detector, tmp_path):
    in_use = detector.lut
    in_use.save(tmp_path / "lut.NPZ")
    detector.set_calibration(tmp_path / "lut.NPZ")  # not parsed as JSON ("not UTF-8 text")
    assert np.array_equal(detector.lut.index, in_use.index) and detector.lut is not in_use
    (tmp_path / "broken.Npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(LutFileError, match=r"broken\.Npz: not a readable LUT \.npz"):
        detector.set_calibration(str(tmp_path / "broken.Npz"))
    detector.set_calibration(in_use)


@pytest.mark.parametrize("names, pattern", [
    (["CAM\n\x1b[31mX"], r"Lut\.camera_names\[0\]: expected a non-empty printable string, got 'CAM\\n\\x1b\[31mX'"),
    (["A", "B\tC"], r"Lut\.camera_names\[1\]: expected a non-empty printable string, got 'B\\tC'"),
])  # fmt: skip
def test_lut_camera_names_must_be_printable(tmp_path, names, pattern):
    rig = _front_copies(len(names))
    lut = build_lut(rig, TINY)
    with pytest.raises(CalibrationError, match=pattern):
        Lut(lut.index, lut.weight, TINY, 4, lut.image_width, lut.image_height, names, lut.calibration_sha256)
    # a lut.npz whose meta names such a camera: refused naming the file
    meta = lut.meta() | {"camera_names": names}
    with open(tmp_path / "lut.npz", "wb") as f:
        np.savez(f, index=lut.index, weight=lut.weight, meta=np.array(json.dumps(meta)))
    with pytest.raises(CalibrationError, match=r"lut\.npz: " + pattern):
        Lut.load(tmp_path / "lut.npz")
