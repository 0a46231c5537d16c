"""streamdet-export: happy path and bad input (one-line error, non-zero exit, nothing left behind)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner

from streamdet.data.sample import load_bundled_sample
from streamdet.export.cli import main
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.detector_config import DetectorConfig
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset


def _invoke(args: list[str]):
    return CliRunner().invoke(main, args)


def _assert_one_line_error(result, *needles: str) -> None:
    assert result.exit_code not in (0, None), result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    for needle in needles:
        assert needle in errors[0], errors[0]


def _leftovers(parent) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def test_tiny_export_prints_what_it_wrote(tmp_path):
    out = tmp_path / "exp"
    result = _invoke(["--preset", "tiny", "--resolution", "160x90", "--out", str(out), "--opset", "18"])
    assert result.exit_code == 0, result.output
    assert f"wrote {out.resolve()}" in result.output
    for name in ("image_encoder.onnx", "volumetric_lifter.onnx", "slice_head.onnx", "lut.npz", "manifest.json"):
        assert name in result.output
    assert "[1/10] loading weights" in result.output  # progress (stderr, mixed in by CliRunner)
    m = read_manifest(out)
    # 90 is not a multiple of 4: the feature map is ceil(size / 4) (a 16:9 size, the bundled cameras' aspect)
    assert (m.image.width, m.image.height, m.image.feature_width, m.image.feature_height) == (160, 90, 40, 23)
    assert m.graph("image_encoder").opset == 18 and m.precisions == ("fp32",)
    assert _leftovers(tmp_path) == []
    assert m.post["top_k"] == get_preset("tiny").post.top_k  # the preset's cap unless --top-k says
    # exporting again replaces the old export
    again = _invoke(["--preset", "tiny", "--resolution", "160x90", "--out", str(out), "--slices", "4", "--top-k", "7"])
    assert again.exit_code == 0, again.output
    m = read_manifest(out)
    assert m.num_slices == 4 and _leftovers(tmp_path) == []
    assert m.post["top_k"] == 7 and m.post["top_k_per_quadrant"] == 7
    scores = next(o for o in onnx.load(out / "slice_head.onnx").graph.output if o.name == "det_scores")
    assert scores.type.tensor_type.shape.dim[1].dim_value == 7  # the graph decodes 7 boxes per quadrant
    _check_top_k_counter(out)


def _check_top_k_counter(export_dir) -> None:
    """StreamingDetector.slice_runs_at_top_k counts the runs whose K-th box passed the threshold, none else."""
    sweep = load_bundled_sample().points.astype(np.float32)
    with StreamingDetector(export_dir, DetectorConfig(score_threshold=0.0)) as det:  # every K-th box passes 0
        results = det.detect_sweep_slices(sweep, 0.0).slices
        assert det.slice_runs_at_top_k == sum(r.num_pillars > 0 for r in results) > 0
    with StreamingDetector(export_dir, DetectorConfig(score_threshold=0.999999)) as det:
        det.detect_sweep_slices(sweep, 0.0)
        assert det.slice_runs_at_top_k == 0


@pytest.mark.parametrize(
    "resolution,needle",
    [("801x450", "even"), ("800x451", "even"), ("0x450", "positive"), ("800", "WIDTHxHEIGHT"), ("axb", "WIDTHxHEIGHT")],
)
def test_bad_resolution(tmp_path, resolution, needle):
    result = _invoke(["--preset", "tiny", "--resolution", resolution, "--out", str(tmp_path / "exp")])
    _assert_one_line_error(result, needle)
    assert list(tmp_path.iterdir()) == []


def test_a_resolution_of_another_aspect_than_the_cameras_is_refused(tmp_path):
    result = _invoke(["--preset", "tiny", "--resolution", "18x4000", "--out", str(tmp_path / "exp")])
    _assert_one_line_error(result, "--resolution 18x4000 does not fit the calibration")
    assert "resizing would distort them" in result.output and list(tmp_path.iterdir()) == []


def test_checkpoint_from_another_preset(tmp_path):
    torch.manual_seed(0)
    tiny = get_preset("tiny")
    ckpt = tmp_path / "tiny.pt"
    torch.save({"preset": tiny.to_dict(), "model": build_detector(tiny).state_dict()}, ckpt)
    result = _invoke(["--preset", "small", "--checkpoint", str(ckpt), "--out", str(tmp_path / "exp")])
    _assert_one_line_error(result, "trained with preset 'tiny', not 'small'")
    assert not (tmp_path / "exp").exists() and _leftovers(tmp_path) == []
    # a bare state dict has no preset name: the shapes tell
    bare = tmp_path / "bare.pt"
    torch.save(build_detector(tiny).state_dict(), bare)
    result = _invoke(["--preset", "small", "--checkpoint", str(bare), "--out", str(tmp_path / "exp")])
    _assert_one_line_error(result, "does not fit preset 'small'", "shape mismatches")
    assert not (tmp_path / "exp").exists() and _leftovers(tmp_path) == []


def test_checkpoint_round_trip_and_bad_files(tmp_path):
    tiny = get_preset("tiny")
    torch.manual_seed(3)
    det = build_detector(tiny)
    ckpt = tmp_path / "ok.pt"
    # other image size and post settings do not matter; the architecture does
    saved = dataclasses.replace(tiny, image=dataclasses.replace(tiny.image, width_px=256, height_px=144))
    torch.save({"preset": saved.to_dict(), "model": det.state_dict(), "epoch": 3}, ckpt)
    result = _invoke(["--preset", "tiny", "--checkpoint", str(ckpt), "--out", str(tmp_path / "exp")])
    assert result.exit_code == 0, result.output
    m = read_manifest(tmp_path / "exp")
    assert m.source["checkpoint"] == str(ckpt) and m.source["seed"] is None
    # shipped weights may hold float16 tensors (training/checkpoint.py save_weights(half=True))
    half = tmp_path / "half.pt"
    state = {k: v.half() if v.is_floating_point() else v for k, v in det.state_dict().items()}
    torch.save({"format": "streamdet-weights-v1", "preset": tiny.to_dict(), "model": state}, half)
    # ... and without --preset the checkpoint's own preset is exported (one export checks both)
    result = _invoke(["--checkpoint", str(half), "--out", str(tmp_path / "exp_half")])
    assert result.exit_code == 0, result.output
    m = read_manifest(tmp_path / "exp_half")
    assert all(p.passed for p in m.parity) and m.preset_name == "tiny"
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    _assert_one_line_error(_invoke(["--preset", "tiny", "--checkpoint", str(tmp_path / "junk.pt"), "--out", str(tmp_path / "e2")]),
                           "cannot be read")
    _assert_one_line_error(_invoke(["--preset", "tiny", "--checkpoint", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "e2")]),
                           "does not exist")
    assert not (tmp_path / "e2").exists()


def test_unwritable_and_foreign_out_dirs(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _assert_one_line_error(_invoke(["--preset", "tiny", "--out", str(blocker / "exp")]), "cannot write into")
    _assert_one_line_error(_invoke(["--preset", "tiny", "--out", str(blocker)]), "is a file")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    _assert_one_line_error(_invoke(["--preset", "tiny", "--out", str(foreign)]), "not a streamdet export")
    assert (foreign / "notes.txt").read_text() == "keep me"
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--preset", "huge"], "huge"),
        (["--slices", "3"], "multiple of 4"),
        (["--opset", "9"], "9"),
        (["--calibration", "/nonexistent/calibration.json"], "does not exist"),
        (["--top-k", "0"], "--top-k"),
        (["--top-k", "many"], "--top-k"),
    ],
)
def test_other_bad_options(tmp_path, args, needle):
    result = _invoke(["--preset", "tiny", "--out", str(tmp_path / "exp"), *args])
    _assert_one_line_error(result, needle)
    assert not (tmp_path / "exp").exists() and _leftovers(tmp_path) == []


def test_broken_calibration_file(tmp_path):
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps({"lidar": {}, "cameras": []}))
    result = _invoke(["--preset", "tiny", "--calibration", str(calib), "--out", str(tmp_path / "exp")])
    _assert_one_line_error(result, "calib.json")
    assert not (tmp_path / "exp").exists() and _leftovers(tmp_path) == []


def two_camera_calibration(tmp_path: Path) -> Path:
    """A calibration of two cameras the bundled sample lacks (CAM_0, CAM_1: its first two, renamed)."""
    from streamdet.data.sample import load_bundled_sample

    doc = load_bundled_sample().rig.to_dict()
    doc["cameras"] = doc["cameras"][:2]
    for i, cam in enumerate(doc["cameras"]):
        cam["name"] = f"CAM_{i}"
    calib = tmp_path / "rig.json"
    calib.write_text(json.dumps(doc))
    return calib


def test_foreign_rig_exports_with_noise_images(tmp_path):
    """A calibration of other cameras (not the bundled sample's): the LUT follows it and the parity inputs fall
    back to seeded noise images, which the manifest says."""
    calib = two_camera_calibration(tmp_path)
    result = _invoke(["--preset", "tiny", "--calibration", str(calib), "--out", str(tmp_path / "exp")])
    assert result.exit_code == 0, result.output
    m = read_manifest(tmp_path / "exp")
    assert m.image.camera_names == ("CAM_0", "CAM_1") and m.lut.calibration_source == str(calib)
    assert "seeded noise images" in m.source["parity_input"]


@pytest.mark.slow
def test_default_export_no_arguments(tmp_path, monkeypatch):
    """No arguments at all: the shipped model's preset, its bundled (or fixed-seed) weights, bundled calibration,
    ./exports/<preset> (the default every reader of an export takes)."""
    from streamdet.core.constants import DEFAULT_EXPORT_DIR, DEFAULT_PRESET

    monkeypatch.chdir(tmp_path)
    result = _invoke([])
    assert result.exit_code == 0, result.output
    m = read_manifest(tmp_path / DEFAULT_EXPORT_DIR)
    assert m.preset_name == DEFAULT_PRESET and (m.image.width, m.image.height) == (384, 216)  # the preset's native size
    assert m.lut.calibration_source.startswith("bundled:") and all(p.passed for p in m.parity)


def test_bundled_checkpoint_is_found_by_the_preset_it_names(tmp_path):
    """Bundled files are named by role: the lookup reads each file's saved preset, skips a LiDAR-only baseline
    (even when its name sorts first) and files of other presets, and finds nothing in an empty folder."""
    from streamdet.export.weights import bundled_checkpoint
    from streamdet.training.checkpoint import save_weights

    tiny = get_preset("tiny")
    lidar_only = dataclasses.replace(tiny, use_image=False)
    assert bundled_checkpoint("tiny", tmp_path) is None
    save_weights(tmp_path / "a_lidar_only.pt", lidar_only, build_detector(lidar_only))
    assert bundled_checkpoint("tiny", tmp_path) is None  # the baseline is never a default
    save_weights(tmp_path / "b_fused.pt", tiny, build_detector(tiny))
    (tmp_path / "0_broken.pt").write_bytes(b"not a checkpoint")
    assert bundled_checkpoint("tiny", tmp_path) == tmp_path / "b_fused.pt"
    assert bundled_checkpoint("small", tmp_path) is None
