"""Camera dropout: train the fused detector on what the runtime feeds it when cameras are missing.

At run time a camera with no frame (dead, unplugged, timed out: ``SliceResult.cameras_missing``) is lifted from
**zero features**, and a quadrant none of whose cameras has a frame reads the lift of zero features of every camera
(``StreamingDetector.blank_image_bev``). A model that always trained with six cameras never saw either, and leans on
them: docs/replay.md, "A quadrant without cameras", measures what that costs. Camera dropout shows it both during
training, in exactly the runtime's form: the dropped cameras' encoder features are zeroed before the lift.

With probability ``p`` a training sample loses ``k`` of its ``J`` cameras, ``k`` uniform in 1..J and the ``k``
cameras uniform among the J. So every camera subset size is as likely as any other, all cameras dark comes with
probability ``p / J``, and a sample keeps all of them with probability ``1 - p``. Nothing changes in the exported
graphs: dropout is a training-time augmentation only (``TrainConfig.camera_dropout``, ``streamdet-train
--camera-dropout``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def check_camera_dropout(value: object, what: str = "camera_dropout") -> float:
    """``value`` as a float probability in [0, 1); ValueError naming ``what`` and quoting the value otherwise (1 would
    never show the model a camera)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise ValueError(f"{what} must be a probability in [0, 1) (the share of samples that lose cameras), got {value!r}")
    return float(value)


def draw_camera_keep(num_samples: int, num_cameras: int, p: float, generator: torch.Generator | None = None,
                     device: torch.device | str = "cpu") -> Tensor:  # fmt: skip
    """(num_samples, num_cameras) bool: True where a camera is kept (see the module doc for the draw).

    Draws on ``generator`` (the CPU's default one when None), on the CPU whatever ``device``, so that a run's drops
    do not depend on where it trains; the result is moved to ``device``."""
    p = check_camera_dropout(p, "p")
    if num_samples < 0 or num_cameras < 1:
        raise ValueError(f"need num_samples >= 0 and num_cameras >= 1, got {num_samples} and {num_cameras}")
    drop_sample = torch.rand(num_samples, generator=generator) < p  # (B,)
    k = torch.randint(1, num_cameras + 1, (num_samples,), generator=generator)  # (B,) cameras to drop, if dropping
    # the k cameras of lowest random rank are dropped: a uniform k-subset
    rank = torch.rand(num_samples, num_cameras, generator=generator).argsort(dim=1).argsort(dim=1)  # (B, J)
    dropped = drop_sample[:, None] & (rank < k[:, None])  # (B, J)
    return (~dropped).to(device)
