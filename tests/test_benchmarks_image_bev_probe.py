"""The image BEV probe (benchmarks/image_bev_probe.py): the probe on separable data, and a tiny end-to-end run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from streamdet.benchmarks.image_bev_probe import balanced_probe, measure
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.checkpoint import save_weights


@pytest.mark.parametrize("seed", range(3))
def test_probe_separates_separable_classes_and_not_noise(seed):
    rng = np.random.default_rng(seed)
    y = rng.integers(0, 3, 300)
    centres = rng.normal(0, 5, (3, 4))
    x = centres[y] + rng.normal(0, 0.3, (300, 4))
    assert balanced_probe(x[:200], y[:200], x[200:], y[200:]) > 0.95
    noise = rng.normal(0, 1, (300, 4))
    assert balanced_probe(noise[:200], y[:200], noise[200:], y[200:]) < 0.6
    assert math.isnan(balanced_probe(x[:10], np.zeros(10, int), x[10:], y[10:]))  # one class: nothing to learn


def test_measure_on_a_tiny_checkpoint(tiny_synth_data, tmp_path):
    torch.manual_seed(0)
    preset = get_preset("tiny")
    ckpt = tmp_path / "tiny.pt"
    det = build_detector(preset)
    save_weights(ckpt, preset, det)
    before = {k: v.clone() for k, v in det.state_dict().items()}
    out = measure(ckpt, tiny_synth_data, None, 2)
    assert out["samples"] == 2 and out["rms_occupied"]["point"] > 0
    assert out["image_over_point_rms"] == pytest.approx(out["rms_occupied"]["fused"] / out["rms_occupied"]["point"])
    again = measure(ckpt, tiny_synth_data, None, 2)  # the train-mode pass leaves the statistics as they were
    assert again["rms_occupied"]["raw_eval"] == out["rms_occupied"]["raw_eval"]
    assert all(torch.equal(v, before[k]) for k, v in det.state_dict().items())
