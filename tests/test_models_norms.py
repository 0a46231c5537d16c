"""Batch-1 normalisation of the image backbone and the image BEV's scale at fusion (issue 19, item 2)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import onnxruntime as ort
import pytest
import torch

from streamdet.export.onnx_export import SLICE_HEAD_IO, export_slice_head
from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import SliceNet, StreamDetector
from streamdet.models.image_bev_norm import ImageBevNorm
from streamdet.models.image_encoder import ImageEncoder
from streamdet.models.norms import FrozenBatchNorm2d, norm2d
from streamdet.models.presets import Preset, get_preset
from streamdet.models.resnet import ResNet
from streamdet.models.slice_split import ExportSliceNet

TINY = get_preset("tiny")


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_frozen_bn_is_the_running_statistics_in_both_modes(seed, dtype):
    gen = torch.Generator().manual_seed(seed)
    bn = FrozenBatchNorm2d(5).to(dtype)
    with torch.no_grad():
        bn.running_mean.copy_(torch.randn(5, generator=gen))
        bn.running_var.copy_(torch.rand(5, generator=gen) + 0.5)
        bn.weight.copy_(torch.randn(5, generator=gen))
        bn.bias.copy_(torch.randn(5, generator=gen))
    x = torch.randn(1, 5, 4, 6, generator=gen, dtype=dtype)
    before = bn.running_mean.clone()
    ref = (x - bn.running_mean.view(1, -1, 1, 1)) / torch.sqrt(bn.running_var.view(1, -1, 1, 1) + bn.eps)
    ref = ref * bn.weight.view(1, -1, 1, 1) + bn.bias.view(1, -1, 1, 1)
    torch.testing.assert_close(bn.train()(x), ref)
    torch.testing.assert_close(bn.eval()(x), ref)
    assert torch.equal(bn.running_mean, before)


@pytest.mark.parametrize("norm", ["frozen_batch", "group"])
def test_backbone_keeps_torchvision_names_and_one_image_is_its_own_batch(norm):
    ref_keys = {k for k in ResNet(18, 8).state_dict() if "running" not in k and "num_batches" not in k}
    net = ResNet(18, 8, norm=norm)
    assert ref_keys <= set(net.state_dict())
    torch.manual_seed(0)
    x = torch.randn(3, 3, 32, 48)
    net.train()
    with torch.no_grad():
        alone = net(x[:1])
        together = net(x)
        evaluated = net.eval()(x[:1])
    for a, t, e in zip(alone, together, evaluated):
        torch.testing.assert_close(a, t[:1], rtol=1e-4, atol=1e-5)  # the other cameras do not change an image's features
        torch.testing.assert_close(a, e, rtol=1e-4, atol=1e-5)  # train mode == eval mode


def test_norm_kinds_and_bad_kind():
    assert isinstance(norm2d("batch", 8), torch.nn.BatchNorm2d)
    assert norm2d("group", 48).num_groups == 16 and norm2d("group", 4).num_groups == 4
    with pytest.raises(ValueError, match="'layer'"):
        norm2d("layer", 8)
    with pytest.raises(ValueError, match="'layer'"):
        dataclasses.replace(TINY.image, norm="layer")


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
def test_shipped_presets_serialise_as_before(name):
    d = get_preset(name).to_dict()
    assert "norm" not in d["image"] and "image_bev_norm" not in d  # existing manifests stay byte-identical
    assert "lut_heights_per_voxel" not in d["lifter"]
    assert Preset.from_dict(json.loads(json.dumps(d))) == get_preset(name)


def test_new_options_round_trip_and_reach_the_modules():
    p = dataclasses.replace(TINY, image=dataclasses.replace(TINY.image, norm="group"), image_bev_norm=True,
                            lifter=dataclasses.replace(TINY.lifter, lut_heights_per_voxel=4))  # fmt: skip
    d = json.loads(json.dumps(p.to_dict()))
    assert d["image"]["norm"] == "group" and d["image_bev_norm"] is True and d["lifter"]["lut_heights_per_voxel"] == 4
    assert Preset.from_dict(d) == p
    det = StreamDetector(p)
    assert isinstance(det.image_encoder.backbone.bn1, torch.nn.GroupNorm)
    assert isinstance(det.slice_net.image_bev_norm, ImageBevNorm)
    assert StreamDetector(dataclasses.replace(p, use_image=False)).slice_net.image_bev_norm is None


@pytest.mark.parametrize("seed", range(3))
def test_image_bev_norm_train_eval_and_zeros(seed):
    gen = torch.Generator().manual_seed(seed)
    norm = ImageBevNorm(4, momentum=1.0)
    x = torch.randn(2, 4, 5, 5, generator=gen) * torch.tensor([0.05, 0.5, 1.0, 10.0]).view(1, -1, 1, 1)
    y = norm.train()(x)
    rms = y.square().mean(dim=(0, 2, 3)).sqrt()
    ms = x.square().mean(dim=(0, 2, 3))
    torch.testing.assert_close(rms, torch.sqrt(ms / (ms + norm.eps)), rtol=1e-4, atol=1e-5)  # 1 up to eps
    torch.testing.assert_close(norm.eval()(x), y, rtol=1e-4, atol=1e-6)  # momentum 1: the running value is this batch's
    assert torch.count_nonzero(norm(torch.zeros(1, 4, 3, 3))) == 0  # no image yet stays no image


def _inputs(preset, q, num_pillars, seed):
    g, pc = preset.grid, preset.pillars
    gen = torch.Generator().manual_seed(seed)
    counts = torch.randint(1, pc.max_points_per_pillar + 1, (num_pillars,), generator=gen)
    mask = (torch.arange(pc.max_points_per_pillar)[None] < counts[:, None]).float()
    feats = torch.randn(num_pillars, pc.max_points_per_pillar, 11, generator=gen) * mask[..., None]
    index = torch.randperm(q * g.quadrant_ny * g.quadrant_nx, generator=gen)[:num_pillars].sort().values
    bev = torch.randn(q, preset.channels, g.quadrant_ny, g.quadrant_nx, generator=gen) * 0.05
    return feats, mask, index, bev


@pytest.mark.parametrize("seed", range(2))
def test_export_form_folds_the_image_bev_norm(seed):
    preset = dataclasses.replace(TINY, image_bev_norm=True)
    torch.manual_seed(seed)
    net = SliceNet(preset)
    with torch.no_grad():
        net.image_bev_norm.running_ms.uniform_(0.001, 0.01)
        net.image_bev_norm.weight.uniform_(0.5, 2.0)
    net.eval()
    args = _inputs(preset, 2, 30, seed)
    with torch.no_grad():
        for got, ref in zip(ExportSliceNet(net)(*args), net(*args)):
            torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-5)


def test_exported_graph_with_image_bev_norm_matches_torch():
    preset = dataclasses.replace(TINY, image_bev_norm=True)
    torch.manual_seed(3)
    det = StreamDetector(preset).eval()
    with torch.no_grad():
        det.slice_net.image_bev_norm.running_ms.fill_(0.004)
    args = _inputs(preset, 2, 60, 4)
    model = export_slice_head(det, args)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {name: t.numpy() for name, t in zip(SLICE_HEAD_IO.inputs, args)})
    with torch.no_grad():
        ref = SliceDecoder(det.slice_net, preset).eval()(*args)
    np.testing.assert_allclose(got[1], ref[1].numpy(), rtol=1e-4, atol=1e-5)


def test_image_encoder_with_group_norm_is_batch_independent():
    cfg = dataclasses.replace(TINY.image, norm="group")
    enc = ImageEncoder(cfg, TINY.channels).train()
    images = torch.randint(0, 255, (3, 24, 40, 3), dtype=torch.uint8)
    with torch.no_grad():
        torch.testing.assert_close(enc(images[1:2]), enc(images)[1:2], rtol=1e-4, atol=1e-5)


def test_small_v2_is_small_with_the_options_on():
    v2, small = get_preset("small_v2"), get_preset("small")
    assert v2.image.norm == "frozen_batch" and v2.image_bev_norm and v2.lifter.lut_heights_per_voxel == 2
    assert dataclasses.replace(v2, name="small", image=small.image, lifter=small.lifter, image_bev_norm=False) == small
    assert Preset.from_dict(json.loads(json.dumps(v2.to_dict()))) == v2


def test_cross_process_conversion_keeps_frozen_batch_norm():
    from streamdet.training.distributed import CrossProcessBatchNorm, convert_batchnorm

    net = torch.nn.Sequential(FrozenBatchNorm2d(4), torch.nn.BatchNorm2d(4))
    convert_batchnorm(net)
    assert type(net[0]) is FrozenBatchNorm2d and isinstance(net[1], CrossProcessBatchNorm)


def _naive_point_match(x, point, eps):
    """Reference of ImageBevNorm(target='point') in training, by loops over channels and cells."""
    q, c, h, w = x.shape
    cells = [(i, yy, xx) for i in range(q) for yy in range(h) for xx in range(w) if float(point[i, :, yy, xx].abs().sum()) > 0]
    point_ms = sum(float(point[i, k, yy, xx]) ** 2 for i, yy, xx in cells for k in range(c)) / (len(cells) * c)
    out = torch.empty_like(x)
    for k in range(c):
        ms = sum(float(x[i, k, yy, xx]) ** 2 for i, yy, xx in cells) / len(cells)
        out[:, k] = x[:, k] * (point_ms ** 0.5 / (ms + eps) ** 0.5)
    return out, point_ms


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_image_bev_matched_to_the_point_bev_on_occupied_cells(seed, dtype):
    gen = torch.Generator().manual_seed(seed)
    norm = ImageBevNorm(3, target="point", momentum=1.0).to(dtype)
    x = (torch.randn(2, 3, 4, 5, generator=gen) * torch.tensor([0.01, 1.0, 30.0]).view(1, -1, 1, 1)).to(dtype)
    point = torch.randn(2, 3, 4, 5, generator=gen).to(dtype) * 2.5
    point[:, :, :2] = 0  # half of the cells hold no points
    y = norm.train()(x, point)
    ref, point_ms = _naive_point_match(x, point, norm.eps)
    torch.testing.assert_close(y, ref, rtol=1e-4, atol=1e-6)
    occupied = point.abs().sum(dim=1) > 0  # (Q, Y, X)
    img_rms = y.permute(1, 0, 2, 3)[:, occupied].square().mean().sqrt()
    pt_rms = point.permute(1, 0, 2, 3)[:, occupied].square().mean().sqrt()
    assert abs(float(img_rms / pt_rms) - 1.0) < 1e-2  # one scale where both exist (eps bends the faintest channel)
    torch.testing.assert_close(norm.point_ms, torch.tensor(point_ms, dtype=dtype), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(norm.eval()(x), y, rtol=1e-4, atol=1e-6)  # momentum 1: eval = this batch's scale


def test_image_bev_point_target_keeps_its_statistics_without_points_and_needs_them():
    norm = ImageBevNorm(2, target="point").train()
    before = (norm.running_ms.clone(), norm.point_ms.clone())
    x = torch.randn(1, 2, 3, 3)
    y = norm(x, torch.zeros(1, 2, 3, 3))  # an empty slice: nothing to match
    torch.testing.assert_close(y, x * norm.scale().view(1, -1, 1, 1))
    assert torch.equal(norm.running_ms, before[0]) and torch.equal(norm.point_ms, before[1])
    with pytest.raises(ValueError, match="point BEV"):
        norm(x)
    with pytest.raises(ValueError, match="learnt"):
        ImageBevNorm(2, target="cells")
    assert not any(True for _ in norm.parameters())  # no learnt gain to shrink


def test_small_v3_exports_with_the_point_target_folded():
    preset = dataclasses.replace(TINY, image_bev_norm=True, image_bev_target="point")
    assert Preset.from_dict(json.loads(json.dumps(preset.to_dict()))) == preset
    assert "image_bev_target" not in dataclasses.replace(preset, image_bev_target="learnt").to_dict()
    torch.manual_seed(5)
    net = SliceNet(preset)
    with torch.no_grad():
        net.image_bev_norm.running_ms.uniform_(0.001, 0.01)
        net.image_bev_norm.point_ms.fill_(3.0)
    net.eval()
    args = _inputs(preset, 2, 30, 5)
    with torch.no_grad():
        for got, ref in zip(ExportSliceNet(net)(*args), net(*args)):
            torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-5)
    v3 = get_preset("small_v3")
    assert dataclasses.replace(v3, name="small_v2", image_bev_target="learnt") == get_preset("small_v2")
    with pytest.raises(ValueError, match="image_bev_target"):
        dataclasses.replace(TINY, image_bev_target="cells")
