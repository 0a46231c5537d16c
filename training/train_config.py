"""What ``streamdet-train`` is asked to do: ``TrainConfig`` (every field's default and unit beside it) and the checks
of the values both training tools share (``--max-minutes``, ``--device``)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import torch

from streamdet.core.json_input import short_repr
from streamdet.models.presets import Preset, get_preset
from streamdet.training.camera_dropout import check_camera_dropout
from streamdet.training.dataset import DataConfig
from streamdet.training.distill import DistillConfig
from streamdet.training.losses import LossConfig

AMP_MODES = ("auto", "off", "bf16", "fp16")
# The longest --max-minutes (7 days): a budget is a finite wall time; inf would run the one-cycle schedule forever
# (its lr never leaves the warm-up start), and a longer run is a --steps plan resumed across sessions.
MAX_MINUTES = 7 * 24 * 60
# A hundred million optimizer steps: far past any run here (10**21 only printed an eta of 9e17 min). Both training
# tools bound --steps by it.
MAX_STEPS = 10**8
# The largest --seed: torch's generators take at most 2**64 - 1, and the data order seeds one with seed + epoch (the
# DistributedSampler), so a seed up to 2**63 - 1 leaves every epoch count room; 2**64 failed with "Overflow when
# unpacking long long" after the dataset was read. streamdet-export's bound (export/cli.py MAX_SEED), copied.
MAX_SEED = 2**63 - 1
# The largest peak learning rate of both training tools: AdamW moves each weight by about lr per step, so past 10 the
# first step throws every weight far outside its scale (the run then stops as diverged); past float32's range
# (--lr 1e41) torch failed with a traceback when the optimizer was built.
MAX_LR = 10.0
# The device types training runs on; torch.device also parses meta, xpu, ipu ..., where the first step failed with a
# traceback after the run's files were written.
DEVICE_TYPES = ("cpu", "cuda", "mps")


@dataclass(frozen=True)
class TrainConfig:
    preset: str = "small"
    use_image: bool = True  # False: the LiDAR-only streaming baseline (no image lane at all)
    # False: that baseline without the quadrant crop, one map of the whole grid per slice (Preset.slice_crop)
    slice_crop: bool = True
    steps: int | None = None  # optimizer steps of the one-cycle schedule
    epochs: int | None = None  # when steps is None: epochs * steps per epoch; both None: a schedule over max_minutes
    batch_size: int = 1  # samples per process per step; each sample brings its slices (8 maps for n = 8)
    lr: float = 2e-3  # one-cycle peak
    weight_decay: float = 0.01  # AdamW
    grad_clip: float = 35.0  # max global gradient norm (CenterPoint)
    pct_start: float = 0.4  # one-cycle warm-up fraction (CenterPoint)
    div_factor: float = 10.0  # start lr = lr / div_factor
    final_div_factor: float = 1e4  # end lr = start lr / final_div_factor
    amp: str = "auto"  # auto: fp16 autocast on CUDA, off on CPU (bf16 autocast was slower on an AVX2 CPU)
    # Fraction of the schedule trained with the image lane off (a zero image BEV; the runtime, where it has no image,
    # feeds the lift of zero features instead: StreamingDetector.blank_image_bev): the LiDAR lane and the BEV encoder learn first at a fraction of the step cost, the image
    # lane joins for the rest. 0: images from the first step.
    image_warmup: float = 0.0
    # Weight of the image-side class loss beside detection (training/image_class.py: each object's class read
    # linearly from the image BEV at its centre, cross-entropy per object); 0 = off, the CenterPoint loss alone.
    image_class_weight: float = 0.0
    # Probability that a training step drops cameras (training/camera_dropout.py: each sample loses k of its J cameras,
    # k uniform in 1..J, lifted from zero features as the runtime lifts a camera without a frame, the camera lane
    # normalising with its stored statistics); 0 = off, every camera always.
    camera_dropout: float = 0.0
    balanced: bool = False  # class-balanced (CBGS) resampling of the training samples
    workers: int = 0  # DataLoader worker processes (0: load in the training process)
    seed: int = 0
    # With steps or epochs: stop (with a checkpoint) once this much wall time has passed. Alone: the one-cycle
    # schedule runs on wall time and training ends when it is spent (not step-reproducible, see schedule.py).
    max_minutes: float | None = None
    log_every: int = 10  # steps between progress lines / metrics records
    checkpoint_every: int = 200  # steps between last.pt rewrites
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    # Distillation (training/distill.py): a trained detector's weights whose head's responses become soft targets
    # beside the labels (None: off), that loss's weight beside the CenterPoint loss, and its terms.
    teacher: str | None = None
    distill_weight: float = 1.0
    distill: DistillConfig = field(default_factory=DistillConfig)
    # Keep the image encoder and lifter as --init gave them (no gradient, fixed BatchNorm statistics): a new slice
    # net learns to read a trained camera lane; with a teacher of the same camera lane one lift serves both.
    freeze_camera_lane: bool = False

    def __post_init__(self) -> None:
        get_preset(self.preset)  # raises for an unknown name
        if not isinstance(self.slice_crop, bool):
            raise ValueError(f"TrainConfig.slice_crop must be True or False, got {self.slice_crop!r}")
        if self.use_image and not self.slice_crop:
            raise ValueError("training without the quadrant crop (slice_crop=False, --no-crop) is supported for the "
                             "LiDAR-only baseline only: add --no-image")  # fmt: skip
        if self.steps is not None and (isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1):
            raise ValueError(f"TrainConfig.steps must be None or a positive integer, got {self.steps!r}")
        if self.epochs is not None and (isinstance(self.epochs, bool) or not isinstance(self.epochs, int) or self.epochs < 1):
            raise ValueError(f"TrainConfig.epochs must be None or a positive integer, got {self.epochs!r}")
        if self.steps is None and self.epochs is None and self.max_minutes is None:
            raise ValueError("TrainConfig needs steps, epochs or max_minutes to know how long to train")
        for name in ("batch_size", "log_every", "checkpoint_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"TrainConfig.{name} must be a positive integer, got {v!r}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ValueError(f"TrainConfig.workers must be a non-negative integer, got {self.workers!r}")
        for name in ("lr", "grad_clip", "div_factor", "final_div_factor"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"TrainConfig.{name} must be a positive number, got {getattr(self, name)!r}")
        check_lr(self.lr, "TrainConfig.lr")
        check_seed(self.seed, "TrainConfig.seed")
        if not (math.isfinite(self.image_class_weight) and self.image_class_weight >= 0):
            raise ValueError(f"TrainConfig.image_class_weight must be a number >= 0, got {self.image_class_weight!r}")
        if self.image_class_weight > 0 and not self.use_image:
            raise ValueError("the image class loss (image_class_weight > 0) needs the image lane: drop --no-image or the weight")
        check_camera_dropout(self.camera_dropout, "TrainConfig.camera_dropout")
        if self.camera_dropout > 0 and not self.use_image:
            raise ValueError("camera dropout (camera_dropout > 0) needs the image lane: drop --no-image or --camera-dropout")
        if not 0.0 <= self.image_warmup < 1.0:
            raise ValueError(f"TrainConfig.image_warmup must be in [0, 1), got {self.image_warmup!r}")
        # options of the image lane that a LiDAR-only run would ignore (config.json recorded them as if they held)
        if self.image_warmup > 0 and not self.use_image:
            raise ValueError(f"the image warm-up (image_warmup {self.image_warmup!r}) needs the image lane: drop --no-image "
                             "or --image-warmup")  # fmt: skip
        if self.data.camera_mode != "all" and not self.use_image:
            raise ValueError(f"camera_mode {self.data.camera_mode!r} picks the cameras a slice sees, which needs the image "
                             "lane: drop --no-image or --camera-mode")  # fmt: skip
        if not 0.0 < self.pct_start < 1.0:
            raise ValueError(f"TrainConfig.pct_start must be in (0, 1), got {self.pct_start!r}")
        if not self.weight_decay >= 0:
            raise ValueError(f"TrainConfig.weight_decay must be >= 0, got {self.weight_decay!r}")
        if self.amp not in AMP_MODES:
            raise ValueError(f"TrainConfig.amp must be one of {AMP_MODES}, got {self.amp!r}")
        check_max_minutes(self.max_minutes, "TrainConfig.max_minutes")
        if self.teacher is not None and (not isinstance(self.teacher, str) or not self.teacher):
            raise ValueError(f"TrainConfig.teacher must be None or a path, got {self.teacher!r}")
        if not (isinstance(self.distill_weight, (int, float)) and math.isfinite(self.distill_weight) and self.distill_weight >= 0):
            raise ValueError(f"TrainConfig.distill_weight must be a number >= 0, got {self.distill_weight!r}")
        if self.freeze_camera_lane and not self.use_image:
            raise ValueError("freeze_camera_lane needs the image lane: drop --no-image or --freeze-camera-lane")

    def build_preset(self) -> Preset:
        return dataclasses.replace(get_preset(self.preset), use_image=self.use_image, slice_crop=self.slice_crop)

    def to_dict(self) -> dict[str, Any]:
        d = _jsonable(dataclasses.asdict(self))
        # written only when not at their defaults: the config of every run before them stays as it was
        if self.slice_crop:
            del d["slice_crop"]
        if self.image_class_weight == 0:
            del d["image_class_weight"]
        if self.camera_dropout == 0:
            del d["camera_dropout"]
        if self.teacher is None:
            for k in ("teacher", "distill_weight", "distill"):
                del d[k]
        if not self.freeze_camera_lane:
            del d["freeze_camera_lane"]
        return d


def check_lr(value: float, name: str) -> None:
    """ValueError unless ``value`` is a finite learning rate in (0, MAX_LR]."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0 < value <= MAX_LR):
        raise ValueError(f"{name} must be a finite learning rate in (0, {MAX_LR:g}], got {value!r}")


def check_seed(value: int, name: str) -> None:
    """ValueError unless ``value`` is an integer seed in 0..MAX_SEED."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SEED:
        raise ValueError(f"{name} must be an integer in 0..{MAX_SEED}, got {short_repr(value)}")


# What a resumed streamdet-train run must keep of its TrainConfig, by the option that sets it: each changes the data
# order the resume skips ahead in (seed, batch size, balanced, slice counts and subsets), the schedule the optimizer
# state continues (steps, epochs, lr) or what the loss asks of the model (camera mode, warm-up, loss weights).
RESUME_OPTIONS = {
    "preset": "--preset", "use_image": "--no-image", "slice_crop": "--no-crop", "steps": "--steps", "epochs": "--epochs",
    "batch_size": "--batch-size", "lr": "--lr", "seed": "--seed", "balanced": "--balanced",
    "image_warmup": "--image-warmup", "image_class_weight": "--image-class-weight", "distill_weight": "--distill-weight",
    "data.num_slices": "--num-slices", "data.max_slices_per_sample": "--max-slices-per-sample",
    "data.camera_mode": "--camera-mode",
}  # fmt: skip
# What a resume may change, and why that is sound: --max-minutes with --steps/--epochs is this invocation's wall-time
# limit (a run split over sessions gets a new one each time; a schedule over --max-minutes alone is compared);
# --log-every / --checkpoint-every / --workers / --amp change how the run is logged, saved, loaded and computed, not
# its data or schedule; --camera-dropout is an augmentation, allowed but said (trainer._restore); --teacher and
# --freeze-camera-lane have their own check (trainer._check_resume_state). Every other field is compared.
RESUME_MAY_CHANGE = ("max_minutes", "log_every", "checkpoint_every", "workers", "amp", "camera_dropout", "teacher",
                     "freeze_camera_lane")  # fmt: skip


def saved_config_values(was: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's ``config`` (TrainConfig.to_dict: fields at their default may be absent) as every field's value,
    keyed flat ("data.num_slices"): what the run was started with."""
    # the fields' own defaults (steps=1 only makes the instance valid: steps defaults to None)
    defaults = {**_flat(_jsonable(dataclasses.asdict(TrainConfig(steps=1)))), "steps": None}
    return {**defaults, **_flat(was)}


def resume_config_changes(was: dict[str, Any], now: TrainConfig) -> list[tuple[str, Any, Any]]:
    """(option, the run's value, the given value) for every field of ``now`` that differs from ``was`` (a resumed
    checkpoint's ``config``, TrainConfig.to_dict: fields at their default may be absent) and that a resume must keep
    (``RESUME_OPTIONS``; a field no option sets is named TrainConfig.<field>)."""
    old = saved_config_values({"preset": now.preset, **was})  # a config without a preset: not compared on it
    new = _flat(_jsonable(dataclasses.asdict(now)))
    by_time = (old.get("steps"), old.get("epochs")) == (None, None) or (now.steps, now.epochs) == (None, None)
    changes = []
    for key, value in new.items():
        top = key.split(".")[0]
        if top in RESUME_MAY_CHANGE and not (key == "max_minutes" and by_time):  # a time plan's budget is its schedule
            continue
        if key not in old or values_differ(old[key], value):
            changes.append((RESUME_OPTIONS.get(key, "--max-minutes" if key == "max_minutes" else f"TrainConfig.{key}"),
                            old.get(key), value))  # fmt: skip
    return changes


def values_differ(was: Any, now: Any) -> bool:
    """Whether a checkpoint's config value differs from the given one. A checkpoint is input: a tensor or another
    object in its config compares to no option's value (and its ``!=`` may not even give a bool)."""
    try:
        return bool(was != now)
    except Exception:  # noqa: BLE001 (any object a checkpoint may hold: it differs)
        return True


def show_option_value(value: Any) -> str:
    """A config value as the user typed it: 8,32 for slice counts, on / off for a flag, none for a missing value
    (anything else a checkpoint holds: its short repr, one line)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, int):
        return short_repr(value)  # a huge one by its digit count
    if isinstance(value, list) and all(isinstance(v, (int, float, str)) and not isinstance(v, bool) for v in value):
        text = ",".join(short_repr(v, 20) if isinstance(v, str) else short_repr(v) for v in value)
        return text if len(text) <= 60 else text[:57] + "..."
    return " ".join(short_repr(value, 60).split())  # a tensor's repr spans lines: the error stays one


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested dict as {"a.b": value} (the config's data / loss / distill sections)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def check_max_minutes(value: float | None, name: str) -> None:
    """ValueError unless ``value`` is None or a finite number of minutes in (0, MAX_MINUTES]."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0 < value <= MAX_MINUTES):
        raise ValueError(f"{name} must be a finite number of minutes in (0, {MAX_MINUTES}] (7 days), got {value!r}")


def check_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch.device, or a one-line ValueError naming it unless training can run there: cpu, or cuda /
    mps where this machine has them (cuda:N only for an N it has). Called before anything is made in --out."""
    shown = short_repr(device if isinstance(device, str) else str(device), 60)
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"{shown} is not a torch device: give cpu, cuda, cuda:N or mps") from None
    if parsed.type not in DEVICE_TYPES:
        raise ValueError(f"{shown}: training runs on {', '.join(DEVICE_TYPES)}, not on {parsed.type}")
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"{shown}: this machine has no usable CUDA device (torch.cuda.is_available() is False); use cpu")
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(f"{shown}: this machine has {count} CUDA device(s), cuda:0..cuda:{count - 1}")
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{shown}: MPS is not available on this machine; use cpu")
    return parsed


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x
