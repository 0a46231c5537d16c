"""Presets: the paper's numbers, validation with clear errors, JSON round trip, torch-free import."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from streamdet.calibration.grid import GridSpec
from streamdet.core.classes import CLASS_NAMES
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


def test_preset_names():
    assert preset_names() == ("paper", "small", "tiny", "small_v2", "small_v3", "small_v3_lite", "small_v3_thin", "small_v3_swift")


def test_small_v3_lite_is_small_v3_with_a_lighter_image_encoder():
    import dataclasses

    v3, lite = get_preset("small_v3"), get_preset("small_v3_lite")
    assert (lite.image.width_px, lite.image.height_px, lite.image.width_divisor) == (320, 180, 4)
    assert (lite.image.feature_width, lite.image.feature_height) == (80, 45)
    assert dataclasses.replace(lite, name="small_v3", image=v3.image) == v3  # nothing else differs
    assert Preset.from_dict(lite.to_dict()) == lite


def test_small_v3_thin_is_small_v3_lite_with_a_thinner_slice_net():
    import dataclasses

    from streamdet.training.checkpoint import transferable_weights
    from streamdet.models.detector import build_detector

    lite, thin = get_preset("small_v3_lite"), get_preset("small_v3_thin")
    assert (thin.bev.num_filters, thin.bev.num_upsample_filters, thin.head.head_channels) == ((16, 32, 64), (16, 16, 16), 8)
    assert dataclasses.replace(thin, name="small_v3_lite", bev=lite.bev, head=lite.head) == lite  # nothing else differs
    assert Preset.from_dict(thin.to_dict()) == thin
    # a run can start from small_v3_lite's camera lane and pillar net (streamdet-train --init)
    _, parts = transferable_weights(thin, lite.to_dict(), build_detector(lite).state_dict())
    assert parts == ("image_encoder", "lifter", "slice_net.pillar_net")


def test_small_v3_swift_is_small_v3_thin_with_a_lighter_camera_lane():
    import dataclasses

    import torch

    from streamdet.models.detector import build_detector

    thin, swift = get_preset("small_v3_thin"), get_preset("small_v3_swift")
    assert (swift.image.width_px, swift.image.height_px) == (224, 126) and swift.lifter.residual == "separable"
    assert (swift.image.feature_width, swift.image.feature_height) == (56, 32)
    assert dataclasses.replace(swift, name="small_v3_thin", image=thin.image, lifter=thin.lifter) == thin  # nothing else
    assert Preset.from_dict(swift.to_dict()) == swift
    # every weight but the lifter's residual keeps its shape (docs/training/issue22/init_swift.py starts from thin's)
    a, b = build_detector(thin).state_dict(), build_detector(swift).state_dict()
    differ = {k for k in b if k not in a or a[k].shape != b[k].shape}
    assert differ and all(k.startswith("lifter.residual.") for k in differ)
    assert all(isinstance(v, torch.Tensor) for v in b.values())


def test_unknown_preset_lists_known_ones():
    with pytest.raises(ValueError, match=r"unknown preset 'huge'.*paper, small, tiny"):
        get_preset("huge")


def test_paper_numbers():
    p = get_preset("paper")
    g = p.grid
    assert (g.nx, g.ny, g.nz) == (512, 512, 16)
    assert (g.quadrant_nx, g.quadrant_ny) == (256, 256)
    assert g.x_range_m == (-51.2, 51.2) and g.z_range_m == (-3.0, 5.0)
    assert p.channels == 64
    assert (p.image.width_px, p.image.height_px, p.image.backbone_depth) == (1600, 900, 50)
    assert (p.image.feature_width, p.image.feature_height) == (400, 225)
    assert p.head.out_stride == 4 and not p.head.multi_head
    assert p.head_map_size == (64, 64)  # per quadrant; the full map is 128 x 128
    assert p.head_cell_m == pytest.approx(0.8)
    assert p.post.top_k == 500 and p.top_k == 500
    assert p.num_classes == len(CLASS_NAMES) == 10
    assert p.bev.layer_strides == (1, 2, 2) and p.bev.num_filters == (64, 128, 256)
    assert p.bev.out_channels == 384
    assert p.use_image


def test_small_and_tiny_sizes():
    s = get_preset("small")
    assert (s.grid.quadrant_nx, s.grid.quadrant_ny, s.grid.nz) == (128, 128, 4)
    assert s.head_cell_m == pytest.approx(0.8) and s.image.backbone_depth == 18
    assert (s.image.width_px, s.image.height_px) == (384, 216) and s.image.width_divisor == 2
    t = get_preset("tiny")
    assert (t.grid.nx, t.grid.nz, t.channels) == (64, 4, 8)
    assert t.top_k == 50


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
@pytest.mark.parametrize("use_image", [True, False])
@pytest.mark.parametrize("multi_head", [True, False])
def test_json_round_trip(name, use_image, multi_head):
    p = get_preset(name)
    p = dataclasses.replace(p, use_image=use_image, head=dataclasses.replace(p.head, multi_head=multi_head))
    d = json.loads(json.dumps(p.to_dict()))
    assert d == p.to_dict()
    assert Preset.from_dict(d) == p


def test_top_k_is_clamped_to_classes_times_cells():
    t = get_preset("tiny")
    big = dataclasses.replace(t, post=dataclasses.replace(t.post, top_k=10**6))
    hh, wh = big.head_map_size
    assert big.top_k == 10 * hh * wh


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ImageConfig(backbone_depth=34), r"backbone_depth must be 18 or 50, got 34"),
        (lambda: ImageConfig(width_px=0), r"ImageConfig.width_px must be a positive integer, got 0"),
        (lambda: ImageConfig(width_divisor=3), r"width_divisor must divide 64, got 3"),
        (lambda: PillarConfig(num_point_features=9), r"num_point_features must be 11"),
        (lambda: PillarConfig(max_pillars=-1), r"PillarConfig.max_pillars must be a positive integer, got -1"),
        (lambda: LifterConfig(z_pool=0), r"LifterConfig.z_pool"),
        (lambda: BevEncoderConfig(layer_strides=(1, 2)), r"BevEncoderConfig.layer_strides must have 3 entries"),
        (lambda: BevEncoderConfig(upsample_strides=(0.25, 0.0, 1.0)), r"upsample_strides must be > 0"),
        (lambda: HeadConfig(tasks=(("car",),)), r"HeadConfig.tasks must cover each of"),
        (lambda: HeadConfig(final_kernel=2), r"HeadConfig.final_kernel must be odd .*got 2"),
        (lambda: PostConfig(score_threshold=1.5), r"score_threshold must be in \[0, 1\), got 1.5"),
        (lambda: PostConfig(nms_iou_threshold=(0.2,)), r"nms_iou_threshold must hold 10 values"),
        (lambda: Preset(name="x", channels=0), r"Preset.channels must be a positive integer, got 0"),
        (
            lambda: Preset(name="x", bev=BevEncoderConfig(upsample_strides=(0.5, 0.5, 1.0))),
            r"bev.upsample_strides\[0\]=0.5 brings stride 1 to 2.0, not head.out_stride=4",
        ),
        (
            lambda: Preset(name="x", grid=GridSpec(voxel_z_m=4.0)),
            r"grid.nz=2 image voxels is not divisible by lifter z_conv_stride \* z_pool = 4",
        ),
    ],
)
def test_validation_errors_name_the_field(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_from_dict_malformed():
    d = get_preset("tiny").to_dict()
    del d["head"]
    with pytest.raises(ValueError, match="lacks the field 'head'"):
        Preset.from_dict(d)
    d = get_preset("tiny").to_dict()
    d["image"]["colour"] = "rgb"
    with pytest.raises(ValueError, match="malformed"):
        Preset.from_dict(d)


def test_presets_module_does_not_import_torch():
    code = "import sys, streamdet.models.presets; assert 'torch' not in sys.modules, 'torch was imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
