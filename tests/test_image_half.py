"""The image_half layout (models/image_half.py): the BEV encoder's image half computed in the lifter graph.

Naive references: PyTorch's SliceNet on the image BEV (the trained function), a hand-built conv of the image half
(the trained conv's image channels scaled by the BatchNorm, no bias), the conv's own output size, and the image_bev
export of the same weights through the same runtime.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF, check_image_layout, image_half_cells, image_map_chw
from streamdet.data.sample import load_bundled_sample
from streamdet.models.detector import build_detector
from streamdet.models.export_form import to_export_form
from streamdet.models.image_half import ImageHalfLifter
from streamdet.models.presets import get_preset
from streamdet.models.slice_split import ExportSliceNet
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.manifest import ManifestError, read_manifest

N_SLICES = 8


def _preset(stage0_stride: int):
    """The tiny preset, or with a strided first conv (the small and paper-like case: the image half is coarser)."""
    preset = get_preset("tiny")
    if stage0_stride == 1:
        return preset
    bev = dataclasses.replace(preset.bev, layer_strides=(stage0_stride, 1), upsample_strides=(1.0, 1.0))
    return dataclasses.replace(preset, bev=bev)


def _detector(seed: int, stage0_stride: int = 1):
    torch.manual_seed(seed)
    det = build_detector(_preset(stage0_stride)).eval()
    with torch.no_grad():  # BatchNorm statistics off their defaults, so the fold is exercised
        for m in det.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.3, 0.3)
    return det


def _pillars(det, q: int, gen: torch.Generator):
    pre = det.preset
    yq, xq = pre.map_cells
    p, m = 40, pre.pillars.max_points_per_pillar
    features = torch.randn(p, m, pre.pillars.num_point_features, generator=gen)
    mask = (torch.rand(p, m, generator=gen) > 0.3).float()
    index = torch.randperm(q * yq * xq, generator=gen)[:p]
    return features, mask, index


def _naive_image_half(det, image_bev: torch.Tensor) -> torch.Tensor:
    """The image channels of stage 0's first conv, BatchNorm scale applied, no shift: a hand-built reference."""
    conv, bn = det.slice_net.bev_encoder.blocks[0][0], det.slice_net.bev_encoder.blocks[0][1]
    c = conv.in_channels // 2
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)  # (C0,)
    weight = conv.weight[:, c:] * scale.view(-1, 1, 1, 1)
    return F.conv2d(image_bev, weight, stride=conv.stride, padding=conv.padding)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("q", [1, 2])
@pytest.mark.parametrize("stride", [1, 2])
def test_slice_net_on_the_image_half_is_slicenet_on_the_image_bev(seed, q, stride):
    det = _detector(seed, stride)
    gen = torch.Generator().manual_seed(seed)
    pillars = _pillars(det, q, gen)
    image_bev = torch.randn(q, det.preset.channels, *det.preset.map_cells, generator=gen)
    half_net = ExportSliceNet(det.slice_net, IMAGE_HALF).eval()
    with torch.no_grad():
        image_half = _naive_image_half(det, image_bev)
        want = det.slice_net(*pillars, image_bev)
        got = half_net(*pillars, image_half)
        want_none = det.slice_net(*pillars, None, num_quadrants=q)  # no image yet: zeros
        got_none = half_net(*pillars, torch.zeros_like(image_half))  # what the runtime feeds then
        got_absent = half_net(*pillars, None, num_quadrants=q)
    for w, g, wn, gn, ga in zip(want, got, want_none, got_none, got_absent):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(gn, wn, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(ga, wn, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("stride", [1, 2])
def test_image_half_lifter_is_the_naive_conv_of_the_lifted_bev(seed, stride):
    det = _detector(seed, stride)
    form = to_export_form(det, IMAGE_HALF)
    assert isinstance(form.volumetric_lifter, ImageHalfLifter)
    g = det.preset.grid
    gen = torch.Generator().manual_seed(seed)
    j, hf, wf = 3, 5, 7
    features = torch.randn(j, det.preset.channels, hf, wf, generator=gen)
    sentinel = j * hf * wf  # an empty slot (lifter.gather_volume)
    index = torch.randint(0, sentinel + 1, (1, 2, g.nz, g.quadrant_ny, g.quadrant_nx), generator=gen)
    weight = torch.rand(1, 2, g.nz, g.quadrant_ny, g.quadrant_nx, generator=gen) * (index < sentinel)
    with torch.no_grad():
        got = form.volumetric_lifter(features, index, weight)
        want = _naive_image_half(det, det.lifter(features, index, weight))
    c0, yh, xh = image_map_chw(det.preset.to_dict(), (g.quadrant_ny, g.quadrant_nx), IMAGE_HALF)
    assert got.shape == (1, c0, yh, xh)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("size", [1, 2, 7, 64, 65])
@pytest.mark.parametrize("stride", [1, 2, 3])
def test_image_half_cells_is_the_conv_output_size(size, stride):
    out = F.conv2d(torch.zeros(1, 1, size, size + 1), torch.zeros(1, 1, 3, 3), stride=stride, padding=1)
    assert image_half_cells((size, size + 1), stride) == tuple(out.shape[-2:])


def test_bad_layouts_and_strides_are_refused():
    with pytest.raises(ValueError, match="image_bevv"):
        check_image_layout("image_bevv")
    with pytest.raises(ValueError, match="stride"):
        image_half_cells((8, 8), 0)
    with pytest.raises(ValueError, match="nope"):
        to_export_form(_detector(0), "nope")


# ---- the export and the runtime -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def half_export(tmp_path_factory) -> Path:
    from click.testing import CliRunner

    from streamdet.export.cli import main as export_main

    out = tmp_path_factory.mktemp("tiny_image_half") / "tiny"
    args = ["--preset", "tiny", "--slices", str(N_SLICES), "--image-layout", IMAGE_HALF, "--int8", "--out", str(out)]
    result = CliRunner().invoke(export_main, args)
    assert result.exit_code == 0, result.output
    return out


def _images(det: StreamingDetector, sample) -> dict[str, np.ndarray]:
    img = det.manifest.image
    arr = sample.load_images((img.width, img.height))  # (J, H, W, 3)
    return {n: arr[sample.rig.names.index(n)] for n in det.camera_names}


def _run(export_dir: Path, sample, with_images: bool):
    det = StreamingDetector(export_dir)
    if with_images:
        det.update_images(_images(det, sample), timestamp=1.0)
    return det.detect_sweep_slices(sample.points, timestamp=1.05, num_slices=N_SLICES)


@pytest.mark.parametrize("with_images", [True, False])
def test_image_half_export_detects_what_the_image_bev_export_does(tiny_export_fp32, half_export, with_images):
    sample = load_bundled_sample()
    old = _run(tiny_export_fp32, sample, with_images)
    new = _run(half_export, sample, with_images)
    for a, b in zip(old.slices, new.slices):
        da, db = a.detections, b.detections
        assert da.boxes.shape == db.boxes.shape
        np.testing.assert_array_equal(da.labels, db.labels)
        np.testing.assert_allclose(db.scores, da.scores, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(db.boxes, da.boxes, rtol=1e-4, atol=1e-3)


def test_the_manifest_names_the_layout_and_its_shapes(tiny_export_fp32, half_export):
    old, new = read_manifest(tiny_export_fp32), read_manifest(half_export)
    assert old.image_layout == IMAGE_BEV and new.image_layout == IMAGE_HALF
    lifter = new.graph("volumetric_lifter")
    g = get_preset("tiny").grid
    c0, yh, xh = image_map_chw(new.preset, (g.quadrant_ny, g.quadrant_nx), IMAGE_HALF)
    assert [t.name for t in lifter.outputs] == [IMAGE_HALF]
    assert tuple(lifter.outputs[0].shape[1:]) == (c0, yh, xh)
    assert new.graph("slice_head").inputs[3].name == IMAGE_HALF


def test_a_manifest_without_the_field_is_the_image_bev_layout(tiny_export_fp32, tmp_path):
    d = json.loads((tiny_export_fp32 / "manifest.json").read_text())
    d.pop("image_layout", None)
    copy = tmp_path / "old"
    shutil.copytree(tiny_export_fp32, copy)
    (copy / "manifest.json").write_text(json.dumps(d))
    assert StreamingDetector(copy).manifest.image_layout == IMAGE_BEV


@pytest.mark.parametrize("layout", ["image_half", "sideways"])
def test_a_manifest_that_misnames_the_layout_is_refused(tiny_export_fp32, tmp_path, layout):
    d = json.loads((tiny_export_fp32 / "manifest.json").read_text())
    d["image_layout"] = layout  # the graphs are image_bev ones
    copy = tmp_path / "bad"
    shutil.copytree(tiny_export_fp32, copy)
    (copy / "manifest.json").write_text(json.dumps(d))
    with pytest.raises(ManifestError, match="image_half|image_layout|sideways"):
        StreamingDetector(copy)


def test_the_int8_graphs_of_the_image_half_layout_run_and_are_recorded(half_export):
    sample = load_bundled_sample()
    det = StreamingDetector(half_export, DetectorConfig(precision="int8"))
    det.update_images(_images(det, sample), timestamp=1.0)
    result = det.detect_sweep_slices(sample.points, timestamp=1.05, num_slices=N_SLICES)
    assert len(result.slices) == N_SLICES
    lifter_records = [p for p in det.manifest.int8.parity if p.graph == "volumetric_lifter"]
    assert lifter_records and all(p.output == IMAGE_HALF for p in lifter_records)
