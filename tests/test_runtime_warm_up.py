"""StreamingDetector.warm_up (runtime_ort/warm_up.py): every graph run on dummy inputs, nothing of it left behind."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.pipeline import detect_sample
from streamdet.runtime_ort.warm_up import dummy_sweep


@pytest.mark.parametrize("seed", [0, 1])
def test_dummy_sweep_lies_inside_the_grid_around_the_sensor(seed):
    pts = dummy_sweep((-12.8, 12.8), 500, seed)
    assert pts.shape == (500, 5) and pts.dtype == np.float32
    assert np.abs(pts[:, :2]).max() < 12.8 and np.hypot(pts[:, 0], pts[:, 1]).min() >= 2.0
    quadrant = (pts[:, 0] >= 0).astype(int) * 2 + (pts[:, 1] >= 0).astype(int)
    assert set(quadrant.tolist()) == {0, 1, 2, 3}  # every quadrant, hence every slice, has points


@pytest.mark.parametrize("fixture", ["tiny_export", "tiny_lidar_export"])
def test_warm_up_leaves_no_image_no_stats_and_the_same_detections(fixture, request):
    export = request.getfixturevalue(fixture)
    sample = load_bundled_sample()
    warm, cold = StreamingDetector(export), StreamingDetector(export)
    warm.warm_up()
    assert warm.image_state is None and warm.stats.summary() == {}
    a, b = detect_sample(warm, sample).detections, detect_sample(cold, sample).detections
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)


@pytest.mark.parametrize("bad", [0, -1, np.int64(0), 1.5, True, "2", None])
def test_warm_up_rounds_must_be_a_positive_int(tiny_export, bad):
    """warm_up(0) is no "warm nothing": refused as any other count below 1, the value quoted, the detector left as it was."""
    with StreamingDetector(tiny_export) as det:
        with pytest.raises(ValueError, match=r"warm_up rounds must be an int >= 1, got ") as e:
            det.warm_up(bad)
        assert str(e.value).endswith(repr(bad))
        assert det.stats.summary() == {} and det.image_state is None
