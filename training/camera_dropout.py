"""Camera dropout: train the fused detector on what the runtime feeds it when cameras are missing.

At run time a camera with no frame (dead, unplugged, timed out: ``SliceResult.cameras_missing``) is lifted from
**zero features**, and a quadrant none of whose cameras has a frame reads the lift of zero features of every camera
(``StreamingDetector.blank_image_bev``). A model that always trained with six cameras never saw either, and leans on
them: docs/replay.md, "A quadrant without cameras", measures what that costs. Camera dropout shows it both during
training, in the runtime's form:

- a training step drops cameras with probability ``p`` (``TrainConfig.camera_dropout``, ``streamdet-train
  --camera-dropout``), decided per step and so the same on every process of a distributed run;
- in such a step every sample loses ``k`` of its ``J`` cameras, ``k`` uniform in 1..J and the ``k`` cameras uniform
  among the J (drawn per process): all cameras dark comes in one such sample in J;
- the dropped cameras' encoder features are exactly zero before the lift, and the camera lane and the image-BEV
  norm normalise with their **stored statistics** (eval mode) in that step, as the exported graphs do. In training
  mode their BatchNorms would normalise a dark sample's zeros with the batch's own statistics, giving a map the
  runtime never makes, and the statistics stored for export would absorb the dark samples.

The draws come from generators seeded by (seed, step[, process]) (``step_generator``): a resumed run drops what the
uninterrupted one drops. Nothing changes in the exported graphs.
"""

from __future__ import annotations

import hashlib
import math
from contextlib import contextmanager
from typing import Iterable, Iterator

import torch
from torch import Tensor, nn


def check_camera_dropout(value: object, what: str = "camera_dropout") -> float:
    """``value`` as a float probability in [0, 1); ValueError naming ``what`` and quoting the value otherwise (1 would
    never show the model a camera)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise ValueError(f"{what} must be a probability in [0, 1) (the share of steps that drop cameras), got {value!r}")
    return float(value)


def step_generator(*key: int) -> torch.Generator:
    """A CPU generator seeded from integers (seed, step, process, ...) of any size, the same on every machine."""
    digest = hashlib.blake2b(",".join(str(int(k)) for k in key).encode(), digest_size=8).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest, "little") & 0x7FFF_FFFF_FFFF_FFFF)


def drops_cameras(p: float, generator: torch.Generator) -> bool:
    """Whether a step drops cameras (probability ``p``)."""
    return bool(torch.rand(1, generator=generator)[0] < check_camera_dropout(p, "p"))


def draw_camera_keep(num_samples: int, num_cameras: int, generator: torch.Generator | None = None,
                     device: torch.device | str = "cpu") -> Tensor:  # fmt: skip
    """(num_samples, num_cameras) bool, True where a camera is kept: each sample loses k cameras, k uniform in
    1..num_cameras, the k uniform among them. Drawn on the CPU (the same draws wherever the run trains), then moved
    to ``device``."""
    if num_samples < 0 or num_cameras < 1:
        raise ValueError(f"need num_samples >= 0 and num_cameras >= 1, got {num_samples} and {num_cameras}")
    k = torch.randint(1, num_cameras + 1, (num_samples,), generator=generator)  # (B,) cameras to drop
    # the k cameras of lowest random rank are dropped: a uniform k-subset
    rank = torch.rand(num_samples, num_cameras, generator=generator).argsort(dim=1).argsort(dim=1)  # (B, J)
    return (rank >= k[:, None]).to(device)


@contextmanager
def stored_statistics(modules: Iterable[nn.Module | None]) -> Iterator[None]:
    """Run ``modules`` (None entries skipped) in eval mode, normalising with their stored statistics and leaving them
    unchanged, then give every submodule its mode back."""
    modes = [(m, m.training) for module in modules if module is not None for m in module.modules()]
    for m, _ in modes:
        m.training = False
    try:
        yield
    finally:
        for m, mode in modes:
            m.training = mode
