"""streamdet-bench's image-lane line names the lift's stages: the lifter graph, or the per-camera terms and the tail
that the detector lifts through by default (before, that case printed "lifter p50 - ms")."""

from __future__ import annotations

from streamdet.benchmarks.report import _lift
from streamdet.benchmarks.streaming import LaneStats
from streamdet.benchmarks.timing import summarize


def _lane(**p50_ms: float) -> LaneStats:
    return LaneStats(summarize([1.0]), {name: {"p50_ms": v, "mean_ms": v} for name, v in p50_ms.items()})


def test_a_lift_through_the_lifter_graph():
    assert _lift(_lane(image_encoder=40.0, volumetric_lifter=37.29)) == "lifter p50 37.29 ms"


def test_a_lift_through_per_camera_terms_names_the_term_and_the_tail():
    line = _lift(_lane(image_encoder=40.0, lifter_partial=1.5, lifter_tail=3.25))
    assert line == "lift through per-camera terms: term p50 1.50 ms a camera, tail p50 3.25 ms a quadrant"


def test_no_lift_recorded():
    assert _lift(_lane(image_encoder=40.0)) == "lifter p50 - ms"
