"""set_calibration with the rig already in use (a vehicle republishing an unchanged calibration) changes nothing and
costs no LUT build or re-lift; any other rig swaps as before (found by a soak of the runtime)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.export_settings import export_rig


def _images(det):
    img = det.image
    return {c: np.full((img.height, img.width, 3), 100, np.uint8) for c in det.camera_names}


@pytest.fixture
def det(tiny_export):
    d = StreamingDetector(tiny_export, DetectorConfig())
    d.update_images(_images(d), timestamp=1.0)
    yield d
    d.close()


def test_the_rig_in_use_again_changes_nothing(det, monkeypatch):
    rig = export_rig(det.manifest, det.export_dir)
    det.set_calibration(rig)  # the export's lut.npz may have been built otherwise: this once, built here
    lut, image = det._lut, det._image
    built = []
    monkeypatch.setattr(det, "_build_lut", lambda r: built.append(r))
    det.set_calibration(rig)
    det.set_calibration(dataclasses.replace(rig))  # an equal rig, another object (as a message decoder makes)
    assert built == [] and det._lut is lut and det._image is image  # no build, no re-lift


def test_a_lut_read_from_a_file_is_never_taken_for_the_rig(det):
    """The export's lut.npz (or a Lut handed over) may have other heights or depths than this detector builds."""
    rig = export_rig(det.manifest, det.export_dir)
    lut = det._lut  # read from the export's lut.npz
    assert lut.calibration_sha256 == rig.sha256()
    det.set_calibration(rig)
    assert det._lut is not lut  # built from the rig, once


def test_another_rig_still_swaps(det):
    rig = export_rig(det.manifest, det.export_dir)
    cam = rig.cameras[0]
    focal = cam.K.copy()
    focal[:2, :2] *= 1.001  # a focal length refined a little
    moved = dataclasses.replace(rig, cameras=(dataclasses.replace(cam, K=focal), *rig.cameras[1:]))
    assert moved.sha256() != rig.sha256()
    lut = det._lut
    det.set_calibration(moved)
    assert det._lut is not lut and det._lut.calibration_sha256 == moved.sha256()
    det.set_calibration(rig)  # and back: the rig in use is the moved one now, so this swaps too
    assert det._lut.calibration_sha256 == rig.sha256()


def test_the_rig_in_use_with_relift_false_still_drops_the_images(det):
    rig = export_rig(det.manifest, det.export_dir)
    det.set_calibration(rig, relift=False)
    assert all(s is None for s in det._image.quadrants) if det._image is not None else True

