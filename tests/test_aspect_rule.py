"""One aspect rule for every tool: streamdet-synth and streamdet-train refuse the camera image sizes that
streamdet-export and the runtime refuse (calibration.lut.check_rig_fits), before any work, naming what would fit."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from streamdet.calibration.camera import CalibrationError
from streamdet.calibration.lut import check_rig_fits
from streamdet.core.constants import STEM_STRIDE
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import (
    SynthConfig, _bundled_rig, fitting_resolutions, generate_dataset, resolution_problem,
)  # fmt: skip
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.batching import Collator, check_rig_fits_preset
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import build_store
from streamdet.training.torch_eval import TorchSweepDetector
from streamdet.training.trainer import TrainConfig, train

TINY = get_preset("tiny")
# The sizes the tests, docs and scripts make datasets at (grep --resolution / resolution=): all must stay accepted.
DOCUMENTED_SIZES = [(32, 18), (48, 27), (64, 36), (128, 72), (160, 90), (192, 108), (384, 216), (480, 270), (800, 450),
                    (1600, 900), (4096, 2304)]  # fmt: skip
OFF_ASPECT = [(320, 240), (17, 31), (16, 16), (4096, 16), (4096, 4096)]


def _runtime_fits(width: int, height: int) -> bool:
    rig = _bundled_rig()
    try:
        check_rig_fits(rig, rig.names, width, height)
    except CalibrationError:
        return False
    return True


def _one_line(result) -> str:
    assert result.exit_code != 0 and isinstance(result.exception, SystemExit), (result.output, result.exception)
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    return errors[0]


# ---- streamdet-synth ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", DOCUMENTED_SIZES + [(427, 240), (801, 450), (55, 31)])
def test_sizes_of_the_rigs_aspect_are_accepted(size):
    assert resolution_problem(size) is None
    assert SynthConfig(resolution=size).resolution == size


@pytest.mark.parametrize("size", [(w, h) for w in (16, 17, 31, 55, 320, 321, 427, 799, 800, 801, 4096)
                                  for h in (16, 18, 31, 180, 181, 240, 449, 450, 451, 2304, 4096)])  # fmt: skip
def test_synth_refuses_exactly_what_the_runtime_refuses(size):
    """Not a second copy of the rule: synth's verdict is check_rig_fits's on the rig it writes, at every size."""
    assert (resolution_problem(size) is None) == _runtime_fits(*size)


@pytest.mark.parametrize("size, nearest", [((320, 240), "320x180 or 426x240"), ((17, 31), "32x18 or 50x28"),
                                           ((16, 16), "the nearest size that fits: 32x18"),
                                           ((4096, 4096), "the nearest size that fits: 4096x2304")])  # fmt: skip
def test_synth_config_names_the_rule_and_what_fits(size, nearest):
    with pytest.raises(ValueError, match="SynthConfig.resolution") as e:
        SynthConfig(resolution=size)
    msg = str(e.value)
    assert "\n" not in msg and f"{size[0]}x{size[1]}" in msg and nearest in msg
    assert "1600x900" in msg and "check_rig_fits" in msg and "aspect" in msg


@pytest.mark.parametrize("size", OFF_ASPECT + [(321, 240), (800, 451)])
def test_the_suggested_sizes_fit(size):
    near = fitting_resolutions(*size)
    assert 1 <= len(near) <= 2 and len(set(near)) == len(near)
    for w, h in near:
        assert _runtime_fits(w, h) and 16 <= w <= 4096 and 16 <= h <= 4096
        assert w % STEM_STRIDE == 0 and h % STEM_STRIDE == 0  # a size streamdet-export takes too (427x240 was not)
        assert SynthConfig(resolution=(w, h)).resolution == (w, h)


def test_a_fitting_size_is_its_own_nearest():
    assert fitting_resolutions(384, 216) == [(384, 216)]
    assert fitting_resolutions(320, 240) == [(320, 180), (426, 240)]  # the same width, then the same height


def test_range_errors_come_before_the_aspect():
    with pytest.raises(ValueError, match="16..4096 pixels each"):
        SynthConfig(resolution=(8, 8))
    with pytest.raises(ValueError, match="16..4096 pixels each"):
        SynthConfig(resolution=(320.0, 240))


@pytest.mark.parametrize("text, nearest", [("320x240", "320x180 or 426x240"), ("17x31", "32x18 or 50x28"),
                                           ("16x16", "32x18")])  # fmt: skip
def test_synth_cli_refuses_before_writing(tmp_path, text, nearest):
    out = tmp_path / "ds"
    args = ["--out", str(out), "--scenes", "1", "--samples-per-scene", "1", "--resolution", text]
    result = CliRunner().invoke(synth_main, args)
    line = _one_line(result)
    assert result.exit_code == 2 and "--resolution" in line and text in line and nearest in line and "aspect" in line
    assert not out.exists()  # refused before any work: not even world.json


# ---- streamdet-train ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def off_aspect_data(tmp_path_factory) -> Path:
    """What streamdet-synth wrote before it refused the size: one 64x48 (4:3) sample per scene, 2 scenes."""
    cfg = SynthConfig(num_scenes=2, seed=4, resolution=(64, 36), world=WorldConfig(samples_per_scene=1))
    object.__setattr__(cfg, "resolution", (64, 48))  # past SynthConfig's check, as an older dataset is
    out = tmp_path_factory.mktemp("off_aspect")
    generate_dataset(out, cfg)
    return out


@pytest.fixture(scope="module")
def off_aspect_store(off_aspect_data):
    return build_store(off_aspect_data, "train", (TINY.image.width_px, TINY.image.height_px))


def test_collator_refuses_a_store_the_runtime_would_refuse(off_aspect_data, off_aspect_store):
    with pytest.raises(ValueError) as e:
        Collator(TINY).check_store(off_aspect_store, off_aspect_data)
    msg = str(e.value)
    assert "\n" not in msg and f"dataset {off_aspect_data}, sample {off_aspect_store.tokens[0]}" in msg
    assert "CAM_FRONT is 64x48" in msg and "128x72" in msg and "'tiny'" in msg


def test_lidar_only_presets_read_no_image(off_aspect_data, off_aspect_store):
    Collator(dataclasses.replace(TINY, use_image=False)).check_store(off_aspect_store, off_aspect_data)


def test_collator_lut_checks_a_rig_it_was_not_shown(off_aspect_store):
    with pytest.raises(ValueError, match="sample 0: its cameras do not fit the 128x72 images"):
        Collator(TINY).lut(off_aspect_store.rigs[0], "sample 0")


def test_a_fitting_dataset_passes(tiny_train_data, tmp_path):
    store = build_store(tiny_train_data, "train", (TINY.image.width_px, TINY.image.height_px))
    Collator(TINY).check_store(store, tiny_train_data)
    check_rig_fits_preset(store.rigs[0].resized(427, 240), TINY, "x")  # 16:9 within the tolerance


def test_train_refuses_and_leaves_nothing(off_aspect_data, off_aspect_store, tmp_path):
    out = tmp_path / "run"
    config = TrainConfig(preset="tiny", steps=1, batch_size=1)
    with pytest.raises(ValueError, match=r"sample .*: its cameras do not fit .* CAM_FRONT is 64x48"):
        train(config, off_aspect_data, out, store=off_aspect_store, device="cpu", echo=lambda _m: None)
    assert not out.exists()


def test_train_cli_names_the_dataset_and_the_camera(off_aspect_data, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(train_main, ["--data", str(off_aspect_data), "--out", str(out), "--preset", "tiny",
                                             "--steps", "1", "--cache-dir", str(tmp_path / "cache")])  # fmt: skip
    line = _one_line(result)
    assert f"dataset {off_aspect_data}, sample " in line and "CAM_FRONT is 64x48 (aspect 1.3333)" in line
    assert "streamdet-export and the runtime would refuse" in line and not out.exists()


def test_torch_evaluation_refuses_the_sample(off_aspect_data):
    sample = NuScenesReader(off_aspect_data, "v1.0-synth").get(0)
    torch.manual_seed(0)
    detector = TorchSweepDetector(build_detector(TINY), num_slices=2)
    with pytest.raises(ValueError, match=f"sample {sample.token} \\(image {off_aspect_data}/samples/CAM_"):
        detector(sample)
