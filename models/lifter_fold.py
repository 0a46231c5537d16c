"""The lifter's 3D convolutions rewritten as 2D convolutions over z folded into channels, for export.

A volume (Q, C, Z, Y, X) is, byte for byte, a 2D map (Q, C * Z, Y, X) with channel ``c * Z + z``. A Conv3d with a
k x k x k kernel, z-padding 1 and z-stride s is then one Conv2d from C * Z to C * Zo channels whose dense weight is
banded: output plane zo reads input plane zo * s - pad + t through kernel tap t, and zeros elsewhere. The result is
the same function (tests/test_models_lifter_fold.py checks it against Conv3d); it multiplies zeros on purpose.

Why: onnxruntime's CPU Conv3d runs im2col + GEMM with only C = 32 output rows, while Conv2d runs its blocked
(NCHWc) kernels. On the small preset's Z = 4 volume the rewrite computes more MACs (``folded_mac_ratio``) and still
runs faster, in fp32 and more so in int8 (measured: benchmarks/RESULTS.md, "Measurements behind design choices").
The zero taps grow with Z (a dense band reads all Z
planes where the kernel reads k of them), so ``fold_pays`` allows the rewrite only while the dense 2D convolutions
cost at most FOLD_MAX_MAC_RATIO times the 3D ones: Z = 4 (small, tiny presets) folds, the paper's Z = 16 does not.

Training never sees this module: it is built from a trained ``VolumetricLifter`` (BatchNorms folded into the
convolutions, eval statistics), exactly like onnxruntime's own Conv + BatchNormalization fusion.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from streamdet.models.bn_fold import fold_bn
from streamdet.models.flat_lifter import FlatLifter, FlatLifterConvs, FlatLifterExport
from streamdet.models.lifter import VolumetricLifter, gather_z_major, z_major
from streamdet.models.presets import LifterConfig

# Largest (dense 2D MACs) / (3D MACs) the rewrite may cost: Z = 4 (ratio 1.40) measured faster (benchmarks/RESULTS.md);
# the paper preset's Z = 16 would compute 4.2x the MACs.
FOLD_MAX_MAC_RATIO = 1.5


def folded_depth(z_in: int, kernel: int, stride: int, pad: int) -> int:
    """Output planes of a z-convolution: the usual (Z + 2 pad - k) // s + 1."""
    z_out = (z_in + 2 * pad - kernel) // stride + 1
    if z_out < 1:
        raise ValueError(f"a z-kernel of {kernel} with padding {pad} does not fit a volume of {z_in} planes")
    return z_out


def banded_weight(weight: Tensor, z_in: int, stride: int, pad: int) -> Tensor:
    """A Conv3d weight (Co, Ci, kz, ky, kx) as the Conv2d weight (Co * Zo, Ci * Z, ky, kx) over folded z.

    Channel ``c * Z + z`` in and ``o * Zo + zo`` out, as reshaping (Q, C, Z, Y, X) to (Q, C * Z, Y, X) numbers them.
    Taps that fall into the z-padding are dropped (they multiply zeros in the 3D convolution too).
    """
    if weight.dim() != 5:
        raise ValueError(f"expected a Conv3d weight (Co, Ci, kz, ky, kx), got shape {tuple(weight.shape)}")
    co, ci, kz, ky, kx = weight.shape
    z_out = folded_depth(z_in, kz, stride, pad)
    band = weight.new_zeros(co, z_out, ci, z_in, ky, kx)  # (Co, Zo, Ci, Z, ky, kx)
    for zo in range(z_out):
        for t in range(kz):
            zi = zo * stride - pad + t
            if 0 <= zi < z_in:
                band[:, zo, :, zi] = weight[:, :, t]
    return band.reshape(co * z_out, ci * z_in, ky, kx)  # (Co*Zo, Ci*Z, ky, kx): out co*Zo+zo, in ci*Z+z


def folded_mac_ratio(cfg: LifterConfig, nz: int) -> float:
    """MACs of the folded convolutions (1x1 projection, residual, z-strided) over those of the 3D ones.

    Per output (y, x) cell and per C x C channel pair: the 3D layers take nz (1x1x1), nz * 27 and Zd * 27 MACs,
    the dense 2D ones nz * nz, nz * nz * 9 and Zd * nz * 9.
    """
    z_down = folded_depth(nz, 3, cfg.z_conv_stride, 1)
    macs_3d = nz + nz * 27 + z_down * 27
    macs_2d = nz * nz + nz * nz * 9 + z_down * nz * 9
    return macs_2d / macs_3d


def fold_pays(cfg: LifterConfig, nz: int) -> bool:
    return folded_mac_ratio(cfg, nz) <= FOLD_MAX_MAC_RATIO


class FoldedLifterConvs(nn.Module):
    """``forward(volume (Q, C, Z, Y, X)) -> image_bev (Q, C, Y, X)``: ``VolumetricLifter.convs`` over folded z.

    Built with zero weights of ``dtype`` on ``device`` (default: torch's); ``load_from`` copies a trained lifter's
    (``from_lifter`` does both, in the lifter's dtype and on its device).
    """

    def __init__(self, cfg: LifterConfig, channels: int, nz: int, *, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> None:  # fmt: skip
        super().__init__()
        c = channels
        self.channels, self.nz = c, nz
        self.z_major = False  # input channel order: c * Z + z (False), z * C + c (True, see to_z_major)
        self.z_down_planes = folded_depth(nz, 3, cfg.z_conv_stride, 1)
        like = {"dtype": dtype, "device": device}
        # input BN folded into the 1x1x1 projection: block-diagonal over z
        self.project = nn.Conv2d(c * nz, c * nz, kernel_size=1, **like)
        self.residual = nn.Conv2d(c * nz, c * nz, kernel_size=3, padding=1, **like)  # BN folded in
        self.z_down = nn.Conv2d(c * nz, c * self.z_down_planes, kernel_size=3, padding=1, **like)  # BN folded in
        self.z_pool = nn.AvgPool3d(kernel_size=(cfg.z_pool, 1, 1), stride=(cfg.z_pool, 1, 1))
        self.relu = nn.ReLU(inplace=True)
        for conv in (self.project, self.residual, self.z_down):
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)
        self._z_stride = cfg.z_conv_stride

    @classmethod
    def from_lifter(cls, lifter: VolumetricLifter, cfg: LifterConfig, nz: int) -> FoldedLifterConvs:
        weight = lifter.project.weight  # the folded weights keep the source's precision (as slice_split.py's)
        folded = cls(cfg, lifter.project.out_channels, nz, dtype=weight.dtype, device=weight.device)
        folded.load_from(lifter)
        return folded.eval()

    @torch.no_grad()
    def load_from(self, lifter: VolumetricLifter) -> None:
        c, nz, zd = self.channels, self.nz, self.z_down_planes
        if lifter.project.out_channels != c:
            raise ValueError(f"lifter has {lifter.project.out_channels} channels, this module {c}")
        if lifter.z_down[0].stride[0] != self._z_stride:
            raise ValueError(f"lifter z-stride {lifter.z_down[0].stride[0]} != {self._z_stride}")
        # project(BN(v)) = W (s * v + t) + b = (W s) v + (W t + b), the same (C, C) block on every plane
        w, b = fold_bn(lifter.project.weight[:, :, 0, 0, 0], lifter.project.bias, lifter.input_norm, bn_first=True)
        block = torch.einsum("oc,zy->ozcy", w, torch.eye(nz, dtype=w.dtype, device=w.device))  # (C, Z, C, Z)
        self.project.weight.copy_(block.reshape(c * nz, c * nz, 1, 1))  # (C*Z, C*Z, 1, 1): out c*Z+z, in c*Z+z
        self.project.bias.copy_(b.repeat_interleave(nz))  # channel c * Z + z
        for conv2d, seq, planes in ((self.residual, lifter.residual, nz), (self.z_down, lifter.z_down, zd)):
            conv3d, bn = seq[0], seq[1]
            if conv3d.kernel_size != (3, 3, 3) or conv3d.padding != (1, 1, 1) or conv3d.stride[1:] != (1, 1):
                raise ValueError(f"only k3 / pad 1 / y-x stride 1 convolutions fold, got {conv3d}")
            band = banded_weight(conv3d.weight, nz, conv3d.stride[0], conv3d.padding[0])  # (C * Zo, C * Z, 3, 3)
            bias = None if conv3d.bias is None else conv3d.bias.repeat_interleave(planes)
            weight, bias = fold_bn(band, bias, bn, planes=planes)  # output channel o * Zo + zo
            conv2d.weight.copy_(weight)
            conv2d.bias.copy_(bias)

    def forward(self, volume: Tensor) -> Tensor:
        q, c, z, y, x = volume.shape
        if (c, z) != (self.channels, self.nz):
            raise ValueError(f"expected a volume of {self.channels} channels x {self.nz} planes, got shape {tuple(volume.shape)}")
        if self.z_major:
            return self.folded(z_major(volume))  # channel z * C + c
        return self.folded(volume.reshape(q, c * z, y, x))  # (Q, C*Z, Y, X): channel c * Z + z

    def folded(self, v: Tensor) -> Tensor:
        """(Q, C*Z, Y, X), channels in this module's order -> image_bev (Q, C, Y, X)."""
        q, _, y, x = v.shape
        v = self.relu(self.project(v))
        v = v + self.relu(self.residual(v))
        v = self.relu(self.z_down(v))  # (Q, C*Zd, Y, X): channel c * Zd + zd whatever the input order
        v = v.reshape(q, self.channels, self.z_down_planes, y, x)  # (Q, C, Zd, Y, X)
        return self.z_pool(v).amax(dim=2)  # (Q, C, Y, X)

    @torch.no_grad()
    def to_z_major(self) -> FoldedLifterConvs:
        """A copy that reads (and keeps until z_down) the folded channels in z-major order, z * C + c.

        The gather produces rows of C channels per voxel; with z outermost among a cell's channels, its
        (Q, Yq, Xq, Z * C) output is the channels-last form of the folded map, and onnxruntime reads it straight
        into its blocked layout (fp32) or its NHWC int8 convolutions, instead of transposing the whole volume
        first (see FoldedLifter).
        """
        if self.z_major:
            return self
        out = copy.deepcopy(self)
        c, nz = self.channels, self.nz
        order = torch.tensor([ci * nz + zi for zi in range(nz) for ci in range(c)])  # z-major channel -> c-major
        order = order.to(out.project.weight.device)
        for conv in (out.project, out.residual):  # z-major in and out (the residual adds its input)
            conv.weight.copy_(conv.weight[order][:, order])
            conv.bias.copy_(conv.bias[order])
        out.z_down.weight.copy_(out.z_down.weight[:, order])  # z-major in, c-major out: the z-pool reads (C, Zd)
        out.z_major = True
        return out


class FoldedLifter(nn.Module):
    """``VolumetricLifter``'s forward (gather, then convolutions) with the folded convolutions, z-major.

    The gather runs over the LUT permuted to (Q, K, Yq, Xq, Z) (int32 index and weight: 1 / C of the volume's size)
    and yields the folded map channels-last, (Q, Yq, Xq, Z * C); the convolutions take it in z-major order
    (``FoldedLifterConvs.to_z_major``). The c-major order would transpose the whole gathered volume, and the int8
    graph would transpose it back for its NHWC convolutions; the z-major gather measured faster on the deployed
    lifter, int8 most (benchmarks/RESULTS.md).
    """

    def __init__(self, convs: FoldedLifterConvs) -> None:
        super().__init__()
        self.convs = convs.to_z_major()

    def forward(self, features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
        return self.convs.folded(gather_z_major(features, lut_index, lut_weight))  # (Q, C, Yq, Xq)


def export_lifter_convs(lifter: VolumetricLifter | FlatLifter, cfg: LifterConfig, nz: int) -> nn.Module:
    """What the exporter traces for the lifter's convolutions: the folded ones where they pay, else the lifter's;
    a flat lifter's with its BatchNorms folded."""
    if isinstance(lifter, FlatLifter):
        return FlatLifterConvs(lifter).eval()
    if fold_pays(cfg, nz):
        return FoldedLifterConvs.from_lifter(lifter, cfg, nz)
    return LifterConvs(lifter)


def export_lifter(lifter: VolumetricLifter | FlatLifter, cfg: LifterConfig, nz: int) -> nn.Module:
    """What the exporter traces for the whole lifter (gather + convolutions)."""
    if isinstance(lifter, FlatLifter):
        return FlatLifterExport(lifter).eval()
    if fold_pays(cfg, nz):
        return FoldedLifter(FoldedLifterConvs.from_lifter(lifter, cfg, nz)).eval()
    return lifter


class LifterConvs(nn.Module):
    """``VolumetricLifter.convs`` (or ``FlatLifter.convs``) as a module to export (the unfolded fallback; the
    benchmark's reference)."""

    def __init__(self, lifter: VolumetricLifter | FlatLifter) -> None:
        super().__init__()
        self.lifter = lifter

    def forward(self, volume: Tensor) -> Tensor:
        return self.lifter.convs(volume)  # (Q, C, Y, X)
