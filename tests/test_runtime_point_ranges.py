"""Points with a reflectance, time or slice index outside their ranges (core/points.py) never reach the net: the
detector drops and counts them, says so once in its log, and no box comes of them."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from streamdet.core.points import MAX_POINT_TIME_S
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector


@pytest.fixture(scope="module")
def detector(tiny_export):
    return StreamingDetector(tiny_export)


@pytest.mark.parametrize(
    "column, value",
    [(3, 1e6), (3, 1e10), (3, -0.5), (4, 1e6), (4, MAX_POINT_TIME_S * 2), (4, -1.0), (5, 1e6), (5, 4096.0), (5, -1.0)],
)
def test_one_corrupted_point_is_dropped_and_counted_not_detected(detector, column, value):
    point = np.array([[20.0, 5.0, 0.0, 0.5, 0.01, 0.0]], np.float32)  # slice 0 of 8: x > 0, a small positive azimuth
    point[0, column] = value
    res = detector.detect_slice(point, 0)
    assert res.num_outside_dropped == 1 and res.num_pillars == 0 and len(res.detections) == 0


def test_a_real_slice_with_corrupted_points_keeps_the_rest_and_warns_once(tiny_export, caplog):
    det = StreamingDetector(tiny_export)
    sample = load_bundled_sample()
    slices = split_sweep(sample.points, det.num_slices)
    clean = det.detect_slice(slices[2], 2)
    bad = slices[2].copy()
    rows = np.arange(0, len(bad), 7)
    bad[rows, 3] = 300.0  # an unscaled intensity, as a 16-bit sensor would give
    with caplog.at_level(logging.WARNING, logger="streamdet.runtime_ort.detector"):
        first = det.detect_slice(bad, 2)
        det.detect_slice(bad, 2)
    assert first.num_outside_dropped >= clean.num_outside_dropped + 1
    dropped = first.num_outside_dropped - clean.num_outside_dropped
    assert 0 < dropped <= len(rows) and first.num_pillars > 0
    warnings = [r for r in caplog.records if "reflectance outside" in r.getMessage()]
    assert len(warnings) == 1 and "intensity_scale" in warnings[0].getMessage()
