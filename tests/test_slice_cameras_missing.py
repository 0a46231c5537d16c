"""SliceResult.cameras_missing: a camera out (not given to the image update) shows in the slices that read it; under
the "full" schedule its features are zeros while the quadrant's image age stays that of the cameras given (found by a
soak of the runtime)."""

from __future__ import annotations

import numpy as np

from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector


def _images(det):
    img = det.image
    return {c: np.full((img.height, img.width, 3), 100, np.uint8) for c in det.camera_names}


def test_a_slice_names_the_cameras_missing_from_the_bev_it_read(tiny_export):
    out = "CAM_FRONT"
    with StreamingDetector(tiny_export, DetectorConfig()) as det:
        slices = split_sweep(load_bundled_sample().points, det.num_slices)
        images = _images(det)
        det.update_images(images, timestamp=0.0)
        assert all(det.detect_slice(p, k, 0.01).cameras_missing == () for k, p in enumerate(slices))
        det.update_images({c: a for c, a in images.items() if c != out}, timestamp=0.1)
        named = 0
        for k, p in enumerate(slices):
            result = det.detect_slice(p, k, 0.11)
            reads_front = out in det.quadrant_cameras(list(quadrants_of_sector(k, det.num_slices)))
            assert result.cameras_missing == ((out,) if reads_front else ()), (k, result.cameras_missing)
            assert result.image_age_s is not None and abs(result.image_age_s - 0.01) < 1e-9  # the age does not show it
            named += reads_front
        assert named > 0  # the front camera's quadrants
        det.update_images(images, timestamp=0.2)  # back again
        assert all(det.detect_slice(p, k, 0.21).cameras_missing == () for k, p in enumerate(slices))
