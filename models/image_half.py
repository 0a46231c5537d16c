"""The BEV encoder's image half computed in the image lane: the ``image_half`` layout of the exported graphs.

Stage 0's first convolution reads the concatenation of the point BEV and the image BEV; the export splits it into
``point_conv(point_bev) + image_conv(image_bev)`` (slice_split.py). The image half depends on the image BEV only,
which changes once per quadrant lift, while the slice graph runs it once per slice (several slices read one lift).
In this layout the lifter graph ends with ``image_conv`` and outputs ``image_half`` (Q, C0, Yh, Xh), the slice graph
takes it in place of ``image_bev`` and adds it to ``point_conv``'s output.

Exactness: each quadrant is its own map in both graphs, so the convolution's zero padding at the quadrant's edges
is the same; its output grid is ``image_half_cells`` (k3, padding 1, stride ``layer_strides[0]``), the grid the
slice graph adds it to. The BatchNorm shift, which the ``image_bev`` layout puts on the image half, goes to the
point half here: the image half of a zeroed image BEV (the first part of a schedule with ``image_warmup``) is then
exactly zero, and ``relu(point_conv(p) + 0)`` is what ``relu(point_conv(p) + image_conv(0))`` gives in the other
layout (the shift is a per-channel constant: the "bias map" of a zeroed BEV is that constant everywhere, carried by
the point half). Where it has no image the runtime feeds neither, but the lift of zero features in the export's own
layout (``StreamingDetector.blank_image_bev``), which both layouts give alike.

The layouts are named by ``core/image_layout.py`` (torch-free, for the runtime too); the manifest records which one an export's graphs use (older exports:
``image_bev``). Measured: docs/replay.md ("Less work per lift").
"""

from __future__ import annotations

from torch import Tensor, nn

from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF, IMAGE_LAYOUTS, check_image_layout, image_half_cells  # noqa: F401


class ImageHalfLifter(nn.Module):
    """``forward(features, *lut) -> image_half (Q, C0, Yh, Xh)``: the lifter, then the image half.

    ``image_conv`` is the export's image half without bias (``ExportSliceNet(net, IMAGE_HALF).image_conv``).
    """

    def __init__(self, lifter: nn.Module, image_conv: nn.Conv2d) -> None:
        super().__init__()
        if image_conv.bias is not None:
            raise ValueError("the image half of the image_half layout carries no bias (it is on the point half)")
        self.lifter = lifter
        self.image_conv = image_conv

    def forward(self, features: Tensor, *lut: Tensor) -> Tensor:
        image_bev = self.lifter(features, *lut)  # (Q, C, Yq, Xq); the LUT in either layout (core/lut_layout.py)
        return self.image_conv(image_bev)  # (Q, C0, Yh, Xh)
