"""Fixtures several test files share."""

import os
import signal
from dataclasses import dataclass
from pathlib import Path

import pytest

# Every session the tests open runs on onnxruntime's CPU provider, also on a machine with onnxruntime-gpu: the tests
# compare outputs bit for bit, which a GPU's kernel choices would not keep, and TensorRT would build engines for
# minutes. The variable reaches the tools the tests start as processes too. A developer who sets it runs them elsewhere.
os.environ.setdefault("STREAMDET_PROVIDERS", "cpu")


@pytest.fixture(scope="session")
def tiny_synth_data(tmp_path_factory) -> Path:
    """One synthetic scene of two samples at 160x90: the smallest dataset the evaluation and studies can score."""
    from streamdet.data.synth_world import WorldConfig
    from streamdet.data.synth_writer import SynthConfig, generate_dataset

    out = tmp_path_factory.mktemp("tiny_synth_data")
    generate_dataset(out, SynthConfig(num_scenes=1, seed=2, resolution=(160, 90), world=WorldConfig(samples_per_scene=2)))
    return out


@pytest.fixture(scope="session")
def tiny_drive_data(tmp_path_factory) -> Path:
    """One key frame with ten 20 Hz sweeps before it (0.5 s of drive) and 12 Hz cameras (as nuScenes) at 160x90, all
    in the split "all": the replays' drive. Shared read-only."""
    from streamdet.data.synth_world import WorldConfig
    from streamdet.data.synth_writer import SynthConfig, generate_dataset

    out = tmp_path_factory.mktemp("tiny_drive_data")
    generate_dataset(out, SynthConfig(num_scenes=1, seed=5, resolution=(160, 90), sweeps_per_sample=10, camera_hz=12.0,
                                      val_fraction=0.0, world=WorldConfig(samples_per_scene=1)))  # fmt: skip
    return out


@pytest.fixture(scope="session")
def tiny_train_data(tmp_path_factory) -> Path:
    """Three synthetic scenes of two samples at the tiny preset's 128x72: scenes 0 and 1 train (4 samples), scene 2
    val. The training tests' dataset, shared read-only (caches go elsewhere)."""
    from streamdet.data.synth_world import WorldConfig
    from streamdet.data.synth_writer import SynthConfig, generate_dataset

    out = tmp_path_factory.mktemp("tiny_train_data")
    generate_dataset(out, SynthConfig(num_scenes=3, seed=3, resolution=(128, 72), world=WorldConfig(samples_per_scene=2)))
    return out


# ---- shared exports ----------------------------------------------------------------------------------------
# Each is made once per test session with streamdet-export and shared read-only: a test that changes an export
# copies it first. Tests of the exporter itself make their own.


@dataclass(frozen=True)
class CliExport:
    path: Path  # the export directory
    output: str  # what streamdet-export printed


def _cli_export(tmp_path_factory, name: str, args: list[str]) -> CliExport:
    from click.testing import CliRunner

    from streamdet.export.cli import main as export_main

    out = tmp_path_factory.mktemp(name) / "tiny"
    result = CliRunner().invoke(export_main, ["--preset", "tiny", *args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    return CliExport(out, result.output)


@pytest.fixture(scope="session")
def tiny_weights(tmp_path_factory) -> Path:
    """Weights of the tiny preset drawn with seed 0 (save_weights' format); read-only: copy it before editing."""
    import torch

    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "tiny.pt"
    save_weights(path, get_preset("tiny"), build_detector(get_preset("tiny")))
    return path


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory) -> Path:
    """A tiny camera + LiDAR export (fp32 + fp16, 8 slices), shared read-only: tests that change it copy it first."""
    return _cli_export(tmp_path_factory, "tiny_export", ["--fp16", "--slices", "8"]).path


@pytest.fixture(scope="session")
def tiny_export_fp32(tmp_path_factory) -> Path:
    """A tiny camera + LiDAR export with the fp32 graphs alone (8 slices): for the "no fp16 graphs" refusals."""
    return _cli_export(tmp_path_factory, "tiny_export_fp32", ["--slices", "8"]).path


@pytest.fixture(scope="session")
def tiny_int8_export(tmp_path_factory) -> CliExport:
    """A tiny camera + LiDAR export with fp32 and int8 graphs (calibrated on the bundled sample), and what the
    exporter printed."""
    return _cli_export(tmp_path_factory, "tiny_int8_export", ["--int8"])


@pytest.fixture(scope="session")
def tiny_lidar_export(tmp_path_factory) -> Path:
    """A tiny LiDAR-only export (fp32, 8 slices) of seeded weights whose heatmap logits are spread (so they detect
    something): the fallback of a tiny camera + LiDAR export. Shared read-only."""
    import dataclasses

    import torch

    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    preset = dataclasses.replace(get_preset("tiny"), use_image=False)
    torch.manual_seed(5)
    model = build_detector(preset).eval()
    with torch.no_grad():
        for task in model.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
    root = tmp_path_factory.mktemp("tiny_lidar_export")
    save_weights(root / "lidar.pt", preset, model)
    return _cli_export(tmp_path_factory, "tiny_lidar_export", ["--checkpoint", str(root / "lidar.pt"), "--slices", "8"]).path


# Property tests (tests/test_property_*.py): a bounded, derandomized profile in CI; HYPOTHESIS_PROFILE=long by hand.
try:
    import os as _os

    from hypothesis import HealthCheck, settings

    settings.register_profile(
        "ci", max_examples=40, deadline=None, derandomize=True, print_blob=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )  # fmt: skip
    settings.register_profile(
        "long", max_examples=3000, deadline=None, print_blob=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )  # fmt: skip
    settings.load_profile(_os.environ.get("HYPOTHESIS_PROFILE", "ci"))
except ImportError:  # hypothesis is in the dev extra; without it the property tests skip themselves
    pass


@pytest.fixture
def alarm():
    """Turn a hang into a failure: SIGALRM (a TimeoutError in the test) after 10 s. For reads of FIFOs and other
    calls that must never block."""

    def handler(signum, frame):
        raise TimeoutError("blocked for 10 s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.alarm(10)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)
