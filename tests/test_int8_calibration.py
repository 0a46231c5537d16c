"""int8 calibration on a dataset (a tiny synthetic one): train-split samples, the graphs' real inputs (recorded by the
fp32 runtime) against a naive rebuild, and an export with --calibration-data whose parity is on the held-out
bundled sample."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import onnxruntime as ort
import pytest
from click.testing import CliRunner

from streamdet.calibration.compact_lut import lifter_feeds
from streamdet.calibration.lut_build import build_lut
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import load_image
from streamdet.data.slicing import slice_sample
from streamdet.data.synth_writer import SynthConfig
from streamdet.export import int8 as q8
from streamdet.export.cli import main
from streamdet.models.presets import Preset, get_preset
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.manifest import GRAPH_NAMES, read_manifest
from streamdet.runtime_ort.pillarize import pillarize

SYNTH = SynthConfig()  # the dataset's version


@pytest.fixture(scope="module")
def dataset(tiny_train_data):
    return tiny_train_data  # three scenes, two of them train (4 samples), read-only (conftest)


@pytest.fixture(scope="module")
def train_tokens(dataset):
    reader = NuScenesReader(dataset, SYNTH.version)
    scenes = set(json.loads((dataset / "splits.json").read_text())["train"])
    return [t for t in reader.sample_tokens if reader.scene_name(t) in scenes]


@pytest.fixture(scope="module")
def export_dir(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("int8_data") / "exp"
    args = ["--preset", "tiny", "--int8", "--calibration-data", str(dataset), "--calibration-samples", "2", "--out", str(out)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "(held-out sample)" in result.output
    return out


def test_samples_come_from_the_train_split(dataset, train_tokens):
    names = ("CAM_FRONT", "CAM_BACK")
    cal = q8.load_calibration_samples(dataset, 2, names)
    assert (cal.source, cal.version, cal.split) == (str(dataset), SYNTH.version, "train")
    tokens = [s.token for s in cal.samples]
    assert len(tokens) == 2 and set(tokens) <= set(train_tokens)
    assert tokens == [train_tokens[0], train_tokens[-1]]  # spread over the split: first and last
    every = q8.load_calibration_samples(dataset, 100, names)
    assert [s.token for s in every.samples] == train_tokens


def test_without_splits_every_sample_is_used(dataset, tmp_path):
    copy = tmp_path / "nosplit"
    shutil.copytree(dataset, copy)
    (copy / "splits.json").unlink()
    cal = q8.load_calibration_samples(copy, 100, ("CAM_FRONT",))
    assert cal.split == "all" and len(cal.samples) == len(NuScenesReader(copy, SYNTH.version))


def _tiny(width: int, height: int) -> Preset:
    p = get_preset("tiny")
    return dataclasses.replace(p, image=dataclasses.replace(p.image, width_px=width, height_px=height))


def test_recorded_inputs_against_a_naive_rebuild(dataset, export_dir):
    """The calibration feeds the fp32 runtime records (record_graph_inputs) against each graph's inputs built by hand:
    each sample's images, a LUT of its own rig, its slices pillarised with the fp32 lifter's image BEV."""
    m = read_manifest(export_dir)
    size = (m.image.width, m.image.height)
    preset = _tiny(*size)
    names = m.image.camera_names
    sessions = {n: ort.InferenceSession(str(export_dir / m.graph(n).file), providers=["CPUExecutionProvider"]) for n in GRAPH_NAMES}
    cal = q8.load_calibration_samples(dataset, 2, names)
    got = q8.record_graph_inputs(StreamingDetector(export_dir), cal.samples)
    enc, lift, slices = (got.feeds(n) for n in GRAPH_NAMES)
    assert len(enc) == len(lift) == 2
    expect_slices, order = 0, []
    for i, sample in enumerate(cal.samples):
        order += ["image_encoder", "volumetric_lifter"]
        images = np.stack([load_image(sample.image_paths[n], size) for n in names])
        assert np.array_equal(enc[i]["images"], images)
        lut = build_lut(sample.rig, preset.grid, preset.image.feature_stride, size)
        (features,) = sessions["image_encoder"].run(None, {"images": images})
        want = lifter_feeds(features, lut.index, lut.weight, m.lut_layout)  # the LUT in the export's layout
        assert sorted(lift[i]) == sorted(want)
        for name in want.keys() - {"features"}:
            assert np.array_equal(lift[i][name], want[name]), name
        np.testing.assert_allclose(lift[i]["features"], features, rtol=1e-5, atol=1e-5)
        (bev,) = sessions["volumetric_lifter"].run(None, lift[i])
        for s in slice_sample(sample, 8):
            pl = pillarize(s.points, preset.grid, s.quadrants, preset.pillars.max_points_per_pillar, preset.pillars.max_pillars)
            if pl.num_pillars == 0:
                continue
            feeds = slices[expect_slices]
            assert np.array_equal(feeds["pillar_index"], pl.index) and np.array_equal(feeds["pillar_features"], pl.features)
            np.testing.assert_allclose(feeds["image_bev"], bev[list(s.quadrants)], rtol=1e-5, atol=1e-5)
            expect_slices += 1
            order.append("slice_head")
    assert len(slices) == expect_slices > 0
    assert [r.graph for r in got.runs] == order  # sample by sample: its images, then its slices


def test_a_sample_of_another_camera_order_is_refused(dataset, export_dir):
    sample = q8.load_calibration_samples(dataset, 1, ("CAM_FRONT",)).samples[0]
    cameras = sample.rig.cameras[::-1]
    reordered = dataclasses.replace(sample, rig=dataclasses.replace(sample.rig, cameras=cameras))
    with pytest.raises(q8.Int8CalibrationDataError, match=f"calibration sample {sample.token}: .*do not match the export's"):
        q8.record_graph_inputs(StreamingDetector(export_dir), [reordered])


def test_manifest_names_the_dataset(dataset, export_dir, train_tokens):
    c = read_manifest(export_dir).int8.calibration
    assert (c.source, c.version, c.split) == (str(dataset), SYNTH.version, "train")
    assert set(c.sample_tokens) <= set(train_tokens) and len(c.sample_tokens) == 2
    assert c.num_images == 12 and c.num_volumes == 2 and c.parity_held_out
