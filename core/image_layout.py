"""Which map the lifter graph hands the slice graph: the layouts of a fused export (models/image_half.py).

Torch-free, for the exporter, the manifest and the runtime alike. ``image_bev``: the lifter outputs the image BEV
(Q, C, Yq, Xq) and the slice graph runs both halves of the BEV encoder's first convolution. ``image_half``: the
lifter graph also runs that convolution's image half and outputs it, (Q, C0, Yh, Xh); the slice graph adds it to its
point half. A manifest without the field is ``image_bev`` (every export before the field existed).
"""

from __future__ import annotations

IMAGE_BEV = "image_bev"
IMAGE_HALF = "image_half"
IMAGE_LAYOUTS: tuple[str, ...] = (IMAGE_BEV, IMAGE_HALF)


def check_image_layout(layout: str) -> str:
    """``layout`` if it is one of IMAGE_LAYOUTS, else a ValueError naming it."""
    if layout not in IMAGE_LAYOUTS:
        raise ValueError(f"image layout must be one of {IMAGE_LAYOUTS}, got {layout!r}")
    return layout


def image_half_cells(quadrant_cells: tuple[int, int], stride: int) -> tuple[int, int]:
    """(Yh, Xh) of the image half: the BEV encoder's first conv (k3, padding 1, ``stride``) on a (Yq, Xq) quadrant."""
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride must be an int >= 1, got {stride!r}")
    yq, xq = quadrant_cells
    return (yq - 1) // stride + 1, (xq - 1) // stride + 1


def image_map_chw(preset: dict, quadrant_cells: tuple[int, int], layout: str) -> tuple[int, int, int]:
    """(C, H, W) of one quadrant's map in ``layout``, from a preset's dict (``Preset.to_dict``, the manifest's)."""
    yq, xq = quadrant_cells
    if check_image_layout(layout) == IMAGE_BEV:
        return int(preset["channels"]), yq, xq
    bev = preset["bev"]
    yh, xh = image_half_cells((yq, xq), int(bev["layer_strides"][0]))
    return int(bev["num_filters"][0]), yh, xh
