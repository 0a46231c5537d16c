"""Checkpoints as plain dicts of state dicts (``torch.load(path, weights_only=True)`` reads them).

Training checkpoint (``save_training_state``)::

    format      "streamdet-train-v1"
    preset      Preset.to_dict() of the trained model (use_image tells the LiDAR-only baseline apart)
    model       StreamDetector.state_dict()
    optimizer   optimizer.state_dict()
    scheduler   lr scheduler state_dict()
    step        optimizer steps done; epoch, epoch_step: where the data order resumes
    config      the TrainConfig as a dict (what the run was asked to do)
    data        {"samples", "tokens_sha256"} of the train split (trainer.data_record): a resume checks it continues
                over the same samples (absent in checkpoints from before it: not checked)
    image_classifier   only with the image class loss: its training-only classifier (training/image_class.py)
    scaler      only under CUDA fp16 autocast (--amp): the loss scaler's state dict (scale, growth tracker)

Weights for shipping (``save_weights``): only ``format`` "streamdet-weights-v1", ``preset``, ``model`` (and an
optional ``meta`` dict). Both have the ``{"preset", "model"}`` keys that ``streamdet.export.weights.load_detector``
reads, so ``streamdet-export --checkpoint`` takes either. ``save_weights(..., half=True)`` stores float tensors as
float16 to halve the file; ``load_weights`` casts them back to the model's dtypes.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from streamdet.core.errors import first_line
from streamdet.models.detector import StreamDetector, build_detector
from streamdet.models.torch_files import (  # noqa: F401 (public here too)
    MAX_CHECKPOINT_BYTES, check_fits, check_state_dict, check_torch_zip, read_torch_file)
from streamdet.models.presets import Preset
from streamdet.training.run_dir import write_run_file

TRAIN_FORMAT = "streamdet-train-v1"
WEIGHTS_FORMAT = "streamdet-weights-v1"


def save_atomic(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save(obj)`` to ``path`` the way every output file is written (core/file_output.py): a hidden temp
    file beside it, flushed, then renamed. A crash or a kill mid-save leaves the previous checkpoint whole, and a
    symlink at ``path`` is replaced rather than written through. The temp file's name holds this process's pid
    (run_dir.write_run_file): one a SIGKILL left is removed when a run next starts in the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_run_file(path, lambda f: torch.save(obj, f))


def save_training_state(path: str | os.PathLike, *, preset: Preset, model: StreamDetector, optimizer, scheduler,
                        step: int, epoch: int, epoch_step: int, config: dict[str, Any],
                        image_classifier: torch.nn.Module | None = None, data: dict[str, Any] | None = None,
                        scaler: dict[str, Any] | None = None) -> None:  # fmt: skip
    extra = {} if image_classifier is None else {"image_classifier": image_classifier.state_dict()}
    if data is not None:
        extra["data"] = data
    if scaler is not None:
        extra["scaler"] = scaler
    save_atomic(
        {
            "format": TRAIN_FORMAT,
            "preset": preset.to_dict(),
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "step": int(step),
            "epoch": int(epoch),
            "epoch_step": int(epoch_step),
            "config": config,
            **extra,
        },
        path,
    )


def load_checkpoint(path: str | os.PathLike, what: str = "checkpoint") -> dict[str, Any]:
    """The checkpoint dict; ValueError (one line) when it is missing, unreadable or lacks model / preset, or when
    its model is not a state dict (str keys, tensor values)."""
    return check_checkpoint(read_torch_file(path, what), path, what)


def check_checkpoint(obj: Any, path: str | os.PathLike, what: str = "checkpoint") -> dict[str, Any]:
    """``obj`` (what ``path`` holds, read) when it is a checkpoint dict with a model state dict and a preset; else
    ``load_checkpoint``'s ValueError."""
    if isinstance(obj, dict) and {"model", "optimizer", "step"} <= obj.keys() and "preset" not in obj:
        # streamdet-train-image's last.pt (image_pretrain.py): a segmenter's training state, no detector in it
        folder = Path(path).parent
        raise ValueError(f"{what} {path} is a streamdet-train-image last.pt (an image segmenter's training state, no "
                         f"detector): streamdet-train --init takes {folder / 'detector_init.pt'} (a whole detector) or "
                         f"{folder / 'encoder.pt'} (its image encoder) from the same run; streamdet-train-image --resume "
                         "continues it")  # fmt: skip
    if not isinstance(obj, dict) or not isinstance(obj.get("model"), dict) or not isinstance(obj.get("preset"), dict):
        raise ValueError(f"{what} {path} is not a streamdet checkpoint (expected a dict with 'model' and 'preset')")
    check_state_dict(obj["model"], path, what)
    return obj


def meta_state_dict(preset: Preset) -> dict[str, torch.Tensor]:
    """The state dict of ``preset``'s detector built on the meta device: every name, shape and dtype, no memory."""
    with torch.device("meta"):
        return build_detector(preset).state_dict()


def is_encoder_weights(path: str | os.PathLike) -> bool:
    """Whether ``path`` holds a bare state dict (``streamdet-train-image``'s ``encoder.pt``) rather than a
    checkpoint dict with 'model' and 'preset'; False for an unreadable file (``load_checkpoint`` says why)."""
    try:
        obj = read_torch_file(path)
    except ValueError:  # reported by load_checkpoint
        return False
    return is_encoder_state(obj)


def is_encoder_state(obj: Any) -> bool:
    """Whether ``obj`` (a file's contents, read) is a bare state dict (an ``encoder.pt``), not a checkpoint dict."""
    return (isinstance(obj, dict) and bool(obj) and "model" not in obj
            and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()))  # fmt: skip


def load_encoder_weights(detector: StreamDetector, path: str | os.PathLike, obj: Any = None) -> None:
    """Copy an ``encoder.pt`` (the image encoder's state dict, ``streamdet-train-image``) into
    ``detector.image_encoder``; ValueError naming the file if it does not fit. ``obj``: the file's contents where
    the caller read them already."""
    if detector.image_encoder is None:
        raise ValueError(f"{path}: holds image encoder weights, but the model has no image lane (use_image=False)")
    if obj is None:
        obj = read_torch_file(path, "image encoder weights")
    state = check_state_dict(obj, path, "image encoder weights", "file")
    own = detector.image_encoder.state_dict()
    check_fits(own, state, path, "image encoder weights", "the detector's image encoder")
    try:
        detector.image_encoder.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=True)
    except (RuntimeError, AttributeError, TypeError) as e:
        raise ValueError(f"{path}: does not fit the detector's image encoder: {first_line(e)}") from None


# The parts a checkpoint of another preset can hand over, each with the preset fields that fix its weights' shapes and
# what its inputs mean: a slice net of new widths (e.g. small_v3_thin) starts from a trained camera lane.
TRANSFERABLE_PARTS: dict[str, tuple[str, ...]] = {
    "image_encoder": ("channels", "image"),
    "lifter": ("channels", "grid", "image", "lifter"),
    "slice_net.pillar_net": ("channels", "grid", "pillars"),
}


def transferable_weights(own: Preset, other: dict[str, Any], state: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], tuple[str, ...]]:
    """The tensors of ``state`` (a model state dict of preset ``other``, as ``Preset.to_dict()``) that a model of
    preset ``own`` can load: every part of ``TRANSFERABLE_PARTS`` whose preset fields are equal in both, and
    the names of those parts. A part whose fields match but whose tensors are missing is skipped (e.g. the image
    encoder of a LiDAR-only checkpoint)."""
    mine = own.to_dict()
    weights: dict[str, torch.Tensor] = {}
    parts = []
    for part, fields in TRANSFERABLE_PARTS.items():
        if any(mine.get(f) != other.get(f) for f in fields):
            continue
        found = {k: v for k, v in state.items() if k.startswith(part + ".")}
        if found:
            weights.update(found)
            parts.append(part)
    return weights, tuple(parts)


def save_weights(path: str | os.PathLike, preset: Preset, model: StreamDetector, half: bool = False,
                 meta: dict[str, Any] | None = None) -> None:  # fmt: skip
    state = {k: (v.half() if half and v.is_floating_point() else v).clone() for k, v in model.state_dict().items()}
    obj: dict[str, Any] = {"format": WEIGHTS_FORMAT, "preset": preset.to_dict(), "model": state}
    if meta is not None:
        obj["meta"] = meta
    save_atomic(obj, path)


def load_weights(path: str | os.PathLike) -> tuple[StreamDetector, Preset]:
    """A detector (eval mode) and its preset from a training checkpoint or shipped weights; float16 tensors are
    cast back to the model's own dtypes."""
    obj = load_checkpoint(path)
    try:
        preset = Preset.from_dict(obj["preset"])
    except ValueError as e:
        raise ValueError(f"checkpoint {path}: {e}") from None
    # the shapes from a model on the meta device first: a saved preset may ask for terabytes, and the real model
    # is only built once the checkpoint's own tensors (already in memory) are known to fill it exactly
    check_fits(meta_state_dict(preset), obj["model"], path, target=f"its own preset {preset.name!r}")
    model = build_detector(preset)
    own = model.state_dict()
    state = {k: v.to(own[k].dtype) for k, v in obj["model"].items()}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = first_line(e)
        raise ValueError(f"checkpoint {path} does not fit its own preset {preset.name!r}: {first}") from None
    return model.eval(), preset
