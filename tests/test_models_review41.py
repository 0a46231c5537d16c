"""Review 41, area models: a training step under autocast with the flat lifter and the image BEV scale (F1), the
presets docstring on the bundled small_v3_swift (F2), zero pillars in training (F3), the peak test on the logits
(F4), the config constructors as strict as ``Preset.from_dict`` (F5) and ``export_slice_net`` leaving the caller's
net alone (F6)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from streamdet.calibration.grid import GridSpec
from streamdet.models import presets as presets_module
from streamdet.models.decode import pick_peaks
from streamdet.models.detector import SliceNet, StreamDetector
from streamdet.models.flat_lifter import gather_z_major_bag
from streamdet.models.image_bev_norm import ImageBevNorm
from streamdet.models.lifter import gather_z_major
from streamdet.models.pillars import PillarFeatureNet
from streamdet.models.presets import (
    BevEncoderConfig,
    HeadConfig,
    ImageConfig,
    LifterConfig,
    PillarConfig,
    PostConfig,
    Preset,
    get_preset,
    preset_names,
)
from streamdet.models.slice_split import export_slice_net

TINY = get_preset("tiny")
WEIGHTS = Path(presets_module.__file__).parent / "weights"


# ---- F1: autocast -----------------------------------------------------------------------------------------------


def _tiny(form: str = "flat", residual: str = "conv", norm: bool = False, target: str = "learnt") -> Preset:
    lifter = LifterConfig(form=form, residual=residual, lut_heights_per_voxel=2 if form == "flat" else 1)
    return dataclasses.replace(TINY, lifter=lifter, image_bev_norm=norm, image_bev_target=target)


def _detector_inputs(p: Preset, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    j, hf, wf = 2, p.image.feature_height, p.image.feature_width
    yq, xq = p.map_cells
    q, k, z = 1, 2, p.grid.nz
    index = torch.randint(0, j * hf * wf + 1, (q, k, z, yq, xq), dtype=torch.int32, generator=gen)
    weight = torch.rand((q, k, z, yq, xq), generator=gen)
    images = torch.randint(0, 255, (j, p.image.height_px, p.image.width_px, 3), dtype=torch.uint8, generator=gen)
    num_pillars, m = 20, p.pillars.max_points_per_pillar
    feats = torch.randn(num_pillars, m, 11, generator=gen)
    mask = torch.ones(num_pillars, m)
    pillar_index = torch.randperm(yq * xq, generator=gen)[:num_pillars]
    return images, index, weight, feats, mask, pillar_index


BF16, FP16 = torch.bfloat16, torch.float16


@pytest.mark.parametrize(
    "preset, dtype",
    [
        (_tiny("flat", residual="separable"), BF16),  # small_v3_swift's lifter
        (_tiny("flat", norm=True, target="learnt"), BF16),  # small_v2's options
        (_tiny("flat", norm=True, target="point"), BF16),  # small_v3's options (the shipped model)
        (_tiny("flat", norm=True, target="point"), FP16),  # --amp auto on CUDA is float16
        (_tiny("volume", norm=True, target="learnt"), BF16),
    ],
    ids=["flat-separable-bf16", "flat-norm-learnt-bf16", "flat-norm-point-bf16", "flat-norm-point-fp16", "volume-norm-learnt-bf16"],
)
def test_training_step_under_cpu_autocast(preset, dtype):
    torch.manual_seed(0)
    det = StreamDetector(preset).train()
    with torch.autocast("cpu", dtype=dtype):
        maps = det(*_detector_inputs(preset))
        loss = sum(m.float().square().mean() for m in maps)
    loss.backward()
    assert torch.isfinite(loss)
    grads = [p.grad for p in det.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    norm = det.slice_net.image_bev_norm
    if norm is not None:  # its statistics stay float32 buffers, updated
        assert norm.running_ms.dtype == torch.float32 and not torch.equal(norm.running_ms, torch.ones_like(norm.running_ms))


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_bag_gather_of_a_low_precision_table_matches_the_float32_gather(dtype):
    gen = torch.Generator().manual_seed(1)
    features = torch.randn(2, 4, 3, 5, generator=gen)  # (J, C, Hf, Wf)
    rows = 2 * 3 * 5
    index = torch.randint(0, rows + 1, (1, 2, 3, 4, 4), dtype=torch.int32, generator=gen)  # sentinel = rows
    weight = torch.rand((1, 2, 3, 4, 4), generator=gen)  # float32, as the LUT's
    got = gather_z_major_bag(features.to(dtype), index, weight)
    assert got.dtype == dtype
    ref = gather_z_major(features, index, weight)
    torch.testing.assert_close(got.float(), ref, atol=0.05, rtol=0.02)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("target", ["learnt", "point"])
def test_image_bev_norm_keeps_float32_statistics_for_a_low_precision_input(dtype, target):
    norm = ImageBevNorm(4, target=target, momentum=0.5).train()
    x = (torch.randn(2, 4, 3, 3) * 3).to(dtype)
    point = torch.randn(2, 4, 3, 3).to(dtype)
    out = norm(x, point)
    assert norm.running_ms.dtype == torch.float32 and torch.isfinite(out).all()
    assert not torch.equal(norm.running_ms, torch.ones(4))
    if target == "point":
        assert norm.point_ms.dtype == torch.float32 and float(norm.point_ms) != 1.0


# ---- F2: the docstring on small_v3_swift ----------------------------------------------------------------------


def test_presets_docstring_says_small_v3_swift_is_bundled():
    doc = presets_module.__doc__
    swift = doc[doc.index("- ``small_v3_swift``"):].split("\n\n")[0]
    assert "Not bundled" not in swift and "models/weights/small_v3_swift.pt" in swift
    assert (WEIGHTS / "small_v3_swift.pt").is_file()


# ---- F3: zero pillars in training -----------------------------------------------------------------------------


def test_pillar_net_in_training_takes_zero_pillars():
    net = PillarFeatureNet(11, 8).train()
    before = net.norm.running_mean.clone(), net.norm.running_var.clone(), int(net.norm.num_batches_tracked)
    out = net(torch.zeros(0, 5, 11), torch.zeros(0, 5))
    assert out.shape == (0, 8)
    after = net.norm.running_mean, net.norm.running_var, int(net.norm.num_batches_tracked)
    assert torch.equal(before[0], after[0]) and torch.equal(before[1], after[1]) and before[2] == after[2]


@pytest.mark.parametrize("p", [TINY, _tiny("flat", norm=True, target="point")], ids=["tiny", "tiny-norm-point"])
def test_slice_net_in_training_takes_zero_pillars(p):
    m = p.pillars.max_points_per_pillar
    yq, xq = p.map_cells
    net = SliceNet(p).train()
    image_bev = torch.randn(1, p.channels, yq, xq, requires_grad=True)
    maps = net(torch.zeros(0, m, 11), torch.zeros(0, m), torch.zeros(0, dtype=torch.int64), image_bev)
    assert all(torch.isfinite(t).all() for t in maps)
    sum(t.sum() for t in maps).backward()
    assert image_bev.grad is not None


# ---- F4: peaks on the logits ----------------------------------------------------------------------------------


def _sigmoid_first_peaks(heatmap: torch.Tensor) -> torch.Tensor:
    """The former peak test (on the sigmoid), for the cases where the two agree: (Q, C, Hh, Wh) scores."""
    heat = heatmap.sigmoid()
    return heat * (F.max_pool2d(heat, 3, 1, 1) == heat).to(heat.dtype)


@pytest.mark.parametrize("neighbour", [17.0, 19.9, 30.0])
def test_a_saturated_neighbour_is_no_peak(neighbour):
    h = torch.full((1, 10, 5, 5), -10.0)
    h[0, 0, 2, 2] = max(20.0, neighbour + 0.5)  # the object's centre
    h[0, 0, 2, 3] = neighbour  # a neighbour below it, whose sigmoid rounds to 1.0 as the centre's does
    assert float(torch.sigmoid(h[0, 0, 2, 3])) == 1.0
    scores, labels, _, rows, cols = pick_peaks(h, 3)
    assert (int(rows[0, 0]), int(cols[0, 0]), int(labels[0, 0])) == (2, 2, 0) and float(scores[0, 0]) == 1.0
    assert float(scores[0, 1]) < 1e-3  # the next is a background cell, not the neighbour
    assert not ((rows[0] == 2) & (cols[0] == 3)).any()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_peaks_on_logits_equal_the_sigmoid_ones_below_saturation(dtype):
    gen = torch.Generator().manual_seed(3)
    h = (torch.randn(2, 10, 6, 7, generator=gen) * 3).to(dtype)
    if dtype == torch.float32:  # in low precision the sigmoid flattens ties the logits do not have
        k = 10 * 6 * 7
        scores, labels, cell, _, _ = pick_peaks(h, k)
        dense = torch.zeros(2, 10 * 6 * 7, dtype=dtype).scatter(1, labels * 42 + cell, scores).view(2, 10, 6, 7)
        torch.testing.assert_close(dense, _sigmoid_first_peaks(h), rtol=0, atol=0)
    scores, *_ = pick_peaks(h, 20)
    assert scores.dtype == dtype and torch.isfinite(scores).all()


def test_pick_peaks_traces_to_onnx_with_the_peak_test_before_the_sigmoid(tmp_path):
    onnx = pytest.importorskip("onnx")

    class Peaks(torch.nn.Module):
        def forward(self, heatmap):
            scores, labels, cell, row, col = pick_peaks(heatmap, 5)
            return scores, labels

    path = tmp_path / "peaks.onnx"
    torch.onnx.export(Peaks(), (torch.randn(1, 10, 4, 4),), str(path), dynamo=False, input_names=["heatmap"])
    nodes = onnx.load(str(path)).graph.node
    ops = [n.op_type for n in nodes]
    assert {"MaxPool", "Equal", "Sigmoid", "TopK"} <= set(ops)
    pool = next(n for n in nodes if n.op_type == "MaxPool")
    sigmoid = next(n for n in nodes if n.op_type == "Sigmoid")
    assert pool.input[0] == sigmoid.input[0] == "heatmap"  # both read the logits


# ---- F5: constructors as strict as from_dict -------------------------------------------------------------------


def _bev(**kwargs) -> BevEncoderConfig:
    base = dict(layer_nums=(1,), layer_strides=(1,), num_filters=(8,), upsample_strides=(1.0,), num_upsample_filters=(8,))
    return BevEncoderConfig(**{**base, **kwargs})


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: HeadConfig(heatmap_bias_init=math.inf), r"HeadConfig.heatmap_bias_init must be a finite number, got float inf"),
        (lambda: HeadConfig(heatmap_bias_init=math.nan), r"heatmap_bias_init must be a finite number, got float nan"),
        (lambda: HeadConfig(heatmap_bias_init="x"), r"heatmap_bias_init must be a finite number, got str 'x'"),
        (lambda: HeadConfig(heatmap_bias_init=True), r"heatmap_bias_init must be a finite number, got bool True"),
        (lambda: HeadConfig(multi_head="yes"), r"HeadConfig.multi_head must be True or False, got str 'yes'"),
        (lambda: HeadConfig(tasks=[list(t) for t in HeadConfig().tasks]), r"HeadConfig.tasks must be a tuple, got list"),
        (lambda: HeadConfig(head_channels=8.0), r"HeadConfig.head_channels must be an integer, got float 8.0"),
        (lambda: Preset(name="x", use_image="no"), r"Preset.use_image must be True or False, got str 'no'"),
        (lambda: Preset(name="x", use_image=1), r"Preset.use_image must be True or False, got int 1"),
        (lambda: Preset(name="x", image_bev_norm="no"), r"Preset.image_bev_norm must be True or False, got str 'no'"),
        (lambda: Preset(name="x", slice_crop=None), r"Preset.slice_crop must be True or False, got NoneType None"),
        (lambda: Preset(name=5), r"Preset.name must be a string, got int 5"),
        (lambda: Preset(name="x", image_bev_target=0), r"Preset.image_bev_target must be a string, got int 0"),
        (lambda: Preset(name="x", channels=8.0), r"Preset.channels must be an integer, got float 8.0"),
        (lambda: Preset(name="x", head={"head_channels": 8}), r"Preset.head must be a HeadConfig, got dict"),
        (lambda: Preset(name="x", grid={"voxel_xy_m": 0.4}), r"Preset.grid must be a GridSpec, got dict"),
        (lambda: _bev(layer_nums=(1.5,)), r"BevEncoderConfig.layer_nums\[0\] must be an integer, got float 1.5"),
        (lambda: _bev(layer_nums=[1]), r"BevEncoderConfig.layer_nums must be a tuple, got list \[1\]"),
        (lambda: _bev(num_filters=(8.0,)), r"BevEncoderConfig.num_filters\[0\] must be an integer, got float 8.0"),
        (lambda: _bev(upsample_strides=(math.nan,)), r"upsample_strides\[0\] must be a finite number, got float nan"),
        (lambda: ImageConfig(backbone_depth=18.0), r"ImageConfig.backbone_depth must be an integer, got float 18.0"),
        (lambda: ImageConfig(feature_stride=4.0), r"ImageConfig.feature_stride must be an integer, got float 4.0"),
        (lambda: ImageConfig(norm=None), r"ImageConfig.norm must be a string, got NoneType None"),
        (lambda: PillarConfig(max_pillars=True), r"PillarConfig.max_pillars must be an integer, got bool True"),
        (lambda: LifterConfig(z_conv_stride=True), r"LifterConfig.z_conv_stride must be an integer, got bool True"),
        (lambda: LifterConfig(lut_heights_per_voxel=2**70), r"lut_heights_per_voxel must be an integer below 2\*\*63"),
        (lambda: PostConfig(score_threshold="0.1"), r"PostConfig.score_threshold must be a finite number, got str '0.1'"),
        (lambda: PostConfig(nms_iou_threshold=[0.2] * 10), r"PostConfig.nms_iou_threshold must be a tuple, got list"),
        (lambda: PostConfig(nms_iou_threshold=(0.2,) * 9 + ("0.2",)), r"nms_iou_threshold\[9\] must be a finite number, got str"),
        (lambda: PostConfig(top_k=500.0), r"PostConfig.top_k must be an integer, got float 500.0"),
    ],
)
def test_constructors_refuse_what_from_dict_refuses(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "field, sub, value",
    [
        ("heatmap_bias_init", "head", math.inf),
        ("multi_head", "head", "yes"),
        ("score_threshold", "post", "0.1"),
        ("backbone_depth", "image", 18.0),
        ("layer_nums", "bev", [1.5, 1, 1]),
        ("use_image", None, "no"),
        ("image_bev_norm", None, 1),
    ],
)
def test_what_from_dict_refuses_the_constructor_refuses_too(field, sub, value):
    d = get_preset("small").to_dict()
    (d[sub] if sub else d)[field] = value
    with pytest.raises(ValueError, match=f"{field}"):
        Preset.from_dict(d)
    base = get_preset("small")
    with pytest.raises(ValueError, match=field):
        if sub is None:
            dataclasses.replace(base, **{field: value})
        else:
            dataclasses.replace(base, **{sub: dataclasses.replace(getattr(base, sub), **{field: value})})


@pytest.mark.parametrize("name", preset_names())
def test_every_preset_constructs_hashes_and_round_trips(name):
    p = get_preset(name)
    hash(p)
    assert Preset.from_dict(json.loads(json.dumps(p.to_dict()))) == p


def test_a_float_field_still_takes_an_int_and_a_grid_its_own_class():
    assert HeadConfig(heatmap_bias_init=-2).heatmap_bias_init == -2
    assert PostConfig(score_threshold=0).score_threshold == 0
    assert Preset(name="x", grid=GridSpec()).grid == GridSpec()


# ---- F6: export_slice_net copies ------------------------------------------------------------------------------


def test_export_slice_net_leaves_a_training_net_training():
    net = SliceNet(TINY).train()
    rewritten = export_slice_net(net)
    assert net.training and all(m.training for m in net.modules())
    assert not rewritten.training and not any(m.training for m in rewritten.modules())
    # a copy: training the net further does not change the rewritten one
    assert rewritten.pillar_net is not net.pillar_net and rewritten.head is not net.head
    with torch.no_grad():
        net.head.shared[0].weight.add_(1.0)
    assert not torch.equal(rewritten.head.shared[0].weight, net.head.shared[0].weight)
