"""The detector's training-time forward over a ``Batch`` (one module, so DistributedDataParallel can wrap it)."""

from __future__ import annotations

from torch import Tensor, nn

from streamdet.core.classes import CLASS_NAMES
from streamdet.models.detector import StreamDetector
from streamdet.models.heads import HeadMaps
from streamdet.training.batching import Batch
from streamdet.training.image_class import ImageBevClassifier, centre_cells


class TrainingModel(nn.Module):
    """``forward(batch) -> (list of HeadMaps, image class logits or None)``: one HeadMaps per head task
    (``CenterHead.forward_tasks``), each map (Qm, ch, Hh, Wh) over the batch's stacked slice maps; with
    ``image_classifier`` and the image lane on, the logits (N, num_classes) of the batch's N objects read from the
    image BEV at their centres (``training/image_class.py``). ``detector`` is the StreamDetector that is exported;
    the classifier is training-only."""

    def __init__(self, detector: StreamDetector, image_classifier: bool = False) -> None:
        super().__init__()
        self.detector = detector
        if image_classifier and not detector.preset.use_image:
            raise ValueError("the image-BEV class loss needs the image lane (the preset has use_image=False)")
        self.image_classifier = ImageBevClassifier(detector.preset.channels, len(CLASS_NAMES)) if image_classifier else None

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

    def forward(self, batch: Batch, use_image: bool = True) -> tuple[list[HeadMaps], Tensor | None]:
        net = self.detector.slice_net
        image_bev = self.image_bev(batch, use_image)
        bev = net.fused_bev(batch.pillar_features, batch.pillar_mask, batch.pillar_index, image_bev, num_quadrants=batch.num_maps)
        task_maps = net.head.forward_tasks(bev)
        if self.image_classifier is None or image_bev is None:
            return task_maps, None
        head_width = batch.heatmap.shape[-1]
        cells = centre_cells(batch.index, batch.box, head_width, image_bev.shape[-1] // head_width)  # (Qm, K)
        return task_maps, self.image_classifier(image_bev, cells, batch.mask)
