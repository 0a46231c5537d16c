"""The detector as three modules, one per exported graph, and their training-time composition.

    ImageEncoder      images (J, H, W, 3) uint8                        -> features (J, C, Hf, Wf)
    VolumetricLifter  features, lut_index, lut_weight (Q, K, Z, Yq, Xq) -> image_bev (Q, C, Yq, Xq)
    SliceNet          pillar tensors + image_bev                        -> head maps, each (Q, ch, Hh, Wh)

``SliceDecoder`` (decode.py) wraps SliceNet with the in-graph decode for ``slice_head.onnx``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.bev_encoder import BevEncoder
from streamdet.models.heads import CenterHead, HeadMaps
from streamdet.models.image_bev_norm import ImageBevNorm
from streamdet.models.image_encoder import ImageEncoder
from streamdet.models.flat_lifter import FlatLifter
from streamdet.models.lifter import VolumetricLifter
from streamdet.models.pillars import MapShape, PillarFeatureNet, scatter_pillars
from streamdet.models.presets import Preset


def slice_map_shape(image_bev: Tensor | None, num_quadrants: int | None, map_cells: tuple[int, int]) -> MapShape:
    """What a slice's point BEV takes its (Q, Yq, Xq) from: the image BEV, else Q maps of ``map_cells`` (a quadrant's
    (Yq, Xq), or the whole grid's (ny, nx) without the crop: ``Preset.map_cells``)."""
    if image_bev is not None:
        return image_bev
    if num_quadrants is None:
        raise ValueError("a slice without an image BEV needs num_quadrants")
    return (num_quadrants, *map_cells)


class SliceNet(nn.Module):
    """``forward(pillar_features (P, M, 11), pillar_mask (P, M), pillar_index (P,) int64, image_bev (Q, C, Yq, Xq)
    or None, *, num_quadrants) -> (heatmap, reg, height, dim, rot, vel)``, raw maps (heatmap as logits), each
    (Q, ch, Hh, Wh).

    Q comes from image_bev's shape, or from ``num_quadrants`` without one. Without an image BEV (``None``) a fused
    net sees zeros, what the runtime feeds before its first image update, and the LiDAR-only baseline
    (``preset.use_image`` False) needs none: its signature is the pillar tensors and Q (an image BEV given to it
    is read for its shape only). Without the quadrant crop (``preset.slice_crop`` False, LiDAR-only) each of the Q
    maps is the whole grid, (ny, nx) cells; one slice is then one map (``num_quadrants=1``).
    """

    def __init__(self, preset: Preset) -> None:
        super().__init__()
        c = preset.channels
        self.use_image = preset.use_image
        self.map_cells = preset.map_cells  # (Yq, Xq), or (ny, nx) without the crop
        self.pillar_net = PillarFeatureNet(preset.pillars.num_point_features, c)
        self.bev_encoder = BevEncoder(preset.bev, 2 * c if preset.use_image else c)
        self.head = CenterHead(preset.head, self.bev_encoder.out_channels)
        # the image BEV brought to the point BEV's scale (models/image_bev_norm.py); absent by default
        self.image_bev_norm = ImageBevNorm(c, preset.image_bev_target) if preset.use_image and preset.image_bev_norm else None

    def fused_bev(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor,
                  image_bev: Tensor | None = None, *, num_quadrants: int | None = None) -> Tensor:  # fmt: skip
        """The BEV encoder's output (Q, C_enc, Hh, Wh), shared by both head variants."""
        shape = slice_map_shape(image_bev, num_quadrants, self.map_cells)
        p_bev = scatter_pillars(self.pillar_net(pillar_features, pillar_mask), pillar_index, shape)  # (Q, C, Yq, Xq)
        if not self.use_image:
            return self.bev_encoder(p_bev)
        if image_bev is None:  # no image lifted yet: zeros, what the runtime feeds before its first image update
            image_bev = torch.zeros_like(p_bev)
        elif self.image_bev_norm is not None:
            image_bev = self.image_bev_norm(image_bev, p_bev)  # (Q, C, Yq, Xq)
        return self.bev_encoder(torch.cat([p_bev, image_bev], dim=1))  # (Q, 2C, Yq, Xq)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor,
                image_bev: Tensor | None = None, *, num_quadrants: int | None = None) -> HeadMaps:  # fmt: skip
        return self.head(self.fused_bev(pillar_features, pillar_mask, pillar_index, image_bev, num_quadrants=num_quadrants))


def build_lifter(preset: Preset) -> VolumetricLifter | FlatLifter:
    """The image lane's lifter of ``preset.lifter.form`` (models/presets.py LifterConfig)."""
    if preset.lifter.form == "flat":
        return FlatLifter(preset.channels, preset.grid.nz, preset.lifter.residual)
    return VolumetricLifter(preset.lifter, preset.channels)


class StreamDetector(nn.Module):
    """The three parts together, for training.

    One call covers one sample's slice: J images and the Q quadrants the slice touches. To batch several samples,
    stack their images along J, their quadrants along Q (with ``lifter.batch_lut_index`` for the LUT indices) and
    offset each pillar_index by the sample's first quadrant times Yq * Xq.
    """

    def __init__(self, preset: Preset) -> None:
        super().__init__()
        self.preset = preset
        self.image_encoder = ImageEncoder(preset.image, preset.channels) if preset.use_image else None
        self.lifter = build_lifter(preset) if preset.use_image else None
        self.slice_net = SliceNet(preset)

    def image_bev(self, images: Tensor, lut_index: Tensor, lut_weight: Tensor, camera_keep: Tensor | None = None) -> Tensor:
        """``camera_keep`` (one bool per image, in ``images`` order; None: all): the images False are lifted from
        zero features, as the runtime lifts a camera without a frame (training/camera_dropout.py)."""
        if self.image_encoder is None or self.lifter is None:
            raise RuntimeError(f"preset {self.preset.name!r} has use_image=False: there is no image lane")
        feats = self.image_encoder(images)  # (J, C, Hf, Wf)
        if camera_keep is not None:
            if camera_keep.numel() != feats.shape[0]:
                raise ValueError(f"camera_keep has {tuple(camera_keep.shape)} entries for {feats.shape[0]} images")
            # exact zeros, as the runtime feeds a missing camera (a product with 0 would keep an inf as NaN)
            feats = torch.where(camera_keep.reshape(-1, 1, 1, 1), feats, torch.zeros_like(feats))  # (J, C, Hf, Wf)
        return self.lifter(feats, lut_index, lut_weight)  # (Q, C, Yq, Xq)

    def forward(
        self,
        images: Tensor | None,
        lut_index: Tensor | None,
        lut_weight: Tensor | None,
        pillar_features: Tensor,
        pillar_mask: Tensor,
        pillar_index: Tensor,
        *,
        num_quadrants: int | None = None,
    ) -> HeadMaps:
        """Head maps of the slice. With use_image=False, images and the LUT may be None; Q is then
        ``num_quadrants`` (or lut_index.shape[0] when a LUT is given)."""
        if self.preset.use_image:
            if images is None or lut_index is None or lut_weight is None:
                raise ValueError("images, lut_index and lut_weight are required when preset.use_image is True")
            image_bev = self.image_bev(images, lut_index, lut_weight)
        else:
            q = num_quadrants if num_quadrants is not None else (None if lut_index is None else lut_index.shape[0])
            if q is None:
                raise ValueError("LiDAR-only forward needs num_quadrants (or a lut_index to take Q from)")
            return self.slice_net(pillar_features, pillar_mask, pillar_index, num_quadrants=q)
        return self.slice_net(pillar_features, pillar_mask, pillar_index, image_bev)


def build_detector(preset: Preset) -> StreamDetector:
    return StreamDetector(preset)
