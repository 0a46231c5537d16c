"""ResNet backbones (torchvision key names and sizes), weight loading, FPN and the image encoder."""

from __future__ import annotations

import math

import pytest
import torch

from streamdet.models.fpn import FPN
from streamdet.models.image_encoder import IMAGENET_MEAN, IMAGENET_STD, ImageEncoder
from streamdet.models.presets import ImageConfig
from streamdet.models.resnet import ResNet, load_backbone_weights

BN_SUFFIXES = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def torchvision_keys(depth: int) -> list[str]:
    """torchvision.models.resnet{18,50}().state_dict() keys without fc, derived from its structure:
    stem conv1/bn1; layers of [2,2,2,2] BasicBlocks (conv1..2) or [3,4,6,3] Bottlenecks (conv1..3); block 0 of a
    layer has downsample.0 (conv) / downsample.1 (bn) when its stride or width changes (not layer1 of ResNet-18)."""
    counts, convs = {18: ((2, 2, 2, 2), 2), 50: ((3, 4, 6, 3), 3)}[depth]

    def bn(prefix: str) -> list[str]:
        return [f"{prefix}.{s}" for s in BN_SUFFIXES]

    keys = ["conv1.weight", *bn("bn1")]
    for li, n in enumerate(counts, start=1):
        for b in range(n):
            p = f"layer{li}.{b}"
            for c in range(1, convs + 1):
                keys += [f"{p}.conv{c}.weight", *bn(f"{p}.bn{c}")]
            if b == 0 and (li > 1 or depth == 50):
                keys += [f"{p}.downsample.0.weight", *bn(f"{p}.downsample.1")]
    return keys


@pytest.mark.parametrize("depth, num_keys, num_params", [(18, 120, 11_176_512), (50, 318, 23_508_032)])
def test_state_dict_matches_torchvision(depth, num_keys, num_params):
    with torch.device("meta"):
        model = ResNet(depth)
    keys = list(model.state_dict())
    assert keys == torchvision_keys(depth)
    # torchvision: 122 / 320 keys and 11,689,512 / 25,557,032 parameters including fc (512 or 2048 -> 1000)
    assert len(keys) == num_keys
    assert sum(p.numel() for p in model.parameters()) == num_params


def test_resnet50_shapes_match_torchvision():
    with torch.device("meta"):
        sd = ResNet(50).state_dict()
    assert sd["conv1.weight"].shape == (64, 3, 7, 7)
    assert sd["layer1.0.conv1.weight"].shape == (64, 64, 1, 1)
    assert sd["layer1.0.downsample.0.weight"].shape == (256, 64, 1, 1)
    assert sd["layer2.0.conv2.weight"].shape == (128, 128, 3, 3)  # v1.5: stride on the 3x3 conv
    assert sd["layer4.2.conv3.weight"].shape == (2048, 512, 1, 1)


@pytest.mark.parametrize("depth", [18, 50])
@pytest.mark.parametrize("hw", [(72, 128), (45, 81), (900, 1600)])
def test_feature_strides_round_up(depth, hw):
    h, w = hw
    with torch.device("meta"):
        feats = ResNet(depth)(torch.empty(1, 3, h, w))
    expansion = 1 if depth == 18 else 4
    for i, f in enumerate(feats):
        s = 4 * 2**i
        assert f.shape == (1, 64 * 2**i * expansion, math.ceil(h / s), math.ceil(w / s))


def test_bad_depth_and_divisor():
    with pytest.raises(ValueError, match="depth must be one of \\[18, 50\\], got 34"):
        ResNet(34)
    with pytest.raises(ValueError, match="width_divisor must divide 64, got 5"):
        ResNet(18, width_divisor=5)


def _assert_same_weights(a: torch.nn.Module, b: torch.nn.Module) -> None:
    sb = b.state_dict()
    for k, v in a.state_dict().items():
        assert torch.equal(v, sb[k]), k


@pytest.mark.parametrize("depth", [18, 50])
def test_load_torchvision_style_file(tmp_path, depth):
    torch.manual_seed(0)
    src = ResNet(depth, width_divisor=16)
    sd = dict(src.state_dict())
    sd["fc.weight"] = torch.zeros(1000, src.out_channels[-1])  # torchvision files carry the classifier
    sd["fc.bias"] = torch.zeros(1000)
    for k in [k for k in sd if k.endswith("num_batches_tracked")]:
        del sd[k]  # old torchvision files predate it
    torch.save(sd, tmp_path / "tv.pth")
    dst = ResNet(depth, width_divisor=16)
    report = load_backbone_weights(dst, tmp_path / "tv.pth")
    assert report.missing == () and report.unexpected == ()
    assert report.loaded == len(sd) - 2
    for k, v in src.state_dict().items():
        if not k.endswith("num_batches_tracked"):
            assert torch.equal(v, dst.state_dict()[k]), k


def test_load_mmdet_style_file(tmp_path):
    torch.manual_seed(1)
    src = ResNet(18, width_divisor=16)
    sd = {f"backbone.{k}": v for k, v in src.state_dict().items()}
    sd["neck.lateral_convs.0.conv.weight"] = torch.zeros(4, 4, 1, 1)  # other mmdet modules are ignored
    torch.save({"meta": {"epoch": 20}, "state_dict": sd}, tmp_path / "htc.pth")
    dst = ResNet(18, width_divisor=16)
    load_backbone_weights(dst, tmp_path / "htc.pth")
    _assert_same_weights(src, dst)


def test_load_reports_missing_and_unexpected(tmp_path):
    src = ResNet(18, width_divisor=16)
    sd = dict(src.state_dict())
    del sd["layer3.1.conv2.weight"]
    sd["layer5.0.conv1.weight"] = torch.zeros(1)
    torch.save(sd, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match=r"1 missing keys \['layer3.1.conv2.weight'\], 1 unexpected keys \['layer5.0.conv1.weight'\]"):
        load_backbone_weights(ResNet(18, width_divisor=16), tmp_path / "bad.pth")
    report = load_backbone_weights(ResNet(18, width_divisor=16), tmp_path / "bad.pth", strict=False)
    assert report.missing == ("layer3.1.conv2.weight",) and report.unexpected == ("layer5.0.conv1.weight",)


def test_load_rejects_wrong_shapes_and_missing_file(tmp_path):
    torch.save(ResNet(18, width_divisor=16).state_dict(), tmp_path / "narrow.pth")
    with pytest.raises(ValueError, match=r"do not fit ResNet-18 .*conv1.weight: checkpoint \(4, 3, 7, 7\) vs model \(8, 3, 7, 7\)"):
        load_backbone_weights(ResNet(18, width_divisor=8), tmp_path / "narrow.pth")
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        load_backbone_weights(ResNet(18), tmp_path / "nope.pth")
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(ValueError, match="expected a state dict"):
        load_backbone_weights(ResNet(18, width_divisor=16), tmp_path / "list.pth")


def naive_fpn(fpn: FPN, feats: list[torch.Tensor]) -> torch.Tensor:
    """Reference: nearest upsampling written as index arithmetic, src = floor(dst * in / out)."""
    top = fpn.lateral[-1](feats[-1])
    for i in range(len(feats) - 2, -1, -1):
        lat = fpn.lateral[i](feats[i])
        h, w = lat.shape[-2:]
        rows = torch.arange(h) * top.shape[-2] // h
        cols = torch.arange(w) * top.shape[-1] // w
        top = lat + top[:, :, rows][:, :, :, cols]
    return fpn.output(top)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("hw", [(72, 128), (45, 81)])
def test_fpn_matches_reference_at_odd_sizes(seed, hw):
    torch.manual_seed(seed)
    backbone = ResNet(18, width_divisor=8)
    fpn = FPN(backbone.out_channels, 8)
    with torch.no_grad():
        feats = backbone(torch.randn(2, 3, *hw))
        out = fpn(feats)
        ref = naive_fpn(fpn, feats)
    assert out.shape == (2, 8, math.ceil(hw[0] / 4), math.ceil(hw[1] / 4))
    torch.testing.assert_close(out, ref)


@pytest.mark.parametrize("seed", [0, 1])
def test_image_encoder_normalises_inside(seed):
    torch.manual_seed(seed)
    enc = ImageEncoder(ImageConfig(width_px=128, height_px=72, backbone_depth=18, width_divisor=8), 8).eval()
    images = torch.randint(0, 256, (3, 70, 130, 3), dtype=torch.uint8)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    x = (images.permute(0, 3, 1, 2).double() / 255.0 - mean) / std
    with torch.no_grad():
        out = enc(images)
        ref = enc.neck(enc.backbone(x.float()))
    assert out.shape == (3, 8, 18, 33) and out.dtype == torch.float32
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)


def test_image_encoder_empty_batch():
    enc = ImageEncoder(ImageConfig(width_px=128, height_px=72, backbone_depth=18, width_divisor=8), 8).eval()
    with torch.no_grad():
        out = enc(torch.zeros(0, 72, 128, 3, dtype=torch.uint8))
    assert out.shape == (0, 8, 18, 32)
