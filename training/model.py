"""The detector's training-time forward over a ``Batch`` (one module, so DistributedDataParallel can wrap it)."""

from __future__ import annotations

from contextlib import nullcontext

import torch
from torch import Tensor, nn

from streamdet.core.classes import CLASS_NAMES
from streamdet.models.detector import StreamDetector
from streamdet.models.heads import HeadMaps
from streamdet.training.batching import Batch
from streamdet.training.camera_dropout import stored_statistics
from streamdet.training.image_class import ImageBevClassifier, centre_cells

CAMERA_LANE = ("image_encoder", "lifter")  # the StreamDetector parts that make the image BEV


class TrainingModel(nn.Module):
    """``forward(batch) -> (list of HeadMaps, (image class logits, labels) or None)``: one HeadMaps per head task
    (``CenterHead.forward_tasks``), each map (Qm, ch, Hh, Wh) over the batch's stacked slice maps; with
    ``image_classifier`` and the image lane on, the logits (N, num_classes) of the batch's N objects read from the
    image BEV at their centres (``training/image_class.py``) and their labels (N,). ``detector`` is the StreamDetector that is exported;
    the classifier is training-only.

    ``freeze_camera_lane``: the image encoder and lifter keep their weights (no gradient) and their BatchNorm
    statistics (eval mode whatever ``train()`` says), and lift without building a graph: a new slice net learns to
    read a camera lane trained before.
    """

    def __init__(self, detector: StreamDetector, image_classifier: bool = False, freeze_camera_lane: bool = False) -> None:
        super().__init__()
        self.detector = detector
        if image_classifier and not detector.preset.use_image:
            raise ValueError("the image-BEV class loss needs the image lane (the preset has use_image=False)")
        if freeze_camera_lane and not detector.preset.use_image:
            raise ValueError("freeze_camera_lane needs the image lane (the preset has use_image=False)")
        self.image_classifier = ImageBevClassifier(detector.preset.channels, len(CLASS_NAMES)) if image_classifier else None
        self.frozen = tuple(getattr(detector, part) for part in CAMERA_LANE) if freeze_camera_lane else ()
        for module in self.frozen:
            module.requires_grad_(False)
            module.eval()

    def train(self, mode: bool = True) -> "TrainingModel":
        super().train(mode)
        for module in self.frozen:
            module.eval()
        return self

    @property
    def task_classes(self) -> tuple[tuple[int, ...], ...]:
        return self.detector.slice_net.head.task_classes

    def image_bev(self, batch: Batch, use_image: bool = True, camera_keep: Tensor | None = None) -> Tensor | None:
        """(Qm, C, Yq, Xq): the lifted quadrant volumes, each slice map reading its lift entry; None for the
        LiDAR-only preset or with ``use_image`` False (the slice net then sees zeros, what the runtime feeds before
        its first image update, or no image BEV at all: ``SliceNet.fused_bev``). ``camera_keep`` (B, J) bool, given
        for a step that drops cameras: the cameras False are lifted from zero features, as the runtime lifts a camera
        without a frame, and the camera lane normalises with its stored statistics (training/camera_dropout.py);
        None: every camera."""
        d = self.detector
        if not (d.preset.use_image and use_image):
            return None
        # a step that drops cameras normalises with the stored statistics, as the exported graphs (camera_dropout.py)
        stored = stored_statistics((d.image_encoder, d.lifter)) if camera_keep is not None else nullcontext()
        with torch.no_grad() if self.frozen else nullcontext(), stored:
            # images sample-major (B * J): camera_keep (B, J) flattens in their order
            lifted = d.image_bev(batch.images, batch.lut_index, batch.lut_weight, camera_keep)  # (L, C, Yq, Xq)
        return lifted.index_select(0, batch.map_source)  # (Qm, C, Yq, Xq)

    def forward(self, batch: Batch, use_image: bool = True, lifted: Tensor | None = None,
                camera_keep: Tensor | None = None) -> tuple[list[HeadMaps], tuple[Tensor, Tensor] | None]:  # fmt: skip
        """``lifted``: the batch's image BEV (Qm, C, Yq, Xq) when it was computed already (a frozen camera lane
        shared with a distillation teacher, training/distill.py); None: lift it here, with the cameras of
        ``camera_keep`` (``image_bev``), given for a step that drops cameras (training/camera_dropout.py): the camera
        lane and the image-BEV norm then normalise with their stored statistics, as the exported graphs do. The second
        output: (logits (N, num_classes), labels (N,)) of the image-side class loss over the N objects of the samples
        that kept every camera (an object whose cameras were dropped has nothing to be read from), or None without
        the classifier or the image lane."""
        net = self.detector.slice_net
        image_bev = lifted if lifted is not None and use_image else self.image_bev(batch, use_image, camera_keep)
        stored = stored_statistics((net.image_bev_norm,)) if camera_keep is not None else nullcontext()
        with stored:
            bev = net.fused_bev(batch.pillar_features, batch.pillar_mask, batch.pillar_index, image_bev, num_quadrants=batch.num_maps)
        task_maps = net.head.forward_tasks(bev)
        if self.image_classifier is None or image_bev is None:
            return task_maps, None
        objects = batch.mask  # (Qm, K)
        if camera_keep is not None:
            whole = camera_keep.reshape(batch.num_samples, -1).all(dim=1)  # (B,) samples that kept every camera
            objects = objects & whole.index_select(0, batch.map_sample)[:, None]  # (Qm, K)
        head_width = batch.heatmap.shape[-1]
        cells = centre_cells(batch.index, batch.box, head_width, image_bev.shape[-1] // head_width)  # (Qm, K)
        return task_maps, (self.image_classifier(image_bev, cells, objects), batch.label[objects])
