"""to_export_form: every export-time rewrite in one place, and the one BatchNorm fold they all use."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from streamdet.export.onnx_export import graph_ios
from streamdet.models.bn_fold import fold_bn
from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import build_detector
from streamdet.models.export_form import LidarSliceDecoder, to_export_form
from streamdet.models.lifter_fold import FoldedLifter
from streamdet.models.presets import get_preset
from streamdet.models.slice_split import ExportSliceNet

TINY = get_preset("tiny")


@pytest.mark.parametrize("use_image", [True, False])
def test_export_form_holds_one_module_per_graph(use_image):
    det = build_detector(dataclasses.replace(TINY, use_image=use_image))
    form = to_export_form(det)
    assert list(form.graphs()) == list(graph_ios(use_image))
    assert isinstance(form.slice_head.slice_net, ExportSliceNet)
    if use_image:
        assert isinstance(form.image_encoder, type(det.image_encoder)) and isinstance(form.volumetric_lifter, FoldedLifter)
        assert type(form.slice_head) is SliceDecoder
    else:
        assert form.image_encoder is None and form.volumetric_lifter is None
        assert isinstance(form.slice_head, LidarSliceDecoder)
    assert not any(m.training for m in form.graphs().values())


def _modes(module: torch.nn.Module) -> dict[str, bool]:
    return {name: m.training for name, m in module.named_modules()}


@pytest.mark.parametrize("image_layout", ["image_bev", "image_half"])
@pytest.mark.parametrize("use_image", [True, False])
@pytest.mark.parametrize("mode", ["train", "eval", "mixed"])
def test_export_form_leaves_the_detector_as_it_was(mode, use_image, image_layout):
    """The form is an eval-mode snapshot: the caller's modes are untouched (a periodic export in a training loop
    keeps its BatchNorm statistics updating), and the form shares no module or tensor with the detector."""
    det = build_detector(dataclasses.replace(TINY, use_image=use_image))
    det.train(mode != "eval")
    if mode == "mixed":
        det.slice_net.eval()
    before = _modes(det)
    state = {k: v.clone() for k, v in det.state_dict().items()}
    form = to_export_form(det, image_layout)
    assert _modes(det) == before
    assert not any(m.training for g in form.graphs().values() for m in g.modules())
    det_tensors = {t.data_ptr() for t in (*det.parameters(), *det.buffers())}
    assert not det_tensors & {t.data_ptr() for g in form.graphs().values() for t in (*g.parameters(), *g.buffers())}
    assert all(torch.equal(v, state[k]) for k, v in det.state_dict().items())  # no weight or statistic changed
    if use_image:  # a later step on the detector leaves the form as it was
        x = torch.randint(0, 255, (1, 32, 48, 3), dtype=torch.uint8)
        with torch.no_grad():
            want = form.image_encoder(x)
            for p in det.image_encoder.parameters():
                p.add_(1.0)
            torch.testing.assert_close(form.image_encoder(x), want)


def _bn(cls, channels: int, seed: int, dtype):
    gen = torch.Generator().manual_seed(seed)
    bn = cls(channels).eval().to(dtype)
    with torch.no_grad():
        bn.running_mean.copy_(torch.randn(channels, generator=gen, dtype=dtype))
        bn.running_var.copy_(torch.rand(channels, generator=gen, dtype=dtype) + 0.5)
        bn.weight.copy_(torch.rand(channels, generator=gen, dtype=dtype) + 0.5)
        bn.bias.copy_(torch.randn(channels, generator=gen, dtype=dtype))
    return bn


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("bias", [False, True])
def test_fold_bn_after_a_linear_map(seed, bias, dtype):
    torch.manual_seed(seed)
    linear = torch.nn.Linear(7, 5, bias=bias).to(dtype)
    bn = _bn(torch.nn.BatchNorm1d, 5, seed, dtype)
    weight, b = fold_bn(linear.weight, linear.bias, bn)
    x = torch.randn(9, 7, dtype=dtype)
    with torch.no_grad():
        torch.testing.assert_close(x @ weight.t() + b, bn(linear(x)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("planes", [1, 3])
def test_fold_bn_with_planes_scales_each_block_of_output_channels(planes, dtype):
    torch.manual_seed(planes)
    conv = torch.nn.Conv2d(4, 2 * planes, 3, padding=1, bias=False).to(dtype)
    bn = _bn(torch.nn.BatchNorm3d, 2, planes, dtype)
    weight, b = fold_bn(conv.weight, None, bn, planes=planes)
    x = torch.randn(1, 4, 6, 5, dtype=dtype)
    with torch.no_grad():
        got = torch.nn.functional.conv2d(x, weight, b, padding=1)
        ref = bn(conv(x).reshape(1, 2, planes, 6, 5)).reshape(1, 2 * planes, 6, 5)  # channel c * planes + z
    torch.testing.assert_close(got, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fold_bn_before_a_1x1_map(dtype):
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(3, 4, 1).to(dtype)
    bn = _bn(torch.nn.BatchNorm2d, 3, 0, dtype)
    weight, b = fold_bn(conv.weight, conv.bias, bn, bn_first=True)
    x = torch.randn(2, 3, 5, 5, dtype=dtype)
    with torch.no_grad():
        torch.testing.assert_close(torch.nn.functional.conv2d(x, weight, b), conv(bn(x)))


def test_fold_bn_refuses_what_it_cannot_fold():
    bn = _bn(torch.nn.BatchNorm2d, 3, 0, torch.float32)
    with pytest.raises(ValueError, match="only into a 1x1 map"):
        fold_bn(torch.zeros(4, 3, 3, 3), None, bn, bn_first=True)
    with pytest.raises(ValueError, match=r"has not 3 x 2 output channels"):
        fold_bn(torch.zeros(4, 3, 1, 1), None, bn, planes=2)
