"""Image pretraining on the synthetic world's per-pixel masks: the detector's image encoder + a segmentation head.

The analogue of the paper's pretrained backbone (issue 19). Every camera image of the train split, with its
``<image>.mask.npz`` (``data/synth_masks.py``: ``class_id`` per pixel, 255 = no annotated object), is a training
example; labels are 0 = background and 1 + class index. A batch mixes images of different samples, so the
backbone's BatchNorm (if the preset's is "batch" or "frozen_batch") sees varied statistics here and can be
frozen afterwards.

Outputs in ``out_dir``: ``last.pt`` (resumable: model, optimizer, step), ``encoder.pt`` (the image encoder's state
dict), ``detector_init.pt`` (a whole detector of the preset, freshly initialised with the seed, image encoder
from here: ``streamdet-train --init`` takes it), ``metrics.jsonl`` (loss and val mIoU), ``config.json``.

Evaluation (``evaluate_miou``): per object class, IoU = TP / (TP + FP + FN) over the val images' pixels, counting
only objects whose box centre lies within ``range_m`` of the LiDAR (pixels of farther objects are ignored, neither
right nor wrong); mIoU averages the classes present in those labels.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.calibration.camera import CalibrationError
from streamdet.calibration.lut import check_rig_fits
from streamdet.core.classes import CLASS_NAMES, NUM_CLASSES
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import load_image
from streamdet.data.splits import split_sample_tokens
from streamdet.data.synth_masks import MASK_NONE, mask_path, read_mask  # noqa: F401 (read_mask re-exported)
from streamdet.models.detector import build_detector
from streamdet.models.image_encoder import ImageEncoder
from streamdet.models.presets import Preset, get_preset
from streamdet.models.seg_head import ImageSegmenter
from streamdet.core.errors import first_line
from streamdet.core.file_output import write_text_atomic
from streamdet.core.json_input import short_repr
from streamdet.progress import counted
from streamdet.training.checkpoint import (  # noqa: F401 (load_encoder_weights re-exported)
    TRAIN_FORMAT, WEIGHTS_FORMAT, check_fits, check_state_dict, load_encoder_weights, read_torch_file, save_atomic, save_weights)
from streamdet.training.run_dir import (
    check_out_dir, discard_unstarted_run, missing_folders, open_run_log, remove_stale_temps, trim_run_log)
from streamdet.training.train_config import check_device, check_lr, check_max_minutes, check_seed, show_option_value, values_differ
from streamdet.training.interrupts import InterruptedMidStep, sigint_deferred
from streamdet.training.trainer import check_optimizer_state, check_weights_finite, init_head_outputs

NUM_LABELS = NUM_CLASSES + 1  # 0 = background
IGNORE = 255
# What a streamdet-train-image run leaves in --out: a new run there without --resume would replace (or append to) it.
PRETRAIN_RUN_FILES = ("last.pt", "encoder.pt", "detector_init.pt", "metrics.jsonl", "result.json")


@dataclass(frozen=True)
class PretrainConfig:
    preset: str = "small"
    steps: int = 2000  # optimizer steps of the cosine schedule
    batch_size: int = 8  # images per step, drawn from all cameras of all train samples
    lr: float = 2e-3  # peak AdamW learning rate
    weight_decay: float = 1e-4
    warmup_steps: int = 50  # linear warm-up before the cosine decay
    max_background_weight: float = 1.0  # CE weight of background; objects get their inverse sqrt frequency
    max_class_weight: float = 20.0  # cap on an object class's CE weight
    range_m: float = 30.0  # evaluation: objects within this distance (m) of the LiDAR
    eval_every: int = 250  # steps between val mIoU evaluations
    checkpoint_every: int = 100  # steps between rewrites of last.pt
    seed: int = 0
    max_minutes: float | None = None  # stop with a checkpoint after this much wall time (resume continues)
    # Stop with a checkpoint once this many steps of the schedule are done (resume continues): a session cut that,
    # unlike max_minutes, lands on the same step on every machine, so a cut schedule can be repeated exactly.
    stop_at_step: int | None = None

    def __post_init__(self) -> None:
        get_preset(self.preset)
        for name in ("steps", "batch_size", "eval_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"PretrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.stop_at_step is not None and (isinstance(self.stop_at_step, bool) or not isinstance(self.stop_at_step, int)
                                              or self.stop_at_step < 1):
            raise ValueError(f"PretrainConfig.stop_at_step must be None or a positive integer, got {self.stop_at_step!r}")
        # a cut past the schedule's end never happens: the run would silently go to the end instead
        if self.stop_at_step is not None and self.stop_at_step > self.steps:
            raise ValueError(f"PretrainConfig.stop_at_step {self.stop_at_step} is past the end of the {self.steps}-step "
                             "schedule: give at most steps")  # fmt: skip
        # lr finite: AdamW with lr inf turns every weight NaN at the first step (range_m inf is "every object")
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"PretrainConfig.lr must be a finite number > 0, got {self.lr!r}")
        check_lr(self.lr, "PretrainConfig.lr")  # and at most MAX_LR, streamdet-train's bound
        check_seed(self.seed, "PretrainConfig.seed")
        if not self.range_m > 0:
            raise ValueError(f"PretrainConfig.range_m must be > 0, got {self.range_m!r}")
        check_max_minutes(self.max_minutes, "PretrainConfig.max_minutes")


def pretrain_preset(preset: Preset) -> Preset:
    """The encoder's config while pretraining: a frozen BatchNorm learns its statistics here (as plain BatchNorm)."""
    if preset.image.norm != "frozen_batch":
        return preset
    return dataclasses.replace(preset, image=dataclasses.replace(preset.image, norm="batch"))


@dataclass(frozen=True, eq=False)
class MaskedImages:
    """Images (N, H, W, 3) uint8, training labels (N, H, W) uint8 (0 background, 1 + class), and evaluation labels
    (the same, IGNORE on objects beyond the range)."""

    images: np.ndarray
    labels: np.ndarray
    eval_labels: np.ndarray
    tokens: tuple[str, ...] = ()  # the samples the images are of, in order (a resume checks it trains on the same)

    def __len__(self) -> int:
        return len(self.images)


def load_masked_images(root: str | Path, split: str | None, size: tuple[int, int], range_m: float,
                       version: str = DEFAULT_TABLE_VERSION, max_samples: int | None = None,
                       progress: Callable[[int, int], None] | None = None) -> MaskedImages:  # fmt: skip
    """Every camera image of the split's samples at ``size`` (W, H), with its labels; a missing mask is an error."""
    reader = NuScenesReader(root, version)
    tokens = split_sample_tokens(reader, root, split)[:max_samples]
    if not tokens:
        raise ValueError(f"{root}: the {split or 'whole'} split holds no sample")
    images, labels, eval_labels = [], [], []
    for i, token in enumerate(tokens):
        sample = reader.get(token)
        try:  # the rule of streamdet-train and the runtime: images resized to another aspect come out distorted
            check_rig_fits(sample.rig, sample.rig.names, *size)
        except CalibrationError as e:
            raise ValueError(f"dataset {root}, sample {token}: its cameras do not fit the {size[0]}x{size[1]} images of "
                             f"the preset ({e})") from None  # fmt: skip
        dist = {t: float(np.hypot(*b[:2])) for t, b in zip(sample.instance_tokens, sample.gt_boxes)}
        for name in sample.rig.names:
            path = Path(sample.image_paths[name])
            mask = mask_path(path)
            if not mask.is_file():
                if mask.exists():  # a FIFO would block the zip reader
                    raise ValueError(f"mask {mask} is not a regular file (a FIFO, a device or a folder?)")
                raise FileNotFoundError(f"{mask} is missing: image pretraining needs the world's masks (world version 2)")
            cam = sample.rig.camera(name)
            image = load_image(path, size, expected_size=(cam.width, cam.height))  # the mask is at the camera's size
            class_id, instance, ids, inst_tokens = read_mask(mask, cam.height, cam.width)
            label = np.where(class_id == MASK_NONE, 0, class_id.astype(np.int64) + 1).astype(np.uint8)
            far_ids = [int(k) for k, t in zip(ids, inst_tokens) if dist.get(str(t), math.inf) >= range_m]
            far = np.isin(instance, far_ids)
            label = cv2.resize(label, size, interpolation=cv2.INTER_NEAREST)
            far = cv2.resize(far.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
            images.append(image)
            labels.append(label)
            eval_labels.append(np.where(far, IGNORE, label).astype(np.uint8))
        if progress is not None:
            progress(i + 1, len(tokens))
    return MaskedImages(np.stack(images), np.stack(labels), np.stack(eval_labels), tuple(tokens))


def class_weights(labels: np.ndarray, config: PretrainConfig) -> torch.Tensor:
    """(NUM_LABELS,) CE weights: background ``max_background_weight``, objects 1 / sqrt(their share of the most
    frequent object class), capped; an absent class gets the cap (it cannot matter)."""
    counts = np.bincount(labels.ravel(), minlength=NUM_LABELS).astype(np.float64)
    objects = counts[1:]
    top = objects.max() if objects.max() > 0 else 1.0
    w = np.where(objects > 0, np.sqrt(top / np.maximum(objects, 1.0)), config.max_class_weight)
    return torch.tensor(np.r_[config.max_background_weight, np.minimum(w, config.max_class_weight)], dtype=torch.float32)


def confusion(pred: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(NUM_LABELS, NUM_LABELS) int64 counts [true, predicted] over the pixels whose label is not IGNORE."""
    keep = labels != IGNORE
    idx = labels[keep].astype(np.int64) * NUM_LABELS + pred[keep].astype(np.int64)
    return np.bincount(idx, minlength=NUM_LABELS * NUM_LABELS).reshape(NUM_LABELS, NUM_LABELS)


def miou_from_confusion(conf: np.ndarray) -> dict:
    """Per object class IoU (classes with labelled pixels) and their mean ``mIoU`` (NaN when no class has any)."""
    tp = np.diag(conf).astype(np.float64)
    fp = conf.sum(axis=0) - tp
    fn = conf.sum(axis=1) - tp
    per_class = {}
    for c in range(1, NUM_LABELS):
        if conf[c].sum() > 0:
            per_class[CLASS_NAMES[c - 1]] = float(tp[c] / (tp[c] + fp[c] + fn[c]))
    miou = float(np.mean(list(per_class.values()))) if per_class else math.nan
    return {"mIoU": miou, "per_class": per_class, "pixels": {CLASS_NAMES[c - 1]: int(conf[c].sum()) for c in range(1, NUM_LABELS)}}


@torch.no_grad()
def evaluate_miou(model: ImageSegmenter, data: MaskedImages, batch_size: int = 8, device: str = "cpu") -> dict:
    """Val mIoU of the object classes within range (module doc)."""
    model.eval()
    conf = np.zeros((NUM_LABELS, NUM_LABELS), dtype=np.int64)
    for i in range(0, len(data), batch_size):
        images = torch.from_numpy(data.images[i : i + batch_size]).to(device)
        pred = model(images).argmax(dim=1).cpu().numpy()  # (B, H, W)
        conf += confusion(pred, data.eval_labels[i : i + batch_size])
    return miou_from_confusion(conf)


def build_segmenter(preset: Preset) -> ImageSegmenter:
    if not preset.use_image:
        raise ValueError(f"preset {preset.name!r} has use_image=False: there is no image encoder to pretrain")
    cfg = pretrain_preset(preset)
    return ImageSegmenter(ImageEncoder(cfg.image, cfg.channels), NUM_LABELS, cfg.channels)


def lr_at(step: int, config: PretrainConfig) -> float:
    """Linear warm-up, then cosine decay to 1 % of the peak at ``config.steps``."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    t = min(1.0, (step - config.warmup_steps) / max(1, config.steps - config.warmup_steps))
    return config.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * t)))


def batch_indices(step: int, n: int, config: PretrainConfig) -> np.ndarray:
    """The images of ``step``: a pure function of (seed, step), so a resumed run draws what the first would have."""
    return np.random.default_rng([config.seed, step]).choice(n, size=min(config.batch_size, n), replace=False)


def write_detector_init(path: Path, preset: Preset, segmenter: ImageSegmenter, seed: int) -> None:
    """A detector of ``preset`` initialised as streamdet-train does (seed, head prior), encoder from ``segmenter``."""
    torch.manual_seed(seed)
    detector = build_detector(preset)
    init_head_outputs(detector)
    detector.image_encoder.load_state_dict(segmenter.encoder.state_dict(), strict=True)
    save_weights(path, preset, detector, meta={"image_pretrain": str(path.parent)})


# What a resumed streamdet-train-image run must keep of its PretrainConfig, by the option that sets it: the cosine
# schedule (steps, lr, warm-up), the batches drawn from (seed, step) and their size, the loss's class weights, and
# what the val mIoU in metrics.jsonl means (--range). --eval-every, --checkpoint-every, --max-minutes and
# --stop-at-step may change: they say when to evaluate, save and stop, not what is trained (a --stop-at-step at or
# before the resumed step is refused in _check_resume: it would stop at once). Every other field is compared, named
# PretrainConfig.<field>.
PRETRAIN_RESUME_OPTIONS = {"preset": "--preset", "steps": "--steps", "batch_size": "--batch-size", "lr": "--lr",
                           "range_m": "--range", "seed": "--seed"}  # fmt: skip
PRETRAIN_RESUME_MAY_CHANGE = ("eval_every", "checkpoint_every", "max_minutes", "stop_at_step")


def data_record(data: MaskedImages) -> dict:
    """What a last.pt records of its train images: their count and a digest of their samples' tokens in order. The
    batches are drawn by index from (seed, step) and the class weights from the labels, so a resume on other images
    (another --data or --max-samples) would continue a run it never was."""
    return {"images": len(data), "tokens_sha256": hashlib.sha256("\n".join(data.tokens).encode()).hexdigest()}


def _check_resume(state: object, resume: str | Path, config: PretrainConfig) -> None:
    """ValueError naming ``resume`` unless it is a streamdet-train-image last.pt of ``config.preset``, run with the
    same settings (``PRETRAIN_RESUME_OPTIONS``) and not yet at ``config.steps``; a streamdet-train checkpoint (same
    keys model / optimizer / step, same preset names) is named as one. Before the images are read."""
    if isinstance(state, dict) and (state.get("format") in (TRAIN_FORMAT, WEIGHTS_FORMAT) or "preset" in state or "scheduler" in state):
        raise ValueError(f"--resume {resume} is a streamdet-train checkpoint (format {state.get('format')!r}: a detector's "
                         f"training state or weights), not a streamdet-train-image last.pt; streamdet-train --resume or "
                         f"--init takes it")  # fmt: skip
    if not isinstance(state, dict) or not {"model", "optimizer", "step"} <= state.keys():
        raise ValueError(f"--resume {resume} is not a streamdet-train-image last.pt (a dict with model, optimizer, step)")
    if not isinstance(state.get("config"), dict) or state["config"].get("preset") != config.preset:
        was = state["config"].get("preset") if isinstance(state.get("config"), dict) else None
        raise ValueError(f"--resume {resume} was pretrained for preset {was!r}, not {config.preset!r}")
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise ValueError(f"--resume {resume}: 'step' must be an integer >= 0, got {step!r}")
    if not isinstance(state["optimizer"], dict):
        raise ValueError(f"--resume {resume}: 'optimizer' is a {type(state['optimizer']).__name__}, not a state dict")
    was, now = state["config"], dataclasses.asdict(config)
    changes = [(PRETRAIN_RESUME_OPTIONS.get(k, f"PretrainConfig.{k}"), was.get(k), v) for k, v in now.items()
               if k not in PRETRAIN_RESUME_MAY_CHANGE and (k not in was or values_differ(was[k], v))]  # fmt: skip
    if changes:
        # another --steps once marked a run cut at step 6 of 500 "finished" under --steps 3, or bent its cosine
        had = ", ".join(f"{option} {show_option_value(old)}" for option, old, _ in changes)
        given = ", ".join(f"{option} {show_option_value(new)}" for option, _, new in changes)
        raise ValueError(f"--resume {resume} was pretrained with {had}; given {given}: a resumed run continues with its "
                         "own schedule and batches; give the same again, or start a new run")  # fmt: skip
    if step >= config.steps:
        raise ValueError(f"--resume {resume} is at step {step}, {'the end' if step == config.steps else 'past the end'} of "
                         f"its {config.steps}-step schedule: nothing left to train")  # fmt: skip
    if config.stop_at_step is not None and config.stop_at_step <= step:
        raise ValueError(f"--stop-at-step {config.stop_at_step}: --resume {resume} is already at step {step}; give a "
                         f"later step (up to {config.steps})")  # fmt: skip


def _check_resume_fits(state: dict, resume: str | Path, config: PretrainConfig, model: ImageSegmenter,
                       train_data: MaskedImages) -> None:  # fmt: skip
    """ValueError naming ``resume`` unless its weights fit ``model`` and it was trained on ``train_data``'s samples
    (a last.pt from before the record: not checked)."""
    weights = check_state_dict(state["model"], resume, "--resume checkpoint")
    check_fits(model.state_dict(), weights, resume, "--resume checkpoint", f"the image segmenter of preset {config.preset!r}")
    data, here = state.get("data"), data_record(train_data)
    if data is not None and data != here:
        count = data.get("images") if isinstance(data, dict) else None
        raise ValueError(f"--resume {resume} was pretrained on other train images ({short_repr(count)} of them) than "
                         f"--data gives now ({here['images']}): a resumed run continues over its own images; give its "
                         "--data and --max-samples, or start a new run")  # fmt: skip


def pretrain(config: PretrainConfig, data_dir: str | Path, out_dir: str | Path, version: str = DEFAULT_TABLE_VERSION,
             resume: str | Path | None = None, device: str = "cpu", echo: Callable[[str], None] = print,
             max_samples: int | None = None, splits: tuple[str | None, str | None] = ("train", "val"),
             overwrite: bool = False, report: Callable[[str], None] | None = None) -> dict:  # fmt: skip
    """Train the segmenter; returns the last evaluation. Resumable from ``out_dir/last.pt`` with ``resume``.

    ``splits``: the (train, val) splits of ``data_dir/splits.json``; None = every sample. An ``out_dir`` holding a
    run (``PRETRAIN_RUN_FILES``) is refused unless ``resume`` continues it or ``overwrite`` replaces it; one holding
    anything but such a run is refused (``trainer.check_out_contents``). A new run that fails before its first logged
    record leaves nothing in ``out_dir``. A NaN or inf loss or weight stops with a ValueError. A Ctrl-C
    (KeyboardInterrupt) writes the checkpoint of the last step done, then goes on as a KeyboardInterrupt. ``echo``
    takes the progress lines and notes, ``report`` (default: ``echo``) the two lines that describe the run: its
    images, and how it ended.
    """
    check_device(device)  # before --out is made: a bad device is refused, not found when the model moves there
    made = missing_folders(out_dir)
    replaced = check_out_dir(out_dir, PRETRAIN_RUN_FILES, resume, overwrite, config_key="pretrain")
    for path in remove_stale_temps(out_dir, PRETRAIN_RUN_FILES):
        echo(f"removed {path}: the temp file of a save that was killed mid-write")
    try:
        return _pretrain_into(config, data_dir, Path(out_dir), version, resume, device, echo, max_samples, splits, replaced,
                              echo if report is None else report)  # fmt: skip
    except BaseException:
        if resume is None or made:  # a failed resume removes only a folder it made itself (its files are all its own)
            discard_unstarted_run(out_dir, PRETRAIN_RUN_FILES, made)
        raise


def _pretrain_into(config: PretrainConfig, data_dir: str | Path, out: Path, version: str, resume: str | Path | None,
                   device: str, echo: Callable[[str], None], max_samples: int | None,
                   splits: tuple[str | None, str | None], replaced: list[Path], report: Callable[[str], None]) -> dict:  # fmt: skip
    """``pretrain`` once ``out`` is checked (``replaced``: the files of an earlier run that --overwrite removes)."""
    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    preset = get_preset(config.preset)
    state = None
    if resume is not None:  # before the images are read: a resume its own config refuses costs no minutes
        state = read_torch_file(resume, "--resume checkpoint", map_location=device)
        _check_resume(state, resume, config)
    size = (preset.image.width_px, preset.image.height_px)
    echo(f"loading {data_dir} train / val images at {size[0]}x{size[1]} with their masks")
    with counted("  train images", echo) as progress:
        train_data = load_masked_images(data_dir, splits[0], size, config.range_m, version, max_samples, progress)
    if config.batch_size > len(train_data):  # streamdet-train's rule: a batch is never silently made smaller
        raise ValueError(f"batch_size {config.batch_size} (--batch-size) is more than the {len(train_data)} train images "
                         f"of {data_dir}: give at most {len(train_data)}")  # fmt: skip
    with counted("  val images", echo) as progress:
        val_data = load_masked_images(data_dir, splits[1], size, config.range_m, version, max_samples, progress)
    report(f"{len(train_data)} train images, {len(val_data)} val images")  # with the closing line, the run's report
    torch.manual_seed(config.seed)
    model = build_segmenter(preset).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    weights = class_weights(train_data.labels, config).to(device)
    step = 0
    if state is not None:
        _check_resume_fits(state, resume, config, model, train_data)
        model.load_state_dict(state["model"])
        try:
            optimizer.load_state_dict(state["optimizer"])
        except (ValueError, KeyError, TypeError, AttributeError, IndexError, RuntimeError) as e:
            raise ValueError(f"--resume {resume}: its optimizer state does not fit this run's optimizer: {first_line(e)}") from None
        check_optimizer_state(optimizer, resume)  # moments of other shapes failed at the first step, with a traceback
        step = state["step"]
        echo(f"resumed {resume} at step {step}")
    for path in replaced:  # overwrite: none of the old run's files may outlive it beside the new run's
        path.unlink(missing_ok=True)
    if state is not None:  # the records a killed run logged after its checkpoint: their steps are trained again
        dropped = trim_run_log(out / "metrics.jsonl", step)
        if dropped:
            echo(f"metrics.jsonl: dropped {dropped} record(s) logged after step {step} (after the checkpoint resumed: "
                 "those steps are trained again)")  # fmt: skip
    write_text_atomic(out / "config.json", json.dumps({"pretrain": dataclasses.asdict(config), "data": str(data_dir),
                                                       "preset": preset.to_dict()}, indent=1) + "\n")  # fmt: skip
    # a resumed run continues its log; never through a symlink nor into a FIFO (check_out_dir refused them before)
    metrics = open_run_log(out / "metrics.jsonl", append=resume is not None)
    last_eval: dict = {}

    def checkpoint() -> None:
        check_weights_finite(model, step)
        save_atomic({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                      "config": dataclasses.asdict(config), "data": data_record(train_data)}, out / "last.pt")  # fmt: skip
        save_atomic(model.encoder.state_dict(), out / "encoder.pt")
        write_detector_init(out / "detector_init.pt", preset, model, config.seed)

    def evaluate() -> dict:
        result = {**evaluate_miou(model, val_data, config.batch_size, device), "step": step}
        metrics.write(json.dumps({"step": step, "val_mIoU": result["mIoU"], "val_IoU": result["per_class"],
                                  "minutes": (time.monotonic() - t0) / 60}) + "\n")  # fmt: skip
        metrics.flush()
        echo(f"step {step}: val mIoU {result['mIoU']:.3f} " + " ".join(f"{c} {v:.2f}" for c, v in result["per_class"].items()))
        model.train()
        return result

    model.train()
    stopped_early = False
    start = step
    last_loss, logged = math.nan, step  # the loss of the last step taken, and the last step metrics.jsonl holds
    in_progress = step + 1  # the step under way, for a message when a second Ctrl-C cuts it
    try:
        while step < config.steps:
            if config.max_minutes is not None and time.monotonic() - t0 > 60 * config.max_minutes:
                stopped_early = True
                break
            if config.stop_at_step is not None and step >= config.stop_at_step:
                stopped_early = True
                break
            # a step with its log and checkpoint is whole or not taken: a Ctrl-C waits for its end (the forward pass
            # alone moves the BatchNorm statistics; training/interrupts.py)
            in_progress = step + 1  # step counts the steps done, and moves on before the step's log and checkpoint
            with sigint_deferred():
                idx = np.sort(batch_indices(step, len(train_data), config))
                images = torch.from_numpy(train_data.images[idx]).to(device)  # (B, H, W, 3)
                labels = torch.from_numpy(train_data.labels[idx]).long().to(device)  # (B, H, W)
                if np.random.default_rng([config.seed, step, 1]).random() < 0.5:  # horizontal flip: the world has no handedness
                    images, labels = images.flip(2), labels.flip(2)
                for group in optimizer.param_groups:
                    group["lr"] = lr_at(step, config)
                loss = F.cross_entropy(model(images), labels, weight=weights)
                if not bool(torch.isfinite(loss.detach())):  # before the update: the weights stay the last finite step's
                    if step > logged:  # the last finite step's loss, which the log would not hold otherwise
                        metrics.write(json.dumps({"step": step, "loss": last_loss, "lr": lr_at(step - 1, config)}) + "\n")
                    metrics.close()
                    raise ValueError(f"training diverged: the loss is {float(loss.detach())} at step {step + 1} (lr "
                                     f"{lr_at(step, config):.3g}); stopped there, nothing written for it (lower --lr)")  # fmt: skip
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
                optimizer.step()
                step += 1
                last_loss = float(loss.detach())
                if step % 10 == 0 or step == 1:
                    metrics.write(json.dumps({"step": step, "loss": last_loss, "lr": lr_at(step - 1, config)}) + "\n")
                    metrics.flush()
                    logged = step
                    echo(f"step {step}/{config.steps} loss {last_loss:.4f} ({(time.monotonic() - t0) / 60:.1f} min)")
                if step % config.checkpoint_every == 0:
                    checkpoint()
            if step % config.eval_every == 0:  # outside: a Ctrl-C need not wait for an evaluation of the val images
                last_eval = evaluate()
    except InterruptedMidStep:
        metrics.close()
        echo(f"interrupted again in the middle of step {in_progress}: nothing written for it (the last checkpoint stays "
             "as it was)")  # fmt: skip
        raise
    except KeyboardInterrupt:
        # a Ctrl-C: the last step done is saved, so --resume loses nothing (before this invocation's first step there
        # is nothing new: a new run then leaves nothing); a second one ends these saves, each atomic (the previous
        # file stays whole)
        metrics.close()
        if step == start:
            raise
        checkpoint()
        echo(f"interrupted after step {step}: wrote {out / 'last.pt'}, encoder.pt and detector_init.pt of that step; "
             f"--resume {out / 'last.pt'} continues from there")  # fmt: skip
        raise
    checkpoint()
    if not last_eval or last_eval.get("step") != step:
        last_eval = evaluate()
    last_eval = {**last_eval, "step": step, "finished": not stopped_early}
    write_text_atomic(out / "result.json", json.dumps(last_eval, indent=1) + "\n")
    metrics.close()
    report(f"{'stopped (--max-minutes / --stop-at-step)' if stopped_early else 'finished'} at step {step}: val mIoU "
           f"{last_eval['mIoU']:.3f}; wrote {out / 'encoder.pt'} and {out / 'detector_init.pt'}")  # fmt: skip
    return last_eval
