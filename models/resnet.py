"""ResNet-18 / ResNet-50 backbones returning C2..C5, with torchvision's state-dict key names.

The modules and attribute names follow torchvision's ``resnet.py`` (``conv1``, ``bn1``, ``layer1.0.conv1``,
``layer1.0.downsample.0`` ...) so that a torchvision or mmdetection checkpoint file on disk loads with
``load_backbone_weights``. There is no ``fc``: the detector only needs the feature maps. Nothing is downloaded;
construction gives a random (Kaiming) init and weight loading is a separate, explicit step.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from streamdet.models.norms import norm2d
from streamdet.models.torch_files import check_state_dict, read_torch_file


def conv3x3(in_ch: int, out_ch: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_ch, out_ch, kernel_size=3, stride=stride, padding=1, bias=False)


def conv1x1(in_ch: int, out_ch: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_ch, out_ch, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, in_ch: int, width: int, stride: int = 1, downsample: nn.Module | None = None,
                 norm: str = "batch") -> None:  # fmt: skip
        super().__init__()
        self.conv1 = conv3x3(in_ch, width, stride)
        self.bn1 = norm2d(norm, width)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = conv3x3(width, width)
        self.bn2 = norm2d(norm, width)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """torchvision's ResNet v1.5 bottleneck: the stride sits on the 3x3 conv."""

    expansion = 4

    def __init__(self, in_ch: int, width: int, stride: int = 1, downsample: nn.Module | None = None,
                 norm: str = "batch") -> None:  # fmt: skip
        super().__init__()
        self.conv1 = conv1x1(in_ch, width)
        self.bn1 = norm2d(norm, width)
        self.conv2 = conv3x3(width, width, stride)
        self.bn2 = norm2d(norm, width)
        self.conv3 = conv1x1(width, width * self.expansion)
        self.bn3 = norm2d(norm, width * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


_LAYOUTS: dict[int, tuple[type[BasicBlock] | type[Bottleneck], tuple[int, int, int, int]]] = {
    18: (BasicBlock, (2, 2, 2, 2)),
    50: (Bottleneck, (3, 4, 6, 3)),
}


class ResNet(nn.Module):
    """ResNet trunk. ``forward(x (B, 3, H, W)) -> [C2, C3, C4, C5]`` at strides 4, 8, 16, 32.

    ``width_divisor`` > 1 narrows every layer (base width 64 // divisor) for fast tests; such a model no longer
    matches pretrained checkpoints in shape, though its key names still do. ``norm`` is the normalisation of
    every ``bn*`` (``models.norms``: "batch", or "frozen_batch" / "group", which work at batch 1); the names stay.
    """

    def __init__(self, depth: int = 50, width_divisor: int = 1, norm: str = "batch") -> None:
        super().__init__()
        if depth not in _LAYOUTS:
            raise ValueError(f"ResNet depth must be one of {sorted(_LAYOUTS)}, got {depth!r}")
        if width_divisor < 1 or 64 % width_divisor:
            raise ValueError(f"ResNet width_divisor must divide 64, got {width_divisor!r}")
        block, counts = _LAYOUTS[depth]
        base = 64 // width_divisor
        self.depth = depth
        self.norm = norm
        self.inplanes = base
        self.conv1 = nn.Conv2d(3, base, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = norm2d(norm, base)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block, base, counts[0], stride=1)
        self.layer2 = self._make_layer(block, base * 2, counts[1], stride=2)
        self.layer3 = self._make_layer(block, base * 4, counts[2], stride=2)
        self.layer4 = self._make_layer(block, base * 8, counts[3], stride=2)
        self.out_channels: tuple[int, ...] = tuple(base * m * block.expansion for m in (1, 2, 4, 8))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _make_layer(
        self, block: type[BasicBlock] | type[Bottleneck], width: int, blocks: int, stride: int
    ) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != width * block.expansion:
            downsample = nn.Sequential(
                conv1x1(self.inplanes, width * block.expansion, stride), norm2d(self.norm, width * block.expansion)
            )
        layers = [block(self.inplanes, width, stride, downsample, self.norm)]
        self.inplanes = width * block.expansion
        layers += [block(self.inplanes, width, norm=self.norm) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def forward(self, x: Tensor) -> list[Tensor]:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        c2 = self.layer1(x)
        c3 = self.layer2(c2)
        c4 = self.layer3(c3)
        c5 = self.layer4(c4)
        return [c2, c3, c4, c5]


@dataclass(frozen=True)
class LoadReport:
    loaded: int  # number of tensors copied into the model
    missing: tuple[str, ...]  # model keys the checkpoint did not provide
    unexpected: tuple[str, ...]  # checkpoint keys the model has no place for (after prefix stripping, fc dropped)


def load_backbone_weights(model: ResNet, path: str | Path, strict: bool = True) -> LoadReport:
    """Copy a local torchvision or mmdetection ResNet checkpoint into ``model``.

    Accepts a plain state dict (torchvision), or a dict with a ``state_dict`` entry whose backbone keys carry a
    ``backbone.`` prefix (mmdetection, e.g. the HTC checkpoint the paper uses); other mmdet modules (neck, heads)
    are ignored. ``fc.*`` is dropped. With ``strict`` a missing or unexpected key raises ValueError naming them;
    a shape mismatch always raises.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"backbone checkpoint not found: {path}")
    # weights_only, the zip checked before anything is inflated; ValueError naming the file when unreadable
    ckpt = read_torch_file(path, "backbone checkpoint")
    if isinstance(ckpt, dict) and isinstance(ckpt.get("state_dict"), dict):
        ckpt = ckpt["state_dict"]
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path}: expected a state dict (or a dict with 'state_dict'), got {type(ckpt).__name__}")
    ckpt = check_state_dict(ckpt, path, "backbone checkpoint", "state_dict")  # str keys, tensor values
    state = {k.removeprefix("module."): v for k, v in ckpt.items()}
    if any(k.startswith("backbone.") for k in state):
        state = {k[len("backbone.") :]: v for k, v in state.items() if k.startswith("backbone.")}
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}

    own = model.state_dict()
    bad_shapes = [
        f"{k}: checkpoint {tuple(v.shape)} vs model {tuple(own[k].shape)}"
        for k, v in state.items()
        if k in own and tuple(v.shape) != tuple(own[k].shape)
    ]
    if bad_shapes:
        raise ValueError(
            f"{path}: {len(bad_shapes)} tensors do not fit ResNet-{model.depth} "
            f"(wrong depth or width_divisor?): {'; '.join(bad_shapes[:5])}"
        )
    for k, v in state.items():
        if k in own and own[k].is_floating_point() and not v.is_floating_point():
            raise ValueError(f"{path}: {k} holds {v.dtype} values where ResNet-{model.depth} has {own[k].dtype} weights")
        if k in own and v.is_floating_point() and v.numel() and not bool(torch.isfinite(v).all()):
            raise ValueError(f"{path}: {k} holds non-finite values (NaN or inf)")
    result = model.load_state_dict(state, strict=False)
    # Old torchvision files predate num_batches_tracked; BatchNorm fills it in, so it is not really missing.
    missing = tuple(k for k in result.missing_keys if not k.endswith("num_batches_tracked"))
    unexpected = tuple(result.unexpected_keys)
    report = LoadReport(loaded=sum(k in own for k in state), missing=missing, unexpected=unexpected)
    if strict and (missing or unexpected):
        raise ValueError(
            f"{path}: checkpoint does not match ResNet-{model.depth}: "
            f"{len(missing)} missing keys {list(missing[:8])}, {len(unexpected)} unexpected keys {list(unexpected[:8])}"
        )
    if report.loaded == 0:
        raise ValueError(f"{path}: no tensor of the checkpoint matches a ResNet key (first keys: {list(ckpt)[:5]})")
    return report
