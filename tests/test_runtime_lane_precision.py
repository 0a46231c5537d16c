"""Per-lane precision: the image lane (encoder + lifter) in one precision, the slice graph in another
(``DetectorConfig.image_lane_precision``, ``--image-precision`` of streamdet-run / streamdet-eval)."""

from __future__ import annotations


import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.cli_utils import PRECISION_CHOICES
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.evaluation.cli import main as eval_main
from streamdet.evaluation.run_cli import main as run_main
from streamdet.runtime_ort.detector import PRECISIONS, DetectorConfig, StreamingDetector


@pytest.fixture(scope="module")
def export_dir(tiny_int8_export):
    return tiny_int8_export.path  # fp32 + int8 (conftest)


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _feed(det: StreamingDetector, sample) -> None:
    img = det.manifest.image
    images = sample.load_images((img.width, img.height))  # (J, H, W, 3)
    det.update_images({n: images[j] for j, n in enumerate(sample.rig.names)}, timestamp=0.0)


def test_cli_choices_are_the_runtime_precisions():
    assert PRECISION_CHOICES == PRECISIONS


def test_config_default_and_validation():
    assert DetectorConfig().image_precision == "fp32"
    assert DetectorConfig(precision="fp16").image_precision == "fp16"
    assert DetectorConfig(precision="fp32", image_lane_precision="int8").image_precision == "int8"
    for bad in ("int4", "", "INT8", 8):
        with pytest.raises(ValueError, match="image_lane_precision must be None or one of"):
            DetectorConfig(image_lane_precision=bad)


def test_mixed_lanes_load_the_right_graphs(export_dir):
    det = StreamingDetector(export_dir, DetectorConfig(precision="fp32", image_lane_precision="int8"))
    assert det.image_encoder.path.name == "image_encoder.int8.onnx"
    assert det.lifter.path.name == "volumetric_lifter.int8.onnx"
    assert det.slice_head.path.name == "slice_head.onnx"
    assert det.precision_label == "int8 image lane + fp32 slices"
    same = StreamingDetector(export_dir, DetectorConfig(precision="int8", image_lane_precision="int8"))
    assert same.precision_label == "int8" and same.slice_head.path.name == "slice_head.int8.onnx"


def test_mixed_lanes_equal_each_lane_alone(export_dir, sample):
    """The image BEV is the int8 detector's, bit for bit; the slices given that BEV are the fp32 detector's."""
    mixed = StreamingDetector(export_dir, DetectorConfig(precision="fp32", image_lane_precision="int8"))
    int8 = StreamingDetector(export_dir, DetectorConfig(precision="int8"))
    fp32 = StreamingDetector(export_dir, DetectorConfig(precision="fp32"))
    for det in (mixed, int8, fp32):
        _feed(det, sample)
    np.testing.assert_array_equal(mixed.image_state.bev, int8.image_state.bev)  # the cached image BEV
    fp32._image = mixed.image_state  # noqa: SLF001 - the int8 image BEV, cached per quadrant
    for k, pts in enumerate(split_sweep(sample.points, mixed.num_slices)):
        a = mixed.detect_slice(pts, k, timestamp=float(k)).detections
        b = fp32.detect_slice(pts, k, timestamp=float(k)).detections
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.scores, b.scores)
        np.testing.assert_array_equal(a.labels, b.labels)


def test_missing_image_lane_graphs_are_refused(export_dir):
    with pytest.raises(ValueError, match=r"no fp16 graphs .*DetectorConfig.image_lane_precision.*--fp16"):
        StreamingDetector(export_dir, DetectorConfig(precision="fp32", image_lane_precision="fp16"))


def test_run_cli(export_dir, tmp_path):
    args = ["--export-dir", str(export_dir), "--image-precision", "int8", "--out", str(tmp_path)]
    result = CliRunner().invoke(run_main, args)
    assert result.exit_code == 0, result.output
    assert "(int8 image lane + fp32 slices, " in result.output
    result = CliRunner().invoke(run_main, ["--export-dir", str(export_dir), "--image-precision", "fp16", "--out", str(tmp_path)])
    assert result.exit_code == 1 and "Traceback" not in result.output and "no fp16 graphs" in result.output


def test_eval_cli_image_precision_is_for_the_dataset_mode(tmp_path):
    gt = tmp_path / "gt.json"
    gt.write_text('{"results": {}}')
    result = CliRunner().invoke(eval_main, ["--gt", str(gt), "--results", str(gt), "--image-precision", "int8"])
    assert result.exit_code == 2 and "--image-precision (dataset mode) not read in the files mode" in result.output


def test_eval_dataset_mode_records_both_lanes(export_dir, tiny_synth_data, tmp_path):
    out = tmp_path / "m.json"
    args = ["--data", str(tiny_synth_data), "--split", "all", "--export-dir", str(export_dir), "--image-precision", "int8",
            "--json", str(out)]  # fmt: skip
    result = CliRunner().invoke(eval_main, args)
    assert result.exit_code == 0, result.output
    assert "(int8 image lane + fp32 slices)" in result.output
    import json

    doc = json.loads(out.read_text())
    assert (doc["precision"], doc["image_precision"]) == ("fp32", "int8")


def test_study_runs_the_lanes_in_their_precisions(export_dir, tiny_synth_data, tmp_path):
    from streamdet.studies import RuntimeOptions
    from streamdet.studies.cli import main as study_main

    assert RuntimeOptions("fp32", 1, "int8").label == "int8 image lane + fp32 slices"
    assert RuntimeOptions("int8", 1, "int8").label == RuntimeOptions("int8").label == "int8"
    args = ["drop-camera", "--export-dir", str(export_dir), "--data", str(tiny_synth_data), "--split", "all",
            "--max-samples", "1", "--image-precision", "int8", "--json", str(tmp_path / "d.json")]  # fmt: skip
    result = CliRunner().invoke(study_main, args)
    assert result.exit_code == 0, result.output
    assert "int8 image lane + fp32 slices" in result.output
