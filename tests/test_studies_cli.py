"""``streamdet-study`` end to end on a tiny export and dataset: tables, JSON keys, PNGs, one-line errors."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner

from streamdet.studies.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def export_dir(tiny_export_fp32) -> Path:
    return tiny_export_fp32  # fp32 graphs alone, 8 slices (conftest)


@pytest.fixture(scope="module")
def data_dir(tiny_synth_data) -> Path:
    return tiny_synth_data


@pytest.fixture(scope="module")
def lidar_only_checkpoint(tmp_path_factory) -> Path:
    import torch

    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    torch.manual_seed(0)
    preset = dataclasses.replace(get_preset("tiny"), use_image=False)
    path = tmp_path_factory.mktemp("ckpt") / "lidar_only.pt"
    save_weights(path, preset, build_detector(preset).eval())
    return path


def _run(args: list[str]):
    return CliRunner().invoke(main, args, catch_exceptions=False)


def _base(export_dir, data_dir, tmp_path, name) -> list[str]:
    return ["--export-dir", str(export_dir), "--data", str(data_dir), "--split", "all",
            "--json", str(tmp_path / f"{name}.json"), "--plot", str(tmp_path / f"{name}.png")]  # fmt: skip


def _outputs(tmp_path, name) -> dict:
    assert (tmp_path / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
    return json.loads((tmp_path / f"{name}.json").read_text())


def test_slices_with_a_pytorch_lidar_only_baseline(export_dir, data_dir, lidar_only_checkpoint, tmp_path):
    res = _run(["slices", *_base(export_dir, data_dir, tmp_path, "s"), "--counts", "1,4,8",
                "--baseline-checkpoint", str(lidar_only_checkpoint)])  # fmt: skip
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "s")
    assert d["study"] == "slices" and d["slice_counts"] == [1, 4, 8] and d["num_samples"] == 2
    assert set(d["fused"]) == set(d["baseline"]) == {"1", "4", "8"}
    assert {"mAP", "NDS", "AP"} <= set(d["fused"]["8"]) and set(d["fused"]["8"]["AP"]) == set(d["classes"])
    assert "LiDAR only" in d["baseline_source"] and "PyTorch" in d["baseline_source"]
    assert "LiDAR-only baseline" in res.output and "mAP averages" in res.output


def test_checkpoint_is_exported_first(data_dir, tmp_path):
    import torch

    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    torch.manual_seed(1)
    ckpt = tmp_path / "fused.pt"
    save_weights(ckpt, get_preset("tiny"), build_detector(get_preset("tiny")).eval())
    res = _run(["drop-camera", "--checkpoint", str(ckpt), "--data", str(data_dir), "--split", "all", "--max-samples", "1",
                "--json", str(tmp_path / "d.json")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "streamdet-study-" in json.loads((tmp_path / "d.json").read_text())["source"]  # the temporary export


def test_a_checkpoint_whose_export_fails_parity_is_named(data_dir, tmp_path, monkeypatch):
    """The study's own words, naming the checkpoint, not the runtime's refusal of a temporary folder gone by then."""
    import torch

    from streamdet.export import graph_steps
    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    torch.manual_seed(1)
    ckpt = tmp_path / "fused.pt"
    save_weights(ckpt, get_preset("tiny"), build_detector(get_preset("tiny")).eval())
    monkeypatch.setattr(graph_steps, "TORCH_TOL_REL", -1.0)  # every fp32 check fails
    res = _run(["drop-camera", "--checkpoint", str(ckpt), "--data", str(data_dir), "--split", "all", "--max-samples", "1"])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert f"exporting {ckpt}: the graphs failed their parity check (" in res.output
    assert "streamdet-study-" not in res.output.split("Error:")[-1]


def test_slices_without_baseline_says_so(export_dir, data_dir, tmp_path):
    res = _run(["slices", *_base(export_dir, data_dir, tmp_path, "s"), "--counts", "8", "--max-samples", "1"])
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "s")
    assert d["baseline"] is None and d["num_samples"] == 1 and "fused column only" in res.output


def test_drop_camera_reports_the_camera(export_dir, data_dir, tmp_path):
    res = _run(["drop-camera", *_base(export_dir, data_dir, tmp_path, "d"), "--camera", "CAM_BACK_LEFT", "--no-cameras"])
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "d")
    assert d["dropped_cameras"] == ["CAM_BACK_LEFT"] and set(d["without"]) == {"CAM_BACK_LEFT"}
    assert set(d["no_cameras"]) == {"mAP", "NDS", "AP"} and "without every camera" in res.output
    assert "without CAM_BACK_LEFT" in res.output and d["num_slices"] == 8


def test_drop_camera_defaults_to_the_back_camera(export_dir, data_dir, tmp_path):
    res = _run(["drop-camera", *_base(export_dir, data_dir, tmp_path, "d"), "--slices", "4", "--max-samples", "1"])
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "d")
    assert d["dropped_cameras"] == ["CAM_BACK"] and d["num_slices"] == 4


def test_calib_noise_zero_level_equals_reference(export_dir, data_dir, tmp_path):
    res = _run(["calib-noise", *_base(export_dir, data_dir, tmp_path, "c"), "--level", "0,0", "--level", "3,30", "--seeds", "2"])
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "c")
    zero, noisy = d["levels"]
    assert zero["mAP_per_seed"] == [d["reference"]["mAP"]] * 2 and zero["lut_changed_fraction"] == 0.0
    assert noisy["max_angle_deg"] == 3.0 and noisy["max_translation_m"] == pytest.approx(0.3)
    assert noisy["lut_changed_fraction"] > 0 and d["graphs_untouched"] is True and d["seeds"] == [0, 1]
    assert {"mAP_mean", "mAP_std", "AP_mean"} <= set(noisy)


def test_resolution_rows(export_dir, data_dir, tmp_path):
    res = _run(["resolution", *_base(export_dir, data_dir, tmp_path, "r"), "--resolution", "320x180", "--resolution", "128x72"])
    assert res.exit_code == 0, res.output
    d = _outputs(tmp_path, "r")
    assert [(r["width"], r["height"], r["upsampled"]) for r in d["rows"]] == [(320, 180, True), (128, 72, False)]
    assert all(r["image_lane_p50_ms"] > 0 and r["image_lane_count"] == 2 for r in d["rows"])
    assert "upsampled" in res.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["drop-camera", "--camera", "CAM_NOPE"], "unknown camera 'CAM_NOPE'"),
        (["slices", "--counts", "1,3"], "slice count 3"),
        (["slices", "--counts", "a,b"], "comma-separated integers"),
        (["calib-noise", "--level", "1"], "DEG,CM"),
        (["calib-noise", "--level", "1,-5"], "translation"),
        (["resolution", "--resolution", "800by450"], "WIDTHxHEIGHT"),
        (["slices", "--split", "nope"], "has no split 'nope'"),
        (["slices", "--split", "val"], "holds no samples"),
        (["drop-camera", "--precision", "fp16"], "no fp16 graphs"),
        (["drop-camera", "--image-precision", "int8"], "no int8 graphs"),
    ],
)
def test_bad_input_is_a_one_line_error(export_dir, data_dir, args, message):
    res = _run([*args, "--export-dir", str(export_dir), "--data", str(data_dir)])
    assert res.exit_code != 0
    assert message in res.output and "Traceback" not in res.output
    assert sum(line.startswith("Error") for line in res.output.splitlines()) == 1


def test_missing_data_unknown_study_and_bad_model_sources(export_dir, data_dir, lidar_only_checkpoint, tmp_path):
    res = _run(["drop-camera", "--export-dir", str(export_dir), "--data", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "does not exist" in res.output
    res = _run(["ablate", "--data", str(data_dir)])
    assert res.exit_code == 2 and "No such command 'ablate'" in res.output
    res = _run(["slices", "--export-dir", str(tmp_path), "--data", str(data_dir)])
    assert res.exit_code == 1 and "holds no manifest.json: not an export directory" in res.output  # as every tool says it
    res = _run(["slices", "--export-dir", str(export_dir), "--checkpoint", str(lidar_only_checkpoint), "--data", str(data_dir)])
    assert res.exit_code == 2 and "not both" in res.output
    res = _run(["slices", "--checkpoint", str(lidar_only_checkpoint), "--data", str(data_dir), "--split", "all"])
    assert res.exit_code == 1 and "LiDAR-only model: pass it as --baseline-checkpoint" in res.output
    assert "Traceback" not in res.output


def test_runs_without_torch(export_dir, data_dir):
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None  # any import of torch now fails
        from click.testing import CliRunner
        from streamdet.studies.cli import main
        res = CliRunner().invoke(main, ["calib-noise", "--export-dir", {str(export_dir)!r}, "--data", {str(data_dir)!r},
                                        "--split", "all", "--max-samples", "1", "--level", "1,10", "--seeds", "1"])
        assert res.exit_code == 0, res.output
        assert not any(m == "torch" or m.startswith("torch.") for m in sys.modules if sys.modules[m] is not None)
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr + out.stdout
    assert out.stdout.strip().endswith("ok")
