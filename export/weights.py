"""The weights an export starts from: a checkpoint, the bundled one for the preset, or fixed-seed initial weights.

Checkpoint format (what ``torch.load(path, weights_only=True)`` must return), either

- ``{"preset": Preset.to_dict(), "model": state_dict, ...}`` (``"state_dict"`` is accepted for ``"model"``), or
- a bare state dict of ``StreamDetector``.

A checkpoint that names its preset is checked against the export's preset by name and architecture; any
checkpoint is loaded with ``strict=True``, so one from another preset fails on missing keys or shapes either way.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from streamdet.models.detector import StreamDetector, build_detector
from streamdet.models.presets import LifterConfig, Preset
from streamdet.models.torch_files import check_fits, check_torch_zip, read_torch_file

DEFAULT_SEED = 0
SHIPPED_MAX_BYTES = 20 * 1024 * 1024  # issue 19: a bundled checkpoint (models/weights/*.pt) stays under 20 MB


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not fit the preset; the message is one line."""


@dataclass(frozen=True)
class WeightsSource:
    checkpoint: str | None  # path actually loaded, None for fixed-seed weights
    checkpoint_sha256: str | None
    seed: int | None  # torch seed of the initial weights, None when a checkpoint was loaded

    def describe(self) -> str:
        if self.checkpoint is None:
            return f"fixed-seed initial weights (torch seed {self.seed}; untrained; heatmap logits spread, centre offsets zero)"
        return f"checkpoint {self.checkpoint}"


def bundled_checkpoint(preset_name: str, folder: str | os.PathLike | None = None) -> Path | None:
    """The shipped fused checkpoint of a preset: the first ``models/weights/*.pt`` (by file name) whose saved
    preset has this name and uses the cameras. Files are named by role, not by preset (``small.pt`` is the shipped
    fused model whatever its preset), and a LiDAR-only baseline beside it (``small_lidar_only.pt``) is never a
    default. None when no bundled file fits: the export then uses fixed-seed weights and says so. ``folder``: another
    folder to search (tests)."""
    folder = Path(folder) if folder is not None else Path(str(importlib.resources.files("streamdet.models"))) / "weights"
    for path in sorted(folder.glob("*.pt")):
        saved = checkpoint_preset(path)
        if saved is not None and saved.get("name") == preset_name and saved.get("use_image", True) is not False:
            return path
    return None


def checkpoint_preset(checkpoint: str | os.PathLike | None) -> dict | None:
    """The preset dict a checkpoint saved; None without a checkpoint, without a preset in it, or when it cannot be
    read (``load_detector`` then says why)."""
    if checkpoint is None or not Path(checkpoint).is_file():
        return None
    try:
        check_torch_zip(checkpoint)
    except ValueError:  # a zip that would inflate past its size: reported by load_detector
        return None
    obj = None
    for mmap in (True, False):  # mmap reads no tensor data, but only the zip format (torch >= 1.6) allows it
        try:
            obj = torch.load(Path(checkpoint), map_location="cpu", weights_only=True, mmap=mmap)
            break
        except Exception:  # any unreadable file: reported by load_detector with its reason
            continue
    saved = obj.get("preset") if isinstance(obj, dict) else None
    return saved if isinstance(saved, dict) else None


def checkpoint_use_image(checkpoint: str | os.PathLike | None) -> bool | None:
    """The ``use_image`` of the preset a checkpoint names; None when ``checkpoint_preset`` has none."""
    saved = checkpoint_preset(checkpoint)
    use_image = saved.get("use_image") if saved is not None else None
    return use_image if isinstance(use_image, bool) else None


def checkpoint_slice_crop(checkpoint: str | os.PathLike | None) -> bool:
    """The ``slice_crop`` of the preset a checkpoint names (absent: True, the quadrant crop every preset has)."""
    saved = checkpoint_preset(checkpoint)
    return saved.get("slice_crop", True) is not False if saved is not None else True


def checkpoint_lifter(checkpoint: str | os.PathLike | None) -> LifterConfig | None:
    """The lifter settings (models/presets.py LifterConfig) of the preset a checkpoint names: its form, residual
    and LUT heights per voxel, which presets changed after checkpoints were trained. A field absent in the saved
    preset has the value it had before the field existed (the dataclass default: "volume", "conv", one height).
    None when ``checkpoint_preset`` has none or its lifter is malformed (``load_detector`` then says why)."""
    saved = checkpoint_preset(checkpoint)
    lifter = saved.get("lifter") if saved is not None else None
    if not isinstance(lifter, dict):
        return None
    try:
        return LifterConfig(**lifter)
    except (TypeError, ValueError):
        return None


def load_detector(preset: Preset, checkpoint: str | os.PathLike | None, seed: int = DEFAULT_SEED) -> tuple[StreamDetector, WeightsSource]:
    """The detector in eval mode with its weights, and where they came from."""
    from streamdet.runtime_ort.manifest import sha256_file

    if checkpoint is None:
        torch.manual_seed(seed)
        det = build_detector(preset)
        _condition_untrained_head(det)
        return det.eval(), WeightsSource(None, None, seed)
    path = Path(checkpoint)
    try:  # weights_only, the zip checked before anything is inflated (models/torch_files.py)
        obj = read_torch_file(path)
    except ValueError as e:
        raise CheckpointError(str(e)) from None
    state = _state_dict(obj, path)
    if isinstance(obj, dict) and isinstance(obj.get("preset"), dict):
        _check_preset(obj["preset"], preset, path)
    det = build_detector(preset)
    try:  # keys and shapes, then integer-cast or non-finite weights: shapes fit, the values are no model
        check_fits(det.state_dict(), state, path, target=f"preset {preset.name!r}")
    except ValueError as e:
        hint = "; was it trained with another preset?" if "does not fit" in str(e) else ""
        raise CheckpointError(f"{e}{hint}") from None
    det.load_state_dict(state, strict=True)
    return det.eval(), WeightsSource(str(path), sha256_file(path), None)


def _condition_untrained_head(det: StreamDetector) -> None:
    """Condition the untrained head so the parity checks compare something (trained checkpoints load as they are).

    - Heatmap output convs redrawn N(0, 0.5), prior bias kept. At initialisation CenterPoint's heatmap is flat at
      the prior sigmoid(-2.19) ~ 0.1: every top-K score lies within ~1e-3 of it, so a tolerance "of the output's
      range" means nothing. Spread logits cover more of (0, 1) around the prior, as a trained model's do.
    - Centre-offset (reg) output convs zeroed: untrained offsets throw box centres cells away from their peak, so
      a peak that moves to the neighbouring cell on a near-tie (see parity.py) could not be told from a wrong box.
      With zero offsets every box sits at its cell's centre.
    """
    with torch.no_grad():
        for task in det.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
            task.branches["reg"][-1].weight.zero_()
            task.branches["reg"][-1].bias.zero_()


def _state_dict(obj: object, path: Path) -> dict[str, torch.Tensor]:
    if isinstance(obj, dict) and any(k in obj for k in ("model", "state_dict")):
        obj = obj.get("model", obj.get("state_dict"))
    if not isinstance(obj, dict) or not obj or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
        raise CheckpointError(
            f"checkpoint {path} holds no state dict (expected {{'model': state_dict, 'preset': ...}} or a bare state dict)"
        )
    return obj


def _check_preset(saved: dict, preset: Preset, path: Path) -> None:
    """The checkpoint's preset must be the export's, up to the image size and the post-processing settings,
    which change neither the weights nor their shapes."""
    name = saved.get("name")
    if name != preset.name:
        raise CheckpointError(f"checkpoint {path} was trained with preset {name!r}, not {preset.name!r}")
    try:
        saved_preset = Preset.from_dict(saved)
    except ValueError as e:
        raise CheckpointError(f"checkpoint {path} has an unreadable preset: {e}") from None
    same = dataclasses.replace(saved_preset, image=dataclasses.replace(saved_preset.image, width_px=preset.image.width_px,
                                                                        height_px=preset.image.height_px), post=preset.post)
    if same != preset:
        diff = [f.name for f in dataclasses.fields(Preset) if getattr(same, f.name) != getattr(preset, f.name)]
        raise CheckpointError(f"checkpoint {path} has preset {name!r} with other settings than this one (fields: {', '.join(diff)})")
