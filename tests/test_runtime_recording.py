"""StreamingDetector.recording (runtime_ort/recording.py): the feeds it records are exactly what the detector hands
its graphs, against a naive rebuild of each graph's inputs (images resized in rig order, the export's LUT, slicing
and pillarisation of the sweep, the cached image BEV of the slice's quadrants), for full and per-quadrant image
updates, empty slices and outputs; recording starts and stops with its block. The LiDAR-only export's recording is
tested in tests/test_export_lidar_only.py (its export fixture)."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

from streamdet.calibration.compact_lut import lifter_feeds
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut
from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.pipeline import detect_sample
from streamdet.runtime_ort.recording import GraphRecording


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture(scope="module")
def naive(tiny_export):
    """Plain onnxruntime sessions of the export's fp32 graphs, its LUT, grid and pillar caps."""
    m = read_manifest(tiny_export)
    sessions = {g.name: ort.InferenceSession(str(tiny_export / g.file), providers=["CPUExecutionProvider"])
                for g in m.graphs if g.precision == "fp32"}  # fmt: skip
    pil = m.preset["pillars"]
    lut = Lut.load(tiny_export / m.lut.file)
    return sessions, lut, GridSpec.from_dict(m.grid), int(pil["max_points_per_pillar"]), int(pil["max_pillars"])


def _equal_feeds(got: dict, want: dict, rtol: float = 0.0) -> None:
    assert sorted(got) == sorted(want)
    for name, value in want.items():
        assert got[name].dtype == value.dtype and got[name].shape == value.shape, name
        np.testing.assert_allclose(got[name], value, rtol=rtol, atol=rtol, err_msg=name)


def _sweep_with_empty_slices(sample) -> np.ndarray:
    """The bundled sweep without its points of x < 0: half of the 8 slices hold no point."""
    return sample.points[sample.points[:, 0] >= 0.5]


@pytest.mark.parametrize("empty_slices", [False, True])
def test_recorded_feeds_equal_a_naive_rebuild(tiny_export, naive, sample, empty_slices):
    sessions, lut, grid, max_pp, max_pillars = naive
    det = StreamingDetector(tiny_export)
    sweep = _sweep_with_empty_slices(sample) if empty_slices else sample.points
    with det.recording() as rec:
        det.update_images(dict(zip(sample.rig.names, sample.load_images((det.image.width, det.image.height)))), timestamp=1.0)
        result = det.detect_sweep_slices(sweep, timestamp=1.0)
    images = sample.load_images((lut.image_width, lut.image_height))  # (J, H, W, 3) in rig order
    assert [r.graph for r in rec.runs[:2]] == ["image_encoder", "volumetric_lifter"]
    (enc,) = rec.of("image_encoder")
    _equal_feeds(enc.feeds, {"images": images})
    (features,) = sessions["image_encoder"].run(None, {"images": images})  # (J, C, Hf, Wf)
    (lift,) = rec.of("volumetric_lifter")
    _equal_feeds(lift.feeds, lifter_feeds(features, lut.index, lut.weight, det.manifest.lut_layout), rtol=1e-5)
    (bev,) = sessions["volumetric_lifter"].run(None, lift.feeds)  # (4, C, Yq, Xq)
    np.testing.assert_array_equal(lift.outputs[0], bev)
    want = []
    for k, points in enumerate(split_sweep(sweep, det.num_slices)):
        quadrants = quadrants_of_sector(k, det.num_slices)
        pl = pillarize(points, grid, quadrants, max_pp, max_pillars)
        if pl.num_pillars:  # an empty slice runs no graph
            want.append({**pl.as_feeds(), "image_bev": bev[list(quadrants)]})  # (Q, C, Yq, Xq)
    slices = rec.of("slice_head")
    assert len(slices) == len(want) == sum(r.num_pillars > 0 for r in result.slices)
    assert (len(want) < det.num_slices) == empty_slices
    for run, feeds in zip(slices, want, strict=True):
        _equal_feeds(run.feeds, feeds)
        for got, ref in zip(run.outputs, sessions["slice_head"].run(None, feeds), strict=True):
            np.testing.assert_array_equal(got, ref)


def test_per_quadrant_update_records_one_lift_per_quadrant(tiny_export, naive, sample):
    sessions, lut, *_ = naive
    det = StreamingDetector(tiny_export)
    images = dict(zip(sample.rig.names, sample.load_images((det.image.width, det.image.height))))
    with det.recording() as rec:
        det.update_images(images, timestamp=1.0, quadrants=[1, 3])
    (enc,) = rec.of("image_encoder")
    cameras = det.quadrant_cameras([1, 3])
    _equal_feeds(enc.feeds, {"images": np.stack([images[n] for n in cameras])})
    lifts = rec.of("volumetric_lifter")
    assert len(lifts) == 2 and all(r.outputs[0].shape[0] == 1 for r in lifts)  # (1, C, Yq, Xq) each
    (features,) = sessions["image_encoder"].run(None, {"images": np.stack(list(images.values()))})  # (J, C, Hf, Wf)
    (full,) = sessions["volumetric_lifter"].run(None, lifter_feeds(features, lut.index, lut.weight, det.manifest.lut_layout))
    for q, run in zip((1, 3), lifts):
        np.testing.assert_allclose(run.outputs[0][0], full[q], rtol=1e-4, atol=1e-5)


def test_recording_starts_and_stops_with_its_block(tiny_export, sample):
    det = StreamingDetector(tiny_export)
    detect_sample(det, sample)  # not recorded
    outer = GraphRecording()
    with det.recording(outer):
        with det.recording() as inner:
            det.detect_slice(split_sweep(sample.points, det.num_slices)[0], 0)
        det.detect_slice(split_sweep(sample.points, det.num_slices)[1], 1)
    det.detect_slice(split_sweep(sample.points, det.num_slices)[2], 2)  # after both blocks: not recorded
    assert [r.graph for r in inner.runs] == ["slice_head"] and len(outer) == 2
    assert outer.runs[0] is not inner.runs[0] and outer.runs[0].feeds.keys() == inner.runs[0].feeds.keys()
    assert outer.feeds("image_encoder") == [] and len(outer.outputs("slice_head")) == 2


def test_a_run_records_in_the_blocks_open_when_it_started(tiny_export, sample):
    """A block opened while a run is under way does not take that run (it began before the block), and one closed
    meanwhile keeps it (it began inside the block)."""
    det = StreamingDetector(tiny_export)
    session = det._sessions["slice_head"]
    run = session.run
    slices = split_sweep(sample.points, det.num_slices)
    late, early = GraphRecording(), GraphRecording()
    opened = det.recording(late)
    closing = det.recording(early)
    closing.__enter__()

    def during(feeds):  # the other thread's calls, made while this run is in onnxruntime
        opened.__enter__()
        closing.__exit__(None, None, None)
        return run(feeds)

    session.run = during
    det.detect_slice(slices[0], 0)
    session.run = run
    opened.__exit__(None, None, None)
    assert len(late) == 0 and [r.graph for r in early.runs] == ["slice_head"]


def test_a_given_manifest_is_used_and_checked(tiny_export):
    m = read_manifest(tiny_export)
    det = StreamingDetector(tiny_export, manifest=m)
    assert det.manifest is m and set(det.sessions) == {"image_encoder", "volumetric_lifter", "slice_head"}
    with pytest.raises(ValueError, match="manifest must be None or a Manifest, got dict"):
        StreamingDetector(tiny_export, manifest=m.to_dict())


def test_both_lanes_record_from_their_threads(tiny_export, sample):
    """StreamingRunner's image and slice workers run the graphs concurrently; the recording holds every run once."""
    from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner

    det = StreamingDetector(tiny_export)
    images = dict(zip(sample.rig.names, sample.load_images((det.image.width, det.image.height))))
    slices = split_sweep(sample.points, det.num_slices)
    with det.recording() as rec, StreamingRunner(det, LaneConfig(max_in_flight=2, queue_size=16)) as runner:
        done = [runner.submit_images(images, timestamp=0.0)]
        done += [runner.submit_slice(pts, k, timestamp=0.01 * k) for k, pts in enumerate(slices)]
        results = [f.result(timeout=60) for f in done]
    non_empty = sum(r.num_pillars > 0 for r in results[1:])
    assert sorted(r.graph for r in rec.runs) == sorted(["image_encoder", "volumetric_lifter"] + ["slice_head"] * non_empty)
