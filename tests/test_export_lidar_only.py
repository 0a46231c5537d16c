"""The LiDAR-only baseline (preset use_image=False) as an ONNX export: the slice graph alone, run by the torch-free
runtime with no image lane, scored through ONNX exactly as through PyTorch (training/torch_eval.py)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.data.slicing import slice_sample
from streamdet.export.cli import main as export_main
from streamdet.models.decode import decode_head_maps
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.detector import DetectorConfig, NoImageLaneError, StreamingDetector
from streamdet.runtime_ort.lanes import StreamingRunner
from streamdet.runtime_ort.manifest import MANIFEST_NAME, ManifestError, read_manifest
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.training.checkpoint import save_weights
from streamdet.training.torch_eval import TorchSweepDetector

LIDAR_ONLY = dataclasses.replace(get_preset("tiny"), use_image=False)
N_SLICES = 8


def _model():
    torch.manual_seed(3)
    model = build_detector(LIDAR_ONLY).eval()
    with torch.no_grad():  # spread the untrained heatmap logits, so scores are not one flat tie at the prior
        for task in model.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
    return model


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ckpt") / "lidar_only.pt"
    save_weights(path, LIDAR_ONLY, _model())
    return path


@pytest.fixture(scope="module")
def export_dir(checkpoint, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "lidar"
    result = CliRunner().invoke(export_main, ["--preset", "tiny", "--checkpoint", str(checkpoint), "--fp16", "--int8",
                                              "--slices", str(N_SLICES), "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "slice_head.onnx" in result.output and "lut.npz" not in result.output
    return out


@pytest.fixture(scope="module")
def detector(export_dir) -> StreamingDetector:
    return StreamingDetector(export_dir)


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def test_export_holds_the_slice_graph_only(export_dir):
    m = read_manifest(export_dir)
    assert sorted(p.name for p in export_dir.iterdir()) == [
        MANIFEST_NAME, "slice_head.fp16.onnx", "slice_head.int8.onnx", "slice_head.onnx"]  # fmt: skip
    assert {g.name for g in m.graphs} == {"slice_head"} and m.precisions == ("fp32", "fp16", "int8")
    assert m.preset["use_image"] is False and not m.use_image
    assert m.image is None and m.lut is None and m.normalisation is None
    inputs = [t.name for t in m.graph("slice_head").inputs]
    assert inputs == ["pillar_features", "pillar_mask", "pillar_index", "quadrants"]  # no image_bev
    # parity of what exists: fp32 against PyTorch, fp16 against fp32, the fp16 "pipeline" (the slice graph)
    assert {(p.precision, p.reference) for p in m.parity} == {("fp32", "torch"), ("fp16", "onnx-fp32")}
    assert all(p.passed for p in m.parity) and m.pipeline_parity is not None and m.pipeline_parity.passed
    assert "no images" in m.source["parity_input"]
    # int8: the slice graph alone, calibrated without a single image
    cal = m.int8.calibration
    assert [g.graph for g in m.int8.graphs] == ["slice_head"] and cal.num_images == 0 and cal.num_volumes == 0
    assert cal.num_slices > 0 and {p.graph for p in m.int8.parity} == {"slice_head"}


def test_onnx_matches_the_pytorch_decode(detector, sample):
    pil = LIDAR_ONLY.pillars
    g = LIDAR_ONLY.grid
    model = _model()
    checked = 0
    for s in slice_sample(sample, 2):  # two quadrants per slice: Q comes from the quadrant ids
        pl = pillarize(s.points, g, s.quadrants, pil.max_points_per_pillar, pil.max_pillars)
        got = detector.slice_head.run(pl.as_feeds(s.quadrants))
        with torch.no_grad():
            maps = model.slice_net(torch.from_numpy(pl.features), torch.from_numpy(pl.mask), torch.from_numpy(pl.index),
                                   num_quadrants=len(s.quadrants))  # fmt: skip
            ref = [t.numpy() for t in decode_head_maps(maps, LIDAR_ONLY.head_cell_m, LIDAR_ONLY.top_k)]
        assert got[0].shape == ref[0].shape == (len(s.quadrants), LIDAR_ONLY.top_k, 9)
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got[0], ref[0], rtol=1e-4, atol=1e-4)
        assert np.array_equal(got[2], ref[2])
        checked += 1
    assert checked == 2


@pytest.mark.parametrize("num_slices", [1, 2, N_SLICES])
def test_sweep_through_onnx_equals_pytorch(detector, sample, num_slices):
    """The point of the export: the baseline scores the same through ONNX as through PyTorch."""
    onnx = detector.detect_sweep(sample.points, timestamp=0.0, num_slices=num_slices)
    ref = TorchSweepDetector(_model(), num_slices=num_slices)(sample)
    assert len(onnx) == len(ref) > 0
    np.testing.assert_allclose(onnx.scores, ref.scores, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(onnx.boxes, ref.boxes, rtol=1e-4, atol=1e-4)
    assert np.array_equal(onnx.labels, ref.labels)


@pytest.mark.parametrize("empty_slices", [False, True])
def test_recorded_feeds_are_the_pillars_and_quadrant_ids(detector, sample, empty_slices):
    """What the runtime records (and the int8 calibration quantizes on): each non-empty slice's pillar tensors with
    its quadrant ids, no image graph; a slice without a pillar runs nothing."""
    from streamdet.export.int8 import record_graph_inputs

    points = sample.points[sample.points[:, 1] >= 0.5] if empty_slices else sample.points  # y < 0: no point
    pil, g = LIDAR_ONLY.pillars, LIDAR_ONLY.grid
    with detector.recording() as rec:
        detector.detect_sweep_slices(points, timestamp=0.0)
    want = []
    for k, pts in enumerate(split_sweep(points, N_SLICES)):
        quadrants = quadrants_of_sector(k, N_SLICES)
        pl = pillarize(pts, g, quadrants, pil.max_points_per_pillar, pil.max_pillars)
        if pl.num_pillars:
            want.append(pl.as_feeds(quadrants))
    assert (len(want) < N_SLICES) == empty_slices and [r.graph for r in rec.runs] == ["slice_head"] * len(want)
    for run, feeds in zip(rec.runs, want, strict=True):
        assert sorted(run.feeds) == sorted(feeds) == ["pillar_features", "pillar_index", "pillar_mask", "quadrants"]
        assert all(np.array_equal(run.feeds[n], feeds[n]) and run.feeds[n].dtype == feeds[n].dtype for n in feeds)
    calibration = record_graph_inputs(detector, [sample])  # the whole bundled sweep: no image read
    assert {r.graph for r in calibration.runs} == {"slice_head"}
    if not empty_slices:
        assert len(calibration) == len(rec)
        assert all(np.array_equal(a.feeds["pillar_features"], b.feeds["pillar_features"]) for a, b in zip(calibration.runs, rec.runs))


def test_runtime_has_no_image_lane(detector, sample, export_dir):
    assert not detector.uses_images and detector.camera_names == () and detector.image is None
    result = detector.detect_slice(slice_sample(sample, N_SLICES)[0].points, 0, timestamp=1.0)
    assert result.image_timestamp is None and result.num_pillars > 0
    images = {"CAM_FRONT": np.zeros((90, 160, 3), np.uint8)}
    with pytest.raises(NoImageLaneError, match="LiDAR-only export .* no image lane: update_images got cameras"):
        detector.update_images(images)
    with pytest.raises(NoImageLaneError, match="LiDAR-only export .* set_calibration has nothing to calibrate"):
        detector.set_calibration(sample.rig)
    with pytest.raises(NoImageLaneError, match="no projection LUT"):
        detector.lut  # noqa: B018
    with pytest.raises(NoImageLaneError, match=r"image_size \(320, 180\) cannot apply"):
        StreamingDetector(export_dir, DetectorConfig(image_size=(320, 180)))
    with pytest.raises(NoImageLaneError, match=r"image_lane_precision 'int8' cannot apply"):
        StreamingDetector(export_dir, DetectorConfig(image_lane_precision="int8"))
    with StreamingRunner(detector) as runner:
        with pytest.raises(NoImageLaneError):
            runner.submit_images(images)
        points = slice_sample(sample, N_SLICES)[0].points
        got = runner.submit_slice(points, 0).result().detections
    want = detector.detect_slice(points, 0).detections  # the runner's slice lane gives what the detector gives
    assert np.array_equal(got.boxes, want.boxes) and np.array_equal(got.scores, want.scores)
    assert np.array_equal(got.labels, want.labels)


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_other_precisions_run(export_dir, sample, precision):
    det = StreamingDetector(export_dir, DetectorConfig(precision=precision))
    assert len(det.detect_sweep(sample.points)) > 0


def _rewrite_manifest(export_dir: Path, tmp_path: Path, change) -> Path:
    d = json.loads((export_dir / MANIFEST_NAME).read_text())
    change(d)
    out = tmp_path / "changed"
    out.mkdir()
    (out / MANIFEST_NAME).write_text(json.dumps(d))
    return out


def test_fused_manifest_without_image_graphs_is_refused(export_dir, tmp_path):
    def as_fused(d: dict) -> None:  # a camera + LiDAR manifest whose image graphs, image spec and LUT were removed
        d["preset"]["use_image"] = True

    with pytest.raises(ManifestError, match="no fp32 graph 'image_encoder' .*use_image is true"):
        read_manifest(_rewrite_manifest(export_dir, tmp_path, as_fused), verify_files=False)


def test_lidar_only_manifest_with_an_image_graph_is_refused(export_dir, tmp_path):
    def add_encoder(d: dict) -> None:
        d["graphs"].append({**d["graphs"][0], "name": "image_encoder", "file": "image_encoder.onnx"})

    with pytest.raises(ManifestError, match=r"LiDAR-only preset \(use_image false\) lists image graphs: image_encoder \(fp32\)"):
        read_manifest(_rewrite_manifest(export_dir, tmp_path, add_encoder), verify_files=False)


def test_streamdet_run_uses_no_images(export_dir, tmp_path):
    from streamdet.evaluation.run_cli import main as run_main

    res = CliRunner().invoke(run_main, ["--export-dir", str(export_dir), "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    assert "LiDAR only: no images used" in res.output
    meta = json.loads((tmp_path / "run" / "results_nusc.json").read_text())["meta"]
    assert meta["use_camera"] is False and meta["use_lidar"] is True


# ---- evaluation: streamdet-eval and streamdet-study on a LiDAR-only export ------------------------------------


@pytest.fixture(scope="module")
def data_dir(tiny_synth_data) -> Path:
    return tiny_synth_data


@pytest.fixture(scope="module")
def fused_export_dir(tiny_export_fp32) -> Path:
    assert N_SLICES == 8  # the shared export's slices
    return tiny_export_fp32  # tiny camera + LiDAR, fp32, read-only (conftest)


def ground_truth_of(data_dir: Path) -> list[list[dict]]:
    """The ground-truth entries of every sample of ``data_dir`` (as the dataset mode scores them)."""
    from streamdet.data.nuscenes import NuScenesReader
    from streamdet.evaluation.dataset_eval import ground_truth_entries

    reader = NuScenesReader(data_dir, "v1.0-synth")
    return [ground_truth_entries(reader.get(t)) for t in reader.sample_tokens]


def test_streamdet_eval_data_mode(export_dir, data_dir, tmp_path):
    from streamdet.evaluation.cli import main as eval_main

    out = tmp_path / "m.json"
    res = CliRunner().invoke(eval_main, ["--data", str(data_dir), "--export-dir", str(export_dir), "--split", "all",
                                         "--json", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["num_samples"] == 2 and 0.0 <= doc["mAP"] <= 1.0
    assert "note: no ground-truth box" not in res.output  # the dataset mode averages the classes present
    res = CliRunner().invoke(eval_main, ["--data", str(data_dir), "--export-dir", str(export_dir), "--split", "all",
                                         "--classes", "car,construction_vehicle"])  # fmt: skip
    assert res.exit_code == 0, res.output
    gt = {e["detection_name"] for entries in ground_truth_of(data_dir) for e in entries}
    assert ("note: no ground-truth box of construction_vehicle" in res.output) == ("construction_vehicle" not in gt)


def test_slices_study_baseline_export_scores_as_the_checkpoint(fused_export_dir, export_dir, checkpoint, data_dir, tmp_path):
    from streamdet.studies.cli import main as study_main

    def run(*baseline: str) -> dict:
        out = tmp_path / f"{baseline[0].strip('-')}.json"
        res = CliRunner().invoke(study_main, ["slices", "--export-dir", str(fused_export_dir), "--data", str(data_dir),
                                              "--split", "all", "--counts", "1,8", "--json", str(out), *baseline])  # fmt: skip
        assert res.exit_code == 0, res.output
        assert "LiDAR-only baseline" in res.output
        return json.loads(out.read_text())

    onnx = run("--baseline-export-dir", str(export_dir))
    torch_route = run("--baseline-checkpoint", str(checkpoint))
    assert "LiDAR only" in onnx["baseline_source"] and "onnxruntime" in onnx["baseline_source"]
    for n in ("1", "8"):
        assert onnx["baseline"][n]["mAP"] == pytest.approx(torch_route["baseline"][n]["mAP"], abs=1e-6)
    assert onnx["fused"] == torch_route["fused"]


@pytest.mark.parametrize("args, message", [
    (["slices"], "is LiDAR-only (preset use_image=false): pass it as --baseline-export-dir"),
    (["drop-camera"], "is LiDAR-only (preset use_image=false): the drop-camera study needs an image lane"),
    (["calib-noise"], "the calib-noise study needs an image lane"),
    (["resolution"], "the resolution study needs an image lane"),
])  # fmt: skip
def test_image_studies_refuse_a_lidar_only_export(export_dir, data_dir, args, message):
    from streamdet.studies.cli import main as study_main

    res = CliRunner().invoke(study_main, [*args, "--export-dir", str(export_dir), "--data", str(data_dir), "--split", "all"])
    assert res.exit_code == 1 and message in res.output and "Traceback" not in res.output, res.output


def test_calib_lut_and_bench_streaming_refuse_a_lidar_only_export(export_dir, tmp_path):
    from streamdet.benchmarks.streaming import measure_streaming
    from streamdet.runtime_ort.calib_cli import main as calib_main
    from streamdet.data.sample import bundled_sample_dir

    res = CliRunner().invoke(calib_main, ["lut", "--calibration", str(bundled_sample_dir() / "calibration.json"),
                                          "--export-dir", str(export_dir)])  # fmt: skip
    assert res.exit_code != 0 and "LiDAR-only export" in res.output and "Traceback" not in res.output
    with pytest.raises(ValueError, match="LiDAR-only export"):
        measure_streaming(export_dir)


def test_saved_results_say_no_camera(export_dir, data_dir, tmp_path):
    from streamdet.evaluation.cli import main as eval_main

    res = CliRunner().invoke(eval_main, ["--data", str(data_dir), "--export-dir", str(export_dir), "--split", "all",
                                         "--save-results", str(tmp_path / "s")])  # fmt: skip
    assert res.exit_code == 0, res.output
    meta = json.loads((tmp_path / "s" / "results.json").read_text())["meta"]
    assert meta["use_camera"] is False and meta["use_lidar"] is True
