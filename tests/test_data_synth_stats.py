"""`streamdet-synth stats`: the cue measurements against naive references, on real and synthetic data, and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.data.sample import bundled_sample_dir
from streamdet.data.synth_cli import main
from streamdet.data.synth_stats import (
    RANGE_BINS,
    _angle_off_axes_deg,
    dataset_stats,
    format_table,
    in_box_face_distance,
    range_bin,
)
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_writer import SynthConfig, generate_dataset

TINY = SynthConfig(num_scenes=1, seed=3, resolution=(64, 36), world=WorldConfig(samples_per_scene=2))


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_stats")
    generate_dataset(root, TINY)
    return root


def _naive_face_distance(points, box):
    out = []
    x, y, z, w, l, h, yaw = box[:7]
    for p in points:
        dx, dy, dz = p[0] - x, p[1] - y, p[2] - z
        lx = math.cos(yaw) * dx + math.sin(yaw) * dy
        ly = -math.sin(yaw) * dx + math.cos(yaw) * dy
        m = min(l / 2 - abs(lx), w / 2 - abs(ly), h / 2 - abs(dz))
        if m >= 0:
            out.append(m)
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_face_distance_matches_naive(seed):
    rng = np.random.default_rng(seed)
    box = np.r_[rng.uniform(-5, 5, 3), rng.uniform(0.5, 4, 3), rng.uniform(-math.pi, math.pi)]
    pts = box[:3] + rng.uniform(-3, 3, size=(400, 3))
    got = in_box_face_distance(pts, box[None])[0]
    np.testing.assert_allclose(np.sort(got), np.sort(_naive_face_distance(pts, box)), atol=1e-12)


def test_face_distance_of_empty_input():
    assert in_box_face_distance(np.zeros((0, 3)), np.array([[0, 0, 0, 1, 1, 1, 0.0]]))[0].shape == (0,)
    assert in_box_face_distance(np.zeros((5, 3)), np.zeros((0, 7))) == []


@pytest.mark.parametrize("yaw,axes,expected", [(0.0, [0.0], 0.0), (math.pi, [0.0], 0.0), (0.3, [0.0], math.degrees(0.3)),
                                               (math.pi / 2, [0.0], 90.0), (1.0, [0.0, math.pi / 2], 90 - math.degrees(1.0)),
                                               (-0.2, [3.0], math.degrees(abs(-0.2 - 3.0 + math.pi)))])
def test_heading_off_road_axis(yaw, axes, expected):
    assert _angle_off_axes_deg(yaw, axes) == pytest.approx(expected, abs=1e-9)


def test_range_bins():
    np.testing.assert_array_equal(range_bin(np.array([0.0, 9.99, 10.0, 45.0, 55.0, 300.0])), [0, 0, 1, 4, 5, 5])
    assert len(RANGE_BINS) == 6


def test_real_sample_figures():
    stats = dataset_stats(bundled_sample_dir())
    assert stats["samples"] == 1
    assert stats["points_per_sweep_mean"] == pytest.approx(34688)
    assert stats["vehicles_off_road_axis_share"] is None  # no road information for real data
    assert stats["distractors_within_40m_per_frame"] is None
    assert 0.0 <= stats["sparse_share_within_50m"] <= 1.0
    shares = [c["share_of_annotations"] for c in stats["classes"].values()]
    assert sum(shares) == pytest.approx(1.0)
    car = stats["classes"]["car"]
    assert car["face_share"] < 0.5 and car["face_median_m"] > 0.05  # real cars are not their boxes
    assert json.loads(json.dumps(stats)) == stats


def test_synthetic_figures(tiny_dataset):
    stats = dataset_stats(tiny_dataset)
    assert stats["samples"] == TINY.world.samples_per_scene
    assert stats["world_version"] is not None
    assert stats["vehicles_heading_measured"] > 0
    assert stats["distractors_within_40m_per_frame"] is not None
    assert 20_000 < stats["points_per_sweep_mean"] < 45_000
    table = format_table(stats, dataset_stats(bundled_sample_dir()))
    assert table.splitlines()[0].count("|") == 4
    assert "car: in-box intensity median / mean" in table


def test_cli_stats_and_the_old_generator_invocation(tmp_path, tiny_dataset):
    runner = CliRunner()
    out = tmp_path / "gen"
    # The documented generator invocation (no subcommand) and the explicit subcommand both write a dataset.
    result = runner.invoke(main, ["--out", str(out), "--scenes", "1", "--samples-per-scene", "1", "--resolution", "32x18"])
    assert result.exit_code == 0, result.output
    assert (out / "v1.0-synth" / "sample.json").is_file()
    result = runner.invoke(main, ["generate", "--out", str(out), "--scenes", "1", "--samples-per-scene", "1",
                                  "--resolution", "32x18", "--overwrite"])
    assert result.exit_code == 0, result.output
    js = tmp_path / "s.json"
    result = runner.invoke(main, ["stats", str(tiny_dataset), "--json", str(js)])
    assert result.exit_code == 0, result.output
    doc = json.loads(js.read_text())
    assert doc["reference"]["samples"] == 1 and doc["data"]["samples"] == TINY.world.samples_per_scene
    assert "| figure |" in result.output


def test_cli_stats_bad_input(tmp_path):
    runner = CliRunner()
    result = runner.invoke(main, ["stats", str(tmp_path / "missing")])
    assert result.exit_code != 0
    assert "missing" in result.output and "Traceback" not in result.output
    (tmp_path / "empty").mkdir()
    result = runner.invoke(main, ["stats", str(tmp_path / "empty"), "--no-reference"])
    assert result.exit_code != 0 and "empty" in result.output
