"""Scoring a model over a dataset: the ONNX runtime route (evaluation/dataset_eval.py, streamdet-eval --data) and
the PyTorch route (training/torch_eval.py) agree, and the CLI reports classes, JSON and one-line errors."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.data.nuscenes import NuScenesReader
from streamdet.evaluation.cli import main as eval_main
from streamdet.evaluation.dataset_eval import OnnxSweepDetector, evaluate_dataset
from streamdet.export.weights import load_detector
from streamdet.models.presets import get_preset
from streamdet.training.torch_eval import TorchSweepDetector

TINY = get_preset("tiny")


@pytest.fixture(scope="module")
def data_dir(tiny_train_data) -> Path:
    assert (TINY.image.width_px, TINY.image.height_px) == (128, 72)  # the shared dataset's image size (conftest)
    return tiny_train_data  # scene 2 (2 samples) is val


@pytest.fixture(scope="module")
def export_dir(tiny_export_fp32) -> Path:
    return tiny_export_fp32  # fixed-seed weights, spread logits; fp32 graphs alone, 8 slices (conftest)


def test_torch_and_onnx_routes_agree(data_dir, export_dir):
    model, _ = load_detector(TINY, None)  # the same fixed-seed weights the export holds
    sample = NuScenesReader(data_dir, "v1.0-synth").get(3)
    onnx = OnnxSweepDetector(export_dir)(sample)
    torch_dets = TorchSweepDetector(model, num_slices=8)(sample)
    assert len(onnx) > 0
    top = min(len(onnx), len(torch_dets), 10)
    # The same boxes lead both lists (ties aside, the order is the score order).
    np.testing.assert_allclose(onnx.scores[:top], torch_dets.scores[:top], rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(onnx.boxes[:top, :3], torch_dets.boxes[:top, :3], atol=2e-3)


def test_evaluate_dataset_names_the_classes(data_dir, export_dir):
    res = evaluate_dataset(OnnxSweepDetector(export_dir, num_slices=4), data_dir, split="val")
    assert res.num_samples == 2 and res.classes and set(res.classes) <= set(TINY_CLASSES)
    assert 0.0 <= res.metrics.mean_ap <= 1.0
    d = res.to_dict()
    assert d["classes"] == list(res.classes) and d["num_samples"] == 2
    only = evaluate_dataset(OnnxSweepDetector(export_dir), data_dir, split="val", classes=("car",), max_samples=1)
    assert only.classes == ("car",) and only.num_samples == 1


TINY_CLASSES = ("car", "truck", "bus", "bicycle", "motorcycle", "pedestrian", "barrier", "traffic_cone")


def test_eval_cli_data_mode(data_dir, export_dir, tmp_path):
    out = tmp_path / "m.json"
    res = CliRunner().invoke(eval_main, ["--data", str(data_dir), "--export-dir", str(export_dir), "--slices", "8",
                                         "--json", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "mAP" in res.output and "mAP / NDS average" in res.output and "8 slices per sweep" in res.output
    doc = json.loads(out.read_text())
    assert doc["num_slices"] == 8 and doc["num_samples"] == 2 and 0.0 <= doc["mAP"] <= 1.0 and doc["classes"]


def test_eval_cli_saved_results_score_the_same_in_files_mode(data_dir, export_dir, tmp_path):
    saved, first, again = tmp_path / "saved", tmp_path / "a.json", tmp_path / "b.json"
    res = CliRunner().invoke(eval_main, ["--data", str(data_dir), "--export-dir", str(export_dir), "--slices", "8",
                                         "--json", str(first), "--save-results", str(saved)])  # fmt: skip
    assert res.exit_code == 0, res.output
    a = json.loads(first.read_text())
    res = CliRunner().invoke(eval_main, ["--gt", str(saved / "gt.json"), "--results", str(saved / "results.json"),
                                         "--classes", ",".join(a["classes"]), "--json", str(again)])  # fmt: skip
    assert res.exit_code == 0, res.output
    b = json.loads(again.read_text())
    assert b["mAP"] == a["mAP"] and b["NDS"] == a["NDS"]


def test_save_results_needs_the_dataset_mode(tmp_path):
    res = CliRunner().invoke(eval_main, ["--gt", __file__, "--results", __file__, "--save-results", str(tmp_path)])
    assert res.exit_code != 0 and "--save-results" in res.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["--slices", "6"], "multiple of 4"),
        (["--export-dir", "/nonexistent/export"], "--export-dir"),
        (["--split", "test"], "split 'test'"),
        (["--precision", "fp16"], "fp16"),
        (["--gt", __file__], "do not combine"),
    ],
)
def test_eval_cli_data_mode_bad_input(data_dir, export_dir, args, message):
    base = ["--data", str(data_dir), "--export-dir", str(export_dir)]
    if args[0] == "--export-dir":
        base = ["--data", str(data_dir)]
    res = CliRunner().invoke(eval_main, [*base, *args])
    assert res.exit_code != 0
    assert message in res.output and "Traceback" not in res.output


@pytest.mark.parametrize(
    "table, change, message",
    [
        ("sample_annotation", lambda r: r.update(size={}), "field 'size' must be 3 positive finite numbers"),
        ("sample", lambda r: r.update(timestamp=10**400), "field 'timestamp'"),
        ("sample_data", lambda r: r.update(filename="/etc/hostname"), "must be a relative path inside the dataset root"),
    ],
)
def test_eval_cli_data_mode_names_a_malformed_table_row(data_dir, export_dir, tmp_path, table, change, message):
    root = tmp_path / "data"
    shutil.copytree(data_dir, root, copy_function=os.link)  # hard links: same files, private tables
    path = root / "v1.0-synth" / f"{table}.json"
    rows = json.loads(path.read_text())
    for row in rows:
        change(row)
    path.unlink()  # not through the link: the shared dataset stays as it is
    path.write_text(json.dumps(rows))
    res = CliRunner().invoke(eval_main, ["--data", str(root), "--export-dir", str(export_dir)])
    assert res.exit_code == 1 and "Traceback" not in res.output
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("Error: nuScenes table") and f"'{table}'" in last and message in last


def test_eval_cli_needs_a_mode():
    res = CliRunner().invoke(eval_main, [])
    assert res.exit_code != 0 and "--data" in res.output
