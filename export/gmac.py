"""GMAC of each exported graph at the export resolution, counted on the meta device (shapes only, no arithmetic)."""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF, check_image_layout, image_map_chw
from streamdet.export.parity_inputs import ParityInputs
from streamdet.export.record import Gmacs
from streamdet.models.detector import StreamDetector
from streamdet.models.flops import count_gmac


def graph_gmacs(det: StreamDetector, inputs: ParityInputs, lut_index: np.ndarray | None = None,
                lut_weight: np.ndarray | None = None, image_layout: str = IMAGE_BEV) -> Gmacs:  # fmt: skip
    """The trained modules' GMAC: encoder per image (J = 1); lifter and slice graph at the parity slice's Q
    quadrants and P pillars. A LiDAR-only detector (no images, no LUT) has the slice graph only. In the image_half
    layout the BEV encoder's image half is counted in the lifter graph, where it runs, not in the slice graph."""
    meta = torch.device("meta")
    on_meta = lambda a: torch.empty(a.shape, dtype=torch.from_numpy(a[:0]).dtype, device=meta)  # noqa: E731
    q, pl = inputs.num_maps, inputs.pillars  # Q: one map per quadrant, or 1 whole-grid map without the crop
    c, g = det.preset.channels, det.preset.grid
    gmacs: Gmacs = {}
    image_bev = None
    if inputs.images is not None:
        j, h, w, _ = inputs.images.shape
        enc = copy.deepcopy(det.image_encoder).to(meta)
        lifter = copy.deepcopy(det.lifter).to(meta)
        hf, wf = math.ceil(h / 4), math.ceil(w / 4)
        gmacs["image_encoder"] = (count_gmac(enc, torch.empty(1, h, w, 3, dtype=torch.uint8, device=meta)), {"J": 1, "H": h, "W": w})
        gmacs["volumetric_lifter"] = (
            count_gmac(lifter, torch.empty(j, c, hf, wf, device=meta), on_meta(lut_index), on_meta(lut_weight)),
            {"J": j, "Q": q, "K": int(lut_index.shape[1])},
        )
        image_bev = torch.empty(q, c, g.quadrant_ny, g.quadrant_nx, device=meta)
    net = copy.deepcopy(det.slice_net).to(meta)
    gmac = count_gmac(net, on_meta(pl.features), on_meta(pl.mask), on_meta(pl.index), image_bev, num_quadrants=q)
    gmacs["slice_head"] = (gmac, {"Q": q, "P": pl.num_pillars})
    if image_bev is not None and check_image_layout(image_layout) == IMAGE_HALF:
        c0, yh, xh = image_map_chw(det.preset.to_dict(), (g.quadrant_ny, g.quadrant_nx), image_layout)
        half = q * c0 * c * 9 * yh * xh / 1e9  # the image half: k3 conv C -> C0 on each of the Q quadrants
        name, (lift, at) = "volumetric_lifter", gmacs["volumetric_lifter"]
        gmacs[name] = (lift + half, at)
        gmacs["slice_head"] = (gmac - half, gmacs["slice_head"][1])
    return gmacs
