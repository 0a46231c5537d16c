"""The detector's export form: every export-time rewrite of a trained ``StreamDetector``, applied in one place.

``to_export_form(det)`` returns the modules the graphs are traced from (export/onnx_export.py), each the same
function as the trained module it replaces (the export's parity checks compare them with the PyTorch modules):

    graph               trained module                 export form
    image_encoder       ImageEncoder                   the same function (a copy; normalisation inside)
    volumetric_lifter   VolumetricLifter               FoldedLifter where the z-fold pays (lifter_fold.py),
                                                       else the same module; in the image_half layout followed
                                                       by the BEV encoder's image half (ImageHalfLifter,
                                                       image_half.py); reading the compacted LUT in the
                                                       compact LUT layout (CompactLifter, compact_lifter.py)
    slice_head          SliceNet + decode              SliceDecoder(ExportSliceNet) (slice_split.py): the
                                                       concatenations split into sums of convolutions, 1x1
                                                       deblocks as convolutions, a multi-head's branches grouped
                                                       (GroupedTaskHead), a single head's regression computed at
                                                       the decode's peaks (PeakHead, peak_head.py), the point BEV
                                                       by gather_pillars;
                                                       LidarSliceDecoder for the LiDAR-only baseline,
                                                       FullMapSliceDecoder for it without the crop

Every BatchNorm is folded by ``bn_fold.fold_bn`` (eval statistics). Training never sees these modules; what is
measured of them is in benchmarks/RESULTS.md.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

from torch import Tensor, nn

from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import SliceNet, StreamDetector
from streamdet.core.lut_layout import LUT_COMPACT, LUT_SLOTS, check_lut_layout
from streamdet.models.compact_lifter import CompactLifter
from streamdet.models.image_half import IMAGE_BEV, IMAGE_HALF, ImageHalfLifter, check_image_layout
from streamdet.models.lifter_fold import export_lifter
from streamdet.models.presets import Preset
from streamdet.models.slice_split import ExportSliceNet


class LidarSliceDecoder(SliceDecoder):
    """``forward(pillar_features, pillar_mask, pillar_index, quadrants (Q,) int64) -> det_boxes, det_scores,
    det_labels``: SliceDecoder of a LiDAR-only net, with Q read off ``quadrants`` (no image BEV exists).

    The pillar tensors cannot tell Q: a slice whose last quadrant has no pillar still gets that quadrant's head
    output, as in PyTorch. A subclass rather than a wrapper so that the exported node scopes stay
    ``/slice_net/...`` and the decode's are the root's (the fp16 / int8 block lists rely on them).
    """

    def __init__(self, slice_net: SliceNet | nn.Module, preset: Preset) -> None:  # nn.Module: its export form
        if slice_net.use_image:
            raise ValueError(f"preset {preset.name!r} has use_image=True: its slice graph needs image_bev")
        super().__init__(slice_net, preset)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor,
                quadrants: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        maps = self.slice_net(pillar_features, pillar_mask, pillar_index, num_quadrants=quadrants.shape[0])
        return self.decode(maps)


class FullMapSliceDecoder(SliceDecoder):
    """``forward(pillar_features, pillar_mask, pillar_index) -> det_boxes, det_scores, det_labels``: SliceDecoder of a
    LiDAR-only net without the quadrant crop (``preset.slice_crop`` False), whose every slice is one map of the
    whole grid, so Q is 1 and the graph needs no quadrant ids. Boxes are relative to the grid's minimum corner.
    """

    def __init__(self, slice_net: SliceNet | nn.Module, preset: Preset) -> None:  # nn.Module: its export form
        if slice_net.use_image or preset.slice_crop:
            raise ValueError(f"preset {preset.name!r} is not a LiDAR-only preset without the crop (slice_crop=False)")
        super().__init__(slice_net, preset)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        maps = self.slice_net(pillar_features, pillar_mask, pillar_index, num_quadrants=1)  # each (1, ch, Hh, Wh)
        return self.decode(maps)


@dataclass(frozen=True, eq=False)
class ExportForm:
    """The modules traced into the graphs, by graph name; None for the graphs a LiDAR-only model lacks."""

    image_encoder: nn.Module | None
    volumetric_lifter: nn.Module | None
    slice_head: SliceDecoder

    def graphs(self) -> dict[str, nn.Module]:
        """The graphs this model exports, in pipeline order."""
        parts = {"image_encoder": self.image_encoder, "volumetric_lifter": self.volumetric_lifter, "slice_head": self.slice_head}
        return {name: module for name, module in parts.items() if module is not None}


def to_export_form(det: StreamDetector, image_layout: str = IMAGE_BEV, lut_layout: str = LUT_SLOTS) -> ExportForm:
    """The export form of a trained detector: a snapshot of its weights, every module in eval mode.

    ``det`` is left as it was: the form is built from a copy, so it shares no module or tensor with it, and its
    modes (train or eval, module by module) are unchanged. Taking the form inside a training loop (a periodic export)
    neither stops the BatchNorm statistics' updates nor sees later steps; the folded modules are snapshots anyway.

    ``image_layout`` (image_half.py): ``image_bev``, the lifter outputs the image BEV and the slice graph runs both
    halves of stage 0's first conv; ``image_half``, the lifter graph also runs the image half and outputs it, the
    slice graph adds it. A LiDAR-only detector has no image half (the layout is ignored). ``lut_layout``
    (core/lut_layout.py): ``compact``, the lifter reads the compacted LUT (CompactLifter, compact_lifter.py).
    """
    preset = det.preset
    check_image_layout(image_layout)
    layout = image_layout if preset.use_image else IMAGE_BEV
    det = copy.deepcopy(det).eval()  # eval() on the caller's modules would stop a training detector's BN updates
    slice_net = ExportSliceNet(det.slice_net, layout, peak_regression=True).eval()
    if not preset.use_image:
        decoder = LidarSliceDecoder if preset.slice_crop else FullMapSliceDecoder
        return ExportForm(None, None, decoder(slice_net, preset).eval())
    lifter = export_lifter(det.lifter, preset.lifter, preset.grid.nz)
    if check_lut_layout(lut_layout) == LUT_COMPACT:
        lifter = CompactLifter(lifter).eval()
    if layout == IMAGE_HALF:
        lifter = ImageHalfLifter(lifter, slice_net.image_conv).eval()
    return ExportForm(det.image_encoder, lifter, SliceDecoder(slice_net, preset).eval())
