"""The PyTorch model as a sweep detector, mirroring the ONNX runtime step by step, for ``evaluate_dataset``.

Image lane: every camera through the encoder, the lifter over all four quadrants with the rig's LUT at the
preset's image size. Slice lane: ``split_sweep``, ``pillarize`` (the runtime's), the slice net, the in-graph
decode (``models/decode.py``), then the runtime's own ``postprocess_slice`` and ``aggregate_sweep``; a LiDAR-only
net without the quadrant crop (``preset.slice_crop`` False) on one whole-grid map per slice, as its export runs. Only the
arithmetic differs from onnxruntime, so this scores what the exported graphs would if they matched PyTorch.
"""

from __future__ import annotations

import numpy as np
import torch

from streamdet.calibration.lut import Lut
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.slice_maps import slice_maps
from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import Sample
from streamdet.models.decode import decode_head_maps
from streamdet.models.detector import StreamDetector
from streamdet.runtime_ort.nms import NmsConfig
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.postprocess import Detections, PostprocessConfig, aggregate_sweep, postprocess_slice
from streamdet.training.batching import check_rig_fits_preset


def _first_image(sample: Sample) -> str:
    """Where the sample's images lie (its first camera's file), for an error to name the dataset."""
    path = next(iter(sample.image_paths.values()), None)
    return f"image {path}" if path is not None else "no image files"


class TorchSweepDetector:
    """``sample -> Detections`` with a StreamDetector (eval mode, no grad)."""

    def __init__(self, model: StreamDetector, num_slices: int = 8, score_threshold: float | None = None,
                 nms: NmsConfig = NmsConfig(), device: str | torch.device = "cpu") -> None:  # fmt: skip
        self.model = model.eval().to(device)
        self.preset = model.preset
        self.num_slices = num_slices
        self.device = torch.device(device)
        threshold = self.preset.post.score_threshold if score_threshold is None else score_threshold
        self.post = PostprocessConfig(score_threshold=threshold, nms=nms)
        self._luts: dict[str, Lut] = {}

    def _lut(self, sample: Sample) -> Lut:
        key = sample.rig.sha256()
        if key not in self._luts:
            # the rule the ONNX runtime applies to the same sample (check_rig_fits): a distorting resize is refused
            check_rig_fits_preset(sample.rig, self.preset, f"sample {sample.token} ({_first_image(sample)})")
            img = self.preset.image
            self._luts[key] = build_lut(sample.rig, self.preset.grid, img.feature_stride, (img.width_px, img.height_px),
                                        heights_per_voxel=self.preset.lifter.lut_heights_per_voxel)  # fmt: skip
        return self._luts[key]

    @torch.no_grad()
    def __call__(self, sample: Sample) -> Detections:
        p, g = self.preset, self.preset.grid
        if p.use_image:
            lut = self._lut(sample)
            images = torch.from_numpy(sample.load_images((p.image.width_px, p.image.height_px))).to(self.device)
            index = torch.from_numpy(np.asarray(lut.index, np.int64)).to(self.device)
            weight = torch.from_numpy(np.array(lut.weight)).to(self.device)
            bev = self.model.image_bev(images, index, weight)  # (4, C, Yq, Xq)
        else:
            bev = None  # the LiDAR-only net reads the slice's quadrant count only
        results = []
        for k, points in enumerate(split_sweep(np.asarray(sample.points, np.float32), self.num_slices)):
            quadrants = quadrants_of_sector(k, self.num_slices)
            pil = pillarize(points, g, quadrants, p.pillars.max_points_per_pillar, p.pillars.max_pillars, crop=p.slice_crop)
            if pil.num_pillars == 0:
                continue
            maps = self.model.slice_net(
                torch.from_numpy(pil.features).to(self.device), torch.from_numpy(pil.mask).to(self.device),
                torch.from_numpy(pil.index).to(self.device), None if bev is None else bev[list(quadrants)],
                num_quadrants=slice_maps(g, quadrants, p.slice_crop).count,  # quadrants, or 1 whole-grid map
            )  # fmt: skip
            boxes, scores, labels = decode_head_maps(maps, p.head_cell_m, p.top_k)
            results.append(postprocess_slice(boxes.cpu().numpy(), scores.cpu().numpy(), labels.cpu().numpy(), quadrants, g,
                                             self.post, crop=p.slice_crop))  # fmt: skip
        return aggregate_sweep(results, self.post.nms)
