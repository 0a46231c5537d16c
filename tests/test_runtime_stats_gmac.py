"""GMAC executed and achieved GFLOP/s in the runtime's stage statistics."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.runtime_ort.stats import LatencyStats


@pytest.mark.parametrize("seed", [0, 1])
def test_gflops_is_twice_the_gmac_over_the_total_time(seed):
    rng = np.random.default_rng(seed)
    stats = LatencyStats(capacity=4)  # the totals cover every run, not only the buffer's
    ms = rng.uniform(1.0, 5.0, 10)
    gmac = rng.uniform(0.1, 2.0, 10)
    for t, g in zip(ms, gmac):
        stats.record("slice_head", t, g)
    s = stats.summary()["slice_head"]
    assert s["gmac_total"] == pytest.approx(gmac.sum())
    assert s["gmac_per_run"] == pytest.approx(gmac.mean())
    assert s["gflop_per_s"] == pytest.approx(2 * gmac.sum() / (ms.sum() / 1e3))


def test_stages_without_work_have_no_flops_keys():
    stats = LatencyStats()
    stats.record("pre", 1.0)
    with stats.time("post", gmac=None):
        pass
    assert not {"gmac_total", "gflop_per_s"} & (set(stats.summary()["pre"]) | set(stats.summary()["post"]))


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_bad_gmac_is_refused(bad):
    with pytest.raises(ValueError, match="gmac"):
        LatencyStats().record("x", 1.0, bad)


def test_detector_reports_the_gmac_of_the_sizes_it_ran(tiny_export):
    from streamdet.data.sample import load_bundled_sample
    from streamdet.data.slicing import split_sweep
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    m = det.manifest
    img = det.image
    sample = load_bundled_sample()
    images = sample.load_images((img.width, img.height))
    update = det.update_images({n: images[j] for j, n in enumerate(sample.rig.names) if n in det.camera_names[:3]})
    slices = split_sweep(sample.points, 8)
    det.detect_slice(slices[0], 0)  # one quadrant
    det.detect_sweep(sample.points, num_slices=1)  # four quadrants
    s = det.stats.summary()
    enc = m.graph("image_encoder")
    expected_enc = enc.gmac * 3 / enc.gmac_at["J"] * (img.width * img.height) / (enc.gmac_at["W"] * enc.gmac_at["H"])
    assert s["image_encoder"]["gmac_total"] == pytest.approx(expected_enc)
    lifter = m.graph("volumetric_lifter")
    # the quadrants none of the three cameras sees are cleared, not lifted
    assert len(update.quadrants) + len(update.cleared) == 4 and update.quadrants
    assert s["volumetric_lifter"]["gmac_total"] == pytest.approx(lifter.gmac * len(update.quadrants) / lifter.gmac_at["Q"])
    head = m.graph("slice_head")
    assert s["slice_head"]["gmac_total"] == pytest.approx(head.gmac * 5 / head.gmac_at["Q"])
    assert s["slice_head"]["gflop_per_s"] > 0
