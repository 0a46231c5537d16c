"""The detector's training-time forward over a ``Batch`` (one module, so DistributedDataParallel can wrap it)."""

from __future__ import annotations

from torch import Tensor, nn

from streamdet.models.detector import StreamDetector
from streamdet.models.heads import HeadMaps
from streamdet.training.batching import Batch


class TrainingModel(nn.Module):
    """``forward(batch) -> list of HeadMaps``, one per head task (``CenterHead.forward_tasks``), each map
    (Qm, ch, Hh, Wh) over the batch's stacked slice maps. ``detector`` is the StreamDetector that is exported."""

    def __init__(self, detector: StreamDetector) -> None:
        super().__init__()
        self.detector = detector

    @property
    def task_classes(self) -> tuple[tuple[int, ...], ...]:
        return self.detector.slice_net.head.task_classes

    def image_bev(self, batch: Batch, use_image: bool = True) -> Tensor | None:
        """(Qm, C, Yq, Xq): the lifted quadrant volumes, each slice map reading its lift entry; None for the
        LiDAR-only preset or with ``use_image`` False (the slice net then sees zeros, what the runtime feeds before
        its first image update, or no image BEV at all: ``SliceNet.fused_bev``)."""
        d = self.detector
        if not (d.preset.use_image and use_image):
            return None
        lifted = d.image_bev(batch.images, batch.lut_index, batch.lut_weight)  # (L, C, Yq, Xq)
        return lifted.index_select(0, batch.map_source)  # (Qm, C, Yq, Xq)

    def forward(self, batch: Batch, use_image: bool = True) -> list[HeadMaps]:
        net = self.detector.slice_net
        image_bev = self.image_bev(batch, use_image)
        bev = net.fused_bev(batch.pillar_features, batch.pillar_mask, batch.pillar_index, image_bev, num_quadrants=batch.num_maps)
        return net.head.forward_tasks(bev)
