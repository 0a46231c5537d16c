"""The training loop: AdamW + one-cycle, gradient clipping, optional autocast, checkpoints, resume, metrics log.

One step = one global batch of ``batch_size * world_size`` samples, each bringing its slices (see
``dataset.py``). Under torchrun every process takes its shard from a ``DistributedSampler``; DDP averages the
gradients, ``CrossProcessBatchNorm`` shares batch statistics, and the loss is normalised by the object count of
the global batch and multiplied by the world size, so the update equals that of one process holding the whole
global batch.

Outputs in ``out_dir``: ``last.pt`` (training checkpoint, rewritten every ``checkpoint_every`` steps and at the
end), ``model.pt`` (weights only, for ``streamdet-export --checkpoint``), ``metrics.jsonl`` and ``config.json``.

``metrics.jsonl`` holds one JSON object per logged step, its values over the global batch averaged over the steps
since the previous record: ``step``, ``epoch``, ``loss`` (what the optimizer minimised: ``heatmap + reg_weight * reg``
plus the weighted image class and distillation terms), ``heatmap`` (focal loss per object), ``reg`` (the code-weighted
L1 of the box codes per object, before ``reg_weight``), its parts before their code weights ``loc_xy``, ``z``,
``dim``, ``rot``, ``vel`` (the sum over those codes of the L1 per object), ``image_class`` / ``distill_heatmap`` /
``distill_box`` where those losses run (before their weights), ``lr``, ``samples_per_s`` and ``slices_per_s`` (over
every process), ``elapsed_s`` (training seconds, a resumed run's included), and ``dropped_targets`` in a record whose
steps left target boxes out (more objects in a head map than ``TargetConfig.max_objects``). A resume first drops the
records logged after the checkpoint it continues (their steps are trained again).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler, Subset

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.core.errors import first_line
from streamdet.core.file_output import write_text_atomic
from streamdet.core.json_input import short_repr
from streamdet.models.detector import build_detector
from streamdet.models.presets import Preset
from streamdet.models.torch_files import check_dense, read_torch_file
from streamdet.training.batching import Batch, Collator
from streamdet.training.camera_dropout import draw_camera_keep, drops_cameras, step_generator
from streamdet.training.checkpoint import (
    TRANSFERABLE_PARTS,
    check_checkpoint,
    check_fits,
    check_state_dict,
    is_encoder_state,
    load_checkpoint,
    load_encoder_weights,
    save_training_state,
    save_weights,
    transferable_weights,
)
from streamdet.training.dataset import SliceDataset, SampleStore, build_store, class_balanced_indices
from streamdet.training.distill import Teacher, distill_loss
from streamdet.training.distributed import DistContext, all_reduce_sum, convert_batchnorm, init_distributed, process_device
from streamdet.training.image_class import image_class_loss_sum
from streamdet.training.losses import CenterPointLoss, loss_terms
from streamdet.training.model import TrainingModel
from streamdet.training.schedule import OneCycle
from streamdet.progress import counted
from streamdet.training.interrupts import InterruptedMidStep, sigint_deferred
from streamdet.training.run_dir import (  # noqa: F401 (re-exported: the run-folder rules, for tests and scripts)
    CONFIG_FILE, NOT_A_RUN, RUN_FILES, _same_folder, check_out_contents, check_out_dir, discard_unstarted_run,
    missing_folders, open_run_log, remove_stale_temps, trim_run_log)
from streamdet.training.train_config import (  # noqa: F401 (re-exported)
    AMP_MODES, MAX_LR, MAX_MINUTES, MAX_SEED, MAX_STEPS, TrainConfig, check_device, check_max_minutes,
    resume_config_changes, show_option_value)

HEAD_OUTPUT_INIT_STD = 0.01


def check_weights_finite(module: torch.nn.Module, step: int) -> None:
    """ValueError when a weight or buffer of ``module`` is NaN or inf: a finite loss can still end in such an
    update (an overflowing gradient norm), and a checkpoint of it would only fail later, at export or --init."""
    for name, value in module.state_dict().items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"training diverged: after step {step} the weight {name} holds NaN or inf; nothing was "
                             f"written for it (lower --lr, or resume from an earlier last.pt)")  # fmt: skip


@dataclass(frozen=True)
class TrainResult:
    steps_done: int
    seconds: float
    stopped_early: bool  # max_minutes ran out before the planned steps
    final_loss: float  # the global batch's loss at the last step (summed over processes)
    checkpoint: Path | None  # last.pt (main process only)
    weights: Path | None  # model.pt
    skipped_samples: int = 0  # samples left out of their batch for holding no pillar (Collator: no usable LiDAR point)
    dropped_targets: int = 0  # target boxes beyond TargetConfig.max_objects of their head map (every process's)


def _amp_context(mode: str, device: torch.device):
    if mode == "auto":
        mode = "fp16" if device.type == "cuda" else "off"
    if mode == "off":
        return nullcontext(), False
    dtype = torch.float16 if mode == "fp16" else torch.bfloat16
    return torch.autocast(device_type=device.type, dtype=dtype), mode == "fp16" and device.type == "cuda"


def init_head_outputs(detector, std: float = HEAD_OUTPUT_INIT_STD) -> None:
    """Draw every head branch's output conv from N(0, std), keeping its bias (the heatmap's is the prior).

    The focal-loss paper's rule (RetinaNet, Lin et al. 2017). With the head's kaiming init, the few occupied
    cells of a sparse slice map come out of batch norm as outliers of many sigma, so the first heatmap holds large
    positive logits and the first steps only undo that (a loss orders of magnitude above a trained one, every
    gradient clipped).
    """
    with torch.no_grad():
        for task in detector.slice_net.head.tasks:
            for branch in task.branches.values():
                torch.nn.init.normal_(branch[-1].weight, 0.0, std)


class ResumableSampler(DistributedSampler):
    """``DistributedSampler`` that can start an epoch part-way: ``skip`` leaves out the first indices of this
    process's order (a resume's batches already trained), so they are never read or pillarised. The samples' own
    randomness is drawn from (seed, epoch, index) (``SliceDataset``), so the batches after the cut are the
    uninterrupted run's. ``len`` stays the whole epoch's."""

    skip: int = 0

    def __iter__(self):
        order = super().__iter__()
        for _ in range(self.skip):
            next(order, None)
        return order


def make_loader(dataset: SliceDataset, config: TrainConfig, ctx: DistContext, collate: Collator) -> tuple[DataLoader, DistributedSampler]:
    """Per-process loader over the (optionally class-balanced) sample list; drop_last keeps every step's global
    batch full and the same on every process count."""
    view = list(range(len(dataset)))
    if config.balanced:
        view = class_balanced_indices(dataset.class_sets(), config.seed).tolist()
    source = Subset(dataset, view)
    sampler = ResumableSampler(source, num_replicas=ctx.world_size, rank=ctx.rank, shuffle=True, seed=config.seed, drop_last=True)
    if len(sampler) < config.batch_size:
        raise ValueError(
            f"{len(view)} training samples over {ctx.world_size} process(es) give {len(sampler)} per process, "
            f"fewer than batch_size={config.batch_size}"
        )
    loader = DataLoader(source, batch_size=config.batch_size, sampler=sampler, collate_fn=collate, drop_last=True,
                        num_workers=config.workers, persistent_workers=False)  # fmt: skip
    return loader, sampler


@dataclass(eq=False)
class _TrainRun:
    """What the set-up builds and the loop advances (one process's view of one training run)."""

    config: TrainConfig
    preset: Preset
    out_dir: Path
    device: torch.device
    ctx: DistContext
    say: Callable[[str], None]
    dataset: SliceDataset
    loader: DataLoader
    sampler: ResumableSampler
    detector: Any  # StreamDetector
    model: TrainingModel
    wrapped: torch.nn.Module  # the model, DDP-wrapped under torchrun
    optimizer: torch.optim.Optimizer
    schedule: OneCycle
    plan: str  # the schedule in words
    criterion: CenterPointLoss
    amp: Any  # autocast context (or a null one)
    scaler: torch.amp.GradScaler
    warmup: bool  # the image lane trains only after config.image_warmup of the schedule
    t_start: float
    teacher: Teacher | None = None
    shared_lane: bool = False  # the frozen camera lane is the teacher's: one lift per step serves both
    epoch: int = 0
    epoch_step: int = 0  # batches of `epoch` done
    elapsed_before: float = 0.0  # training seconds of the run this one resumes
    data_dir: str = ""  # --data, as given (for messages)
    skipped_samples: int = 0  # this invocation's samples without a pillar, left out of their batches
    skipped_steps: int = 0  # batches left with no sample at all, no optimizer step taken
    dropped_targets: int = 0  # this process's target boxes beyond the cap of their head map (Batch.num_dropped)

    def checkpoint(self) -> Path | None:
        if not self.ctx.is_main:
            return None
        path = self.out_dir / "last.pt"
        save_training_state(path, preset=self.preset, model=self.detector, optimizer=self.optimizer,
                            scheduler=self.schedule, step=self.schedule.step, epoch=self.epoch,
                            epoch_step=self.epoch_step, config=self.config.to_dict(),
                            image_classifier=self.model.image_classifier, data=data_record(self.dataset.store),
                            scaler=self.scaler.state_dict() if self.scaler.is_enabled() else None)  # fmt: skip
        return path

    def elapsed(self) -> float:
        """Training time so far, the same on every process (the slowest one's)."""
        local = torch.tensor([self.elapsed_before + time.perf_counter() - self.t_start], dtype=torch.float64)
        if self.ctx.initialised and self.ctx.world_size > 1:
            torch.distributed.all_reduce(local, op=torch.distributed.ReduceOp.MAX)
        return float(local)


def _denormals_flushed(fn: Callable) -> Callable:
    """Run ``fn`` with denormals flushed to zero (Adam's second moments of tiny gradients go denormal, and denormal
    arithmetic makes CPU steps many times slower), then give the process its default back: the setting is global,
    and float work after training in the same process (hypothesis' float strategies, a caller's own maths) must not
    inherit it."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        torch.set_flush_denormal(True)
        try:
            return fn(*args, **kwargs)
        finally:
            torch.set_flush_denormal(False)

    return wrapper


@_denormals_flushed
def train(
    config: TrainConfig,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    version: str = DEFAULT_TABLE_VERSION,
    resume: str | Path | None = None,
    init: str | Path | None = None,
    cache_dir: str | Path | None = None,
    device: str | torch.device | None = None,
    store: SampleStore | None = None,
    echo: Callable[[str], None] = print,
    overwrite: bool = False,
    report: Callable[[str], None] | None = None,
) -> TrainResult:
    """Train on the ``train`` split of ``data_dir``; see the module docstring for what lands in ``out_dir``.

    ``store`` skips reading the dataset (tests, or several runs over one store). ``resume`` continues a
    ``last.pt``: model, optimizer, scheduler, fp16 loss scaler and data position, so the continuation is the
    uninterrupted run's (given the same --amp and device kind).
    ``init`` starts from the weights of a checkpoint of the same preset (``model.pt``, ``last.pt`` or shipped
    weights) with a fresh optimizer and schedule: fine-tuning, or a second budget on top of a first; from a checkpoint
    of another preset, the parts whose configuration both share (``checkpoint.TRANSFERABLE_PARTS``: image encoder,
    lifter, pillar net), every other weight initialised with the seed; or from an image encoder's weights
    (streamdet-train-image's ``encoder.pt``), likewise. ``config.teacher`` adds the distillation loss of that
    detector's responses (training/distill.py); ``config.freeze_camera_lane`` keeps ``init``'s camera lane.
    An ``out_dir`` that already holds a run (``RUN_FILES``) is refused unless ``resume`` continues it or ``overwrite``
    replaces it; one holding anything but a run is refused (``check_out_contents``). A new run that fails before its
    first checkpoint or logged record leaves nothing in ``out_dir`` (``discard_unstarted_run``). A loss or weight that
    turns NaN or inf stops training with a ValueError (nothing written for it); a Ctrl-C (KeyboardInterrupt) between
    or during steps writes last.pt and model.pt at the last step done, then goes on as a KeyboardInterrupt.
    ``echo`` takes the progress lines and notes, ``report`` (default: ``echo``) the two lines that describe the run:
    what it trains on what, and how it ended.
    """
    if resume is not None and init is not None:
        raise ValueError("give either resume (continue a run) or init (start a new run from weights), not both")
    if config.freeze_camera_lane and init is None and resume is None:
        raise ValueError("freeze_camera_lane keeps the camera lane as initialised: give init (the weights to keep)")
    if device is not None:
        device = check_device(device)  # before --out is made: a bad device is refused, not found at the first step
    made = missing_folders(out_dir)
    # before any process starts (every one sees the same folder): after set-up the main process writes into it
    replaced = check_out_dir(out_dir, RUN_FILES, resume, overwrite)
    if os.environ.get("RANK", "0") == "0":
        for path in remove_stale_temps(out_dir, RUN_FILES):
            echo(f"removed {path}: the temp file of a save that was killed mid-write")
    try:
        return _train_into(config, data_dir, out_dir, version, resume, init, cache_dir, device, store, echo, replaced,
                           echo if report is None else report)  # fmt: skip
    except BaseException:
        # a new run, or a resume into a folder this invocation made (everything in it is its own); a resume in an
        # existing folder leaves that run's files alone. The main process (torchrun's rank 0) owns --out.
        if (resume is None or made) and os.environ.get("RANK", "0") == "0":
            discard_unstarted_run(out_dir, RUN_FILES, made)
        raise


def _train_into(config: TrainConfig, data_dir: str | Path, out_dir: str | Path, version: str, resume: str | Path | None,
                init: str | Path | None, cache_dir: str | Path | None, device: torch.device | None,
                store: SampleStore | None, echo: Callable[[str], None], replaced: list[Path],
                report: Callable[[str], None]) -> TrainResult:  # fmt: skip
    """``train`` once ``out_dir`` is checked: set up, write the run's files, train, save (``replaced``: the files
    of an earlier run that --overwrite removes)."""
    state = None
    if resume is not None:  # before the dataset is read: a resume the run's own config refuses costs no minutes
        state = load_checkpoint(resume, "resume checkpoint")
        _check_resume_state(state, resume, config)
        plan = _finished_plan(state, config)
        if plan is not None:  # a --steps or time plan's end is known without the data (an --epochs plan's is not)
            return _finished_resume(state, resume, out_dir, config, plan, state["scheduler"]["step"], report)
    loaded_init = _read_init(init) if init is not None else None  # as early: a bad --init costs no minutes either
    run = _set_up(config, data_dir, out_dir, version, init, cache_dir, device, store, echo, loaded_init)
    if resume is not None:
        _restore(run, resume, state)
        if run.schedule.done:
            return _finished_resume(state, resume, out_dir, config, run.plan, run.schedule.step, report)
    if run.teacher is not None:
        # with camera dropout the teacher lifts every camera itself: its targets are the whole scene's
        run.shared_lane = config.freeze_camera_lane and not config.camera_dropout and run.teacher.shares_camera_lane(run.detector)
        run.say(f"distilling from {config.teacher} (preset {run.teacher.preset.name!r}, weight {config.distill_weight:g})"
                + ("; the frozen camera lane is the teacher's: one lift per step for both" if run.shared_lane else ""))  # fmt: skip
    if run.ctx.is_main:
        for path in replaced:  # --overwrite: none of the old run's files may outlive it beside the new run's
            path.unlink(missing_ok=True)
    _write_config(run, data_dir, init)
    if resume is not None and run.ctx.is_main:
        # the records a killed run logged after its checkpoint are trained again now: they must not stay twice
        dropped = trim_run_log(run.out_dir / "metrics.jsonl", run.schedule.step)
        if dropped:
            run.say(f"metrics.jsonl: dropped {dropped} record(s) logged after step {run.schedule.step} (after the "
                    "checkpoint resumed: those steps are trained again)")  # fmt: skip
    # never through a symlink nor into a FIFO that appeared while the data was read (check_out_dir refused them before)
    log_file = open_run_log(run.out_dir / "metrics.jsonl", append=resume is not None) if run.ctx.is_main else None
    n_params = sum(p.numel() for p in run.model.parameters())
    # what is trained, on what, how: with the closing line, the run's own report (``report``: stdout in the CLI)
    (report if run.ctx.is_main else run.say)(
        f"training {run.preset.name} ({'camera + LiDAR' if run.preset.use_image else 'LiDAR only'}"
        f"{'' if run.preset.slice_crop else ', no quadrant crop'}, {n_params / 1e6:.2f} M parameters) "
        f"on {len(run.dataset.store)} samples, slices {list(config.data.num_slices)}, {run.ctx.world_size} process(es) x batch "
        f"{config.batch_size}, {len(run.loader)} steps/epoch, {run.plan}, device {run.device}"
    )
    try:
        stopped_early, last_loss = _loop(run, log_file, init)
        # this process's share: the global batch's loss is the sum over processes (NaN where no step was taken: on all)
        last_loss = float(all_reduce_sum(torch.tensor([last_loss], dtype=torch.float64), run.ctx)[0])
        check_weights_finite(run.model, run.schedule.step)
    finally:
        if log_file is not None:
            log_file.close()  # also when training diverged: the log up to that step stays readable
    ckpt = run.checkpoint()
    step = run.schedule.step
    weights = _save_model(run, init)
    seconds = time.perf_counter() - run.t_start
    if run.skipped_samples:
        run.say(f"skipped {run.skipped_samples} sample(s) without a usable LiDAR point in their slices "
                f"({run.skipped_steps} batch(es) left empty, no step taken for them)")  # fmt: skip
    dropped_targets = int(all_reduce_sum(torch.tensor([float(run.dropped_targets)], dtype=torch.float64), run.ctx)[0])
    _say_dropped_targets(run, dropped_targets)
    if run.ctx.is_main:
        report(f"{'stopped by --max-minutes' if stopped_early else 'done'} after {step} steps in {seconds / 60:.1f} min; "
               f"wrote {run.out_dir}")  # fmt: skip
    return TrainResult(step, seconds, stopped_early, last_loss, ckpt, weights, run.skipped_samples, dropped_targets)


def _save_model(run: _TrainRun, init: str | Path | None) -> Path | None:
    """model.pt of the run's weights now (main process only; None on the others)."""
    if not run.ctx.is_main:
        return None
    weights = run.out_dir / "model.pt"
    save_weights(weights, run.preset, run.detector, meta={"steps": run.schedule.step, "config": run.config.to_dict(),
                                                          "init": str(init) if init is not None else None})  # fmt: skip
    return weights


def _say_dropped_targets(run: _TrainRun, count: int) -> None:
    """The one warning of a run whose maps held more objects than the targets' cap: those beyond it are no target
    (training/targets.py), which nothing else would tell."""
    if count:
        cap = run.config.data.targets.max_objects
        run.say(f"warning: {count} target box(es) left out: a head map held more than the cap of {cap} objects "
                "(TargetConfig.max_objects); metrics.jsonl counts them per record (dropped_targets)")  # fmt: skip


def _read_init(init: str | Path) -> Any:
    """What ``init`` holds, read and checked once, before the dataset is read: an image encoder's state dict
    (streamdet-train-image's encoder.pt) or a checkpoint dict (``check_checkpoint``); ValueError naming it."""
    obj = read_torch_file(init, "init checkpoint")
    return obj if is_encoder_state(obj) else check_checkpoint(obj, init, "init checkpoint")


def _finished_plan(state: dict[str, Any], config: TrainConfig) -> str | None:
    """The plan in words when ``state`` (a checked last.pt) finished the schedule ``config`` asks for and that is
    known before the data is read: a --steps plan, or a time plan; None otherwise (an --epochs plan's length needs
    the steps per epoch; a schedule that does not match is reported by ``_restore``)."""
    sched = state["scheduler"]
    try:
        if config.steps is not None:
            total, step = sched.get("total_steps"), sched.get("step")
            if isinstance(total, int) and isinstance(step, int) and total == config.steps and step >= total:
                return f"{total} steps"
        elif config.epochs is None:
            budget, elapsed = sched.get("budget_s"), float(sched.get("elapsed_s"))
            if budget is not None and budget == 60 * config.max_minutes and math.isfinite(elapsed) and elapsed >= budget:
                return f"one-cycle over {config.max_minutes:g} min of wall time"
    except (TypeError, ValueError, OverflowError):  # a crafted scheduler state: _restore says what is wrong with it
        return None
    return None


def _finished_resume(state: dict[str, Any], resume: str | Path, out_dir: str | Path, config: TrainConfig, plan: str,
                     step: int, report: Callable[[str], None]) -> TrainResult:  # fmt: skip
    """A --resume of a checkpoint that finished its schedule: nothing is left to train. A run stopped between its
    last two writes (last.pt, then model.pt) has a finished last.pt and no model.pt of it (none, or an earlier
    one): in the checkpoint's own folder it is written now, from the checkpoint. Otherwise a ValueError that says
    where the weights are or how to get them. ``step``: the schedule's, where it ended."""
    own, weights = Path(resume).parent, Path(out_dir) / "model.pt"
    if not _same_folder(own, Path(out_dir)):
        if _weights_of_step(own / "model.pt", step):
            where = f"its weights are {own / 'model.pt'}"
        else:
            where = (f"its folder has no model.pt of it: resume it there (--out {own}) to write one from it, or export "
                     f"the checkpoint itself (streamdet-export --checkpoint {resume})")  # fmt: skip
        raise ValueError(f"checkpoint {resume} finished its schedule ({plan}): nothing left to train; {where}")
    if _weights_of_step(weights, step):
        raise ValueError(f"checkpoint {resume} finished its schedule ({plan}): nothing left to train; its weights are "
                         f"{weights}")  # fmt: skip
    if os.environ.get("RANK", "0") == "0":
        preset = config.build_preset()
        detector = build_detector(preset)
        check_fits(detector.state_dict(), state["model"], resume, "resume checkpoint", f"preset {preset.name!r}")
        detector.load_state_dict(state["model"])
        save_weights(weights, preset, detector, meta={"steps": step, "config": config.to_dict(), "init": None})
        report(f"checkpoint {resume} finished its schedule ({plan}), but its folder held no model.pt of step {step} "
               f"(the run was stopped between its last two writes): wrote {weights} from it; nothing left to train")  # fmt: skip
    return TrainResult(step, 0.0, False, math.nan, Path(resume), weights)


def _weights_of_step(path: Path, step: int) -> bool:
    """Whether ``path`` is a model.pt the run wrote at ``step`` (its meta says so)."""
    if not path.is_file():
        return False
    try:
        obj = read_torch_file(path)
    except ValueError:
        return False  # unreadable: the checkpoint's weights replace it
    meta = obj.get("meta") if isinstance(obj, dict) else None
    return isinstance(meta, dict) and meta.get("steps") == step


def _set_up(config: TrainConfig, data_dir: str | Path, out_dir: str | Path, version: str, init: str | Path | None,
            cache_dir: str | Path | None, device: str | torch.device | None, store: SampleStore | None,
            echo: Callable[[str], None], loaded_init: Any = None) -> _TrainRun:  # fmt: skip
    """Device and processes, model (from ``init``'s weights if given: ``loaded_init``, what ``_read_init`` read),
    teacher, optimizer, data, schedule, loss. The model and teacher come before the data: a --init or --teacher
    that does not fit is refused before minutes of reading the train split."""
    t_start = time.perf_counter()
    device = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ctx = init_distributed(device)
    device = process_device(device, ctx)
    say = echo if ctx.is_main else (lambda _msg: None)
    preset = config.build_preset()

    torch.manual_seed(config.seed)
    detector = build_detector(preset)
    init_head_outputs(detector)  # a resumed run overwrites it with the checkpoint
    if init is not None:
        _load_init_weights(detector, preset, init, say, loaded_init)
    if ctx.initialised and ctx.world_size > 1:
        convert_batchnorm(detector)
    model = TrainingModel(detector, image_classifier=config.image_class_weight > 0,
                          freeze_camera_lane=config.freeze_camera_lane).to(device).train()  # fmt: skip
    teacher = Teacher(config.teacher, preset, device) if config.teacher is not None else None
    warmup = preset.use_image and config.image_warmup > 0
    # During the warm-up the image lane gets no gradient; DDP must then look for unused parameters.
    wrapped = DistributedDataParallel(model, find_unused_parameters=warmup) if ctx.initialised and ctx.world_size > 1 else model
    trained = [p for p in model.parameters() if p.requires_grad]  # not a frozen camera lane
    optimizer = torch.optim.AdamW(trained, lr=config.lr / config.div_factor, weight_decay=config.weight_decay)

    if store is None:
        size = (preset.image.width_px, preset.image.height_px) if preset.use_image else None
        say(f"reading the train split of {data_dir} ({'images ' + f'{size[0]}x{size[1]}' if size else 'no images'})")
        with counted("  samples read", say) as progress:  # none on a cache hit
            store = build_store(data_dir, "train", size, version=version, cache_dir=cache_dir, progress=progress, echo=say)
    collate = Collator(preset, config.data.camera_mode)
    collate.check_store(store, data_dir)  # the cameras must fit the preset's images: the export's and runtime's rule
    dataset = SliceDataset(store, preset, config.data, seed=config.seed)
    loader, sampler = make_loader(dataset, config, ctx, collate)
    schedule, plan = _schedule(config, len(loader))
    amp, use_scaler = _amp_context(config.amp, device)
    return _TrainRun(
        config=config, preset=preset, out_dir=Path(out_dir), device=device, ctx=ctx, say=say, dataset=dataset,
        loader=loader, sampler=sampler, detector=detector, model=model, wrapped=wrapped, optimizer=optimizer,
        schedule=schedule, plan=plan, criterion=CenterPointLoss(config.loss).to(device), amp=amp,
        scaler=torch.amp.GradScaler("cuda", enabled=use_scaler), warmup=warmup, t_start=t_start, teacher=teacher,
        data_dir=str(data_dir),
    )  # fmt: skip


def _load_init_weights(detector, preset: Preset, init: str | Path, say: Callable[[str], None], loaded: Any = None) -> None:
    """``init``'s weights into ``detector`` (``loaded``: what ``_read_init`` read from it, else it is read here)."""
    if loaded is None:
        loaded = _read_init(init)
    if is_encoder_state(loaded):  # streamdet-train-image's encoder.pt: the image encoder; the rest stays seeded
        load_encoder_weights(detector, init, loaded)
        say(f"initialised the image encoder from {init}; every other weight from the seed")
        return
    state = loaded  # its model a state dict of tensors (check_checkpoint)
    own = detector.state_dict()

    def own_dtypes(weights: dict) -> dict:  # shipped weights may be stored in float16: back to the model's own dtypes
        return {k: v.to(own[k].dtype) for k, v in weights.items()}

    if state["preset"] == preset.to_dict():
        check_fits(own, state["model"], init, "init checkpoint", f"preset {preset.name!r}")
        detector.load_state_dict(own_dtypes(state["model"]))
        say(f"initialised from the weights of {init}")
        return
    # another preset: the parts whose configuration is the same (e.g. the camera lane under a new slice net)
    weights, parts = transferable_weights(preset, state["preset"], state["model"])
    if not parts:
        raise ValueError(f"init checkpoint {init} holds another preset ({state['preset'].get('name')!r}) than {preset.name!r} "
                         f"and shares none of its parts ({', '.join(TRANSFERABLE_PARTS)}) with it")  # fmt: skip
    # a size mismatch or a tensor the model lacks despite equal configs: a checkpoint edited by hand
    check_fits(own, weights, init, "init checkpoint", f"preset {preset.name!r}", partial=True)
    try:
        unexpected = detector.load_state_dict(own_dtypes(weights), strict=False).unexpected_keys
    except RuntimeError as e:
        raise ValueError(f"init checkpoint {init}: {first_line(e)}") from None
    if unexpected:
        raise ValueError(f"init checkpoint {init}: tensors the model does not have: {', '.join(sorted(unexpected)[:5])}")
    say(f"initialised {', '.join(parts)} from {init} (preset {state['preset'].get('name')!r}); every other weight from the seed")


def _schedule(config: TrainConfig, steps_per_epoch: int) -> tuple[OneCycle, str]:
    """The one-cycle schedule over the configured steps, epochs or minutes, and that plan in words."""
    if config.steps is not None or config.epochs is not None:
        total_steps = config.steps if config.steps is not None else config.epochs * steps_per_epoch
        schedule = OneCycle(config.lr, config.pct_start, config.div_factor, config.final_div_factor, total_steps=total_steps)
        return schedule, f"{total_steps} steps"
    schedule = OneCycle(config.lr, config.pct_start, config.div_factor, config.final_div_factor, budget_s=60 * config.max_minutes)
    return schedule, f"one-cycle over {config.max_minutes:g} min of wall time"


def data_record(store: SampleStore) -> dict[str, Any]:
    """What a last.pt records of the data it trained on: the train split's sample count and a digest of its tokens
    in order. A resume skips ahead in the data order of these samples; another split (another --data, a dataset
    regenerated with other scenes) would continue in an order the run never had. The path is not compared: a run
    split over sessions may find the same dataset at another path on another machine."""
    digest = hashlib.sha256("\n".join(store.tokens).encode()).hexdigest()
    return {"samples": len(store.tokens), "tokens_sha256": digest}


def _check_resume_state(state: dict[str, Any], resume: str | Path, config: TrainConfig) -> None:
    """ValueError (one line) unless ``state`` (a loaded last.pt) can continue under ``config``: a training checkpoint
    of the same preset, run with the same settings (``train_config.resume_config_changes``: a changed --batch-size
    or --seed once failed with StopIteration, or silently continued in another data order). Before the dataset is
    read and before anything in --out is written."""
    for key in ("optimizer", "scheduler", "step", "epoch", "epoch_step"):
        if key not in state:
            raise ValueError(f"checkpoint {resume} lacks {key!r}: it holds weights only, it cannot resume a run")
    preset = config.build_preset()
    if state["preset"] != preset.to_dict():
        saved = state["preset"]
        name = saved.get("name")
        flags = "".join(f" {flag}" for flag, key in (("--no-image", "use_image"), ("--no-crop", "slice_crop")) if saved.get(key) is False)
        given = "".join(f" {flag}" for flag, on in (("--no-image", preset.use_image), ("--no-crop", preset.slice_crop)) if not on)
        same_name = f"; its preset {name!r} has changed since (another streamdet version?)" if name == preset.name and flags == given else ""
        shown = name if isinstance(name, str) and name.isidentifier() else short_repr(name, 40)
        raise ValueError(f"checkpoint {resume} was trained with --preset {shown}{flags}, given --preset "
                         f"{preset.name}{given}{same_name}: resume it with its own (leave --preset out to take it), or "
                         f"start a new run from its weights with --init {resume}")  # fmt: skip
    was, now = state.get("config", {}), config.to_dict()
    if not isinstance(was, dict):
        raise ValueError(f"checkpoint {resume}: 'config' is a {type(was).__name__}, not the TrainConfig dict")
    for key in ("epoch", "epoch_step"):
        if isinstance(state[key], bool) or not isinstance(state[key], int) or state[key] < 0:
            raise ValueError(f"checkpoint {resume}: {key!r} must be an integer >= 0, got {state[key]!r}")
    for key in ("optimizer", "scheduler"):
        if not isinstance(state[key], dict):
            raise ValueError(f"checkpoint {resume}: {key!r} is a {type(state[key]).__name__}, not a state dict")
    same_file = lambda a, b: a == b or (a is not None and b is not None and Path(a).resolve() == Path(b).resolve())  # noqa: E731
    try:
        same = same_file(was.get("teacher"), now.get("teacher"))
    except TypeError:  # a teacher that is no path
        same = False
    if not same or was.get("freeze_camera_lane") != now.get("freeze_camera_lane"):
        raise ValueError(f"checkpoint {resume} was trained with teacher={was.get('teacher')!r}, freeze_camera_lane="
                         f"{bool(was.get('freeze_camera_lane'))}: resume it with the same (given teacher={now.get('teacher')!r}, "
                         f"freeze_camera_lane={config.freeze_camera_lane})")  # fmt: skip
    if (config.image_class_weight > 0) != ("image_classifier" in state):
        raise ValueError(f"checkpoint {resume} was trained {'without' if config.image_class_weight > 0 else 'with'} the image "
                         f"class loss: resume it with the image_class_weight it was started with")  # fmt: skip
    changes = resume_config_changes(was, config)
    if changes:
        had = ", ".join(f"{option} {show_option_value(old)}" for option, old, _ in changes)
        given = ", ".join(f"{option} {show_option_value(new)}" for option, _, new in changes)
        raise ValueError(f"--resume {resume} was trained with {had}; given {given}: a resumed run continues with its own "
                         f"data order, schedule and loss; give the same again, or start a new run from its weights "
                         f"with --init {resume}")  # fmt: skip


def _restore(run: _TrainRun, resume: str | Path, state: dict[str, Any]) -> None:
    """Continue the run a ``last.pt`` holds (``state``, checked by ``_check_resume_state``): model, optimizer,
    schedule and data position."""
    preset = run.preset
    was = state.get("config", {})
    data, here = state.get("data"), data_record(run.dataset.store)
    if data is not None and data != here:  # a checkpoint from before the record: not checked
        def show(d: object) -> str:
            if not isinstance(d, dict):
                return short_repr(d, 40)
            return f"{short_repr(d.get('samples'), 20)} samples, tokens sha256 {short_repr(d.get('tokens_sha256'), 20)[:13]}..."

        raise ValueError(f"--resume {resume} was trained on another train split ({show(data)}) than --data {run.data_dir} "
                         f"holds ({show(here)}): a resumed run continues over its own samples in its own order; give its "
                         f"--data, or start a new run with --init {resume}")  # fmt: skip
    # the skip-ahead would run out of batches (StopIteration); equal is a run cut right after an epoch's last batch
    if state["epoch_step"] > len(run.loader):
        raise ValueError(f"checkpoint {resume}: its data position (batch {state['epoch_step']} of epoch {state['epoch']}) "
                         f"is past the {len(run.loader)} batches of an epoch of this run")  # fmt: skip
    check_fits(run.detector.state_dict(), state["model"], resume, "resume checkpoint", f"preset {preset.name!r}")
    if was.get("camera_dropout", 0.0) != run.config.camera_dropout:  # allowed (an augmentation), but said
        run.say(f"resuming {resume} with camera_dropout {run.config.camera_dropout:g}; it was trained with "
                f"{was.get('camera_dropout', 0.0):g} so far")  # fmt: skip
    classifier = run.model.image_classifier
    if classifier is not None:
        weights = check_state_dict(state["image_classifier"], resume, "resume checkpoint", "image_classifier")
        check_fits(classifier.state_dict(), weights, resume, "resume checkpoint", "the image classifier")
    run.detector.load_state_dict(state["model"])
    if classifier is not None:
        classifier.load_state_dict(state["image_classifier"])
    try:
        run.optimizer.load_state_dict(state["optimizer"])
    except (ValueError, KeyError, TypeError, AttributeError, IndexError, RuntimeError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ValueError(f"checkpoint {resume}: its optimizer state does not fit this run's optimizer: {first}") from None
    check_optimizer_state(run.optimizer, resume)
    try:
        run.schedule.load_state_dict(state["scheduler"])
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ValueError(f"checkpoint {resume}: its scheduler state does not fit this run: {first}") from None
    if run.schedule.step < 0 or not math.isfinite(run.schedule.elapsed_s) or run.schedule.elapsed_s < 0:
        raise ValueError(f"checkpoint {resume}: scheduler step {run.schedule.step} / elapsed_s {run.schedule.elapsed_s} "
                         f"must be >= 0 and finite")  # fmt: skip
    _restore_scaler(run, resume, state.get("scaler"))
    run.epoch, run.epoch_step, run.elapsed_before = state["epoch"], state["epoch_step"], run.schedule.elapsed_s
    if not run.schedule.done:  # a finished one: _finished_resume says what there is to do
        run.say(f"resumed {resume} at step {run.schedule.step} (epoch {run.epoch}, batch {run.epoch_step})")


def _restore_scaler(run: _TrainRun, resume: str | Path, saved: object) -> None:
    """The fp16 loss scaler's state (CUDA fp16 autocast): its scale and growth tracker decide which of the next steps
    are skipped, so a resume without them is not the uninterrupted run. A run resumed under another --amp starts a
    fresh scaler (or drops the saved one), and says so."""
    if not run.scaler.is_enabled():
        if saved:
            run.say(f"resuming {resume} without fp16 autocast: it was trained with it (--amp), its loss scaler is dropped")
        return
    if not saved:
        run.say(f"resuming {resume} with fp16 autocast and a fresh loss scaler: it was trained without it (--amp)")
        return
    if not isinstance(saved, dict):
        raise ValueError(f"checkpoint {resume}: 'scaler' is a {type(saved).__name__}, not the GradScaler's state dict")
    try:
        run.scaler.load_state_dict(saved)
    except (ValueError, KeyError, TypeError, RuntimeError) as e:
        raise ValueError(f"checkpoint {resume}: its loss scaler state does not fit: {first_line(e)}") from None
    scale = run.scaler.get_scale()
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"checkpoint {resume}: its loss scaler's scale must be finite and > 0, got {scale!r}")


def check_optimizer_state(optimizer: torch.optim.Optimizer, path: str | Path) -> None:
    """ValueError naming the file unless every per-parameter tensor of the loaded optimizer state (AdamW's moments)
    has its parameter's shape and is finite: torch loads any, and fails (or trains on garbage) at the next step.
    streamdet-train-image's --resume calls it too (image_pretrain._pretrain_into)."""
    for param, entry in optimizer.state.items():
        if not isinstance(entry, dict):
            raise ValueError(f"checkpoint {path}: an optimizer state entry is a {type(entry).__name__}, not a dict")
        for name, value in entry.items():
            if not isinstance(value, torch.Tensor):
                continue
            check_dense(value, f"optimizer state {name!r}", path)  # a sparse or meta moment: isfinite would fail on it
            if value.dim() > 0 and tuple(value.shape) != tuple(param.shape):
                raise ValueError(f"checkpoint {path}: optimizer state {name!r} has shape {tuple(value.shape)} for a "
                                 f"parameter of shape {tuple(param.shape)}")  # fmt: skip
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise ValueError(f"checkpoint {path}: optimizer state {name!r} holds non-finite values")


def _write_config(run: _TrainRun, data_dir: str | Path, init: str | Path | None) -> None:
    if run.ctx.is_main:
        run.out_dir.mkdir(parents=True, exist_ok=True)
        # atomic: a config.json cut short would make the folder look like no run at all to --resume / --overwrite
        write_text_atomic(run.out_dir / "config.json", json.dumps({"train": run.config.to_dict(), "preset": run.preset.to_dict(),
                                                                   "data_dir": str(data_dir), "world_size": run.ctx.world_size,
                                                                   "init": str(init) if init is not None else None}, indent=1))  # fmt: skip


def _loop(run: _TrainRun, log_file, init: str | Path | None = None) -> tuple[bool, float]:
    """Train until the schedule is done (or --max-minutes runs out); (stopped early, the last step's loss).

    A Ctrl-C (KeyboardInterrupt) ends the loop with last.pt and model.pt written at the last step done (its partial
    log window logged), then goes on: ``--resume`` loses no step. A Ctrl-C during a step waits for its end
    (``sigint_deferred``); a second one ends it at once, and then nothing is written (the step's state is half
    changed: its forward pass alone moves the BatchNorm statistics). Before the first step of this invocation there is
    nothing new to write. Under torchrun the other processes may be inside a collective: nothing is written there,
    the run resumes from its last checkpoint."""
    window = {"t": time.perf_counter(), "samples": 0, "slices": 0, "loss": 0.0, "parts": {}, "n": 0, "dropped": 0}
    # the lr of the last step taken; the step under way (schedule.step moves on before its log and checkpoint)
    last = {"lr": math.nan, "in_progress": run.schedule.step + 1}
    start = run.schedule.step
    try:
        return _steps(run, log_file, window, last)
    except InterruptedMidStep:
        run.say(f"interrupted again in the middle of step {last['in_progress']}: nothing written for it (the last "
                "checkpoint stays as it was)")  # fmt: skip
        raise
    except KeyboardInterrupt:
        # before this invocation's first step there is nothing new to save (a new run then leaves nothing)
        if run.ctx.world_size > 1 or not run.ctx.is_main or run.schedule.step == start:
            raise
        # a second Ctrl-C here ends the saves below: each is atomic (the previous file stays whole)
        if window["n"]:
            _log(window, run.schedule, last["lr"], run.epoch, run.ctx, run.say, log_file)
        if log_file is not None:
            log_file.close()
        check_weights_finite(run.model, run.schedule.step)
        run.checkpoint()
        _save_model(run, init)
        _say_dropped_targets(run, run.dropped_targets)
        run.say(f"interrupted after step {run.schedule.step}: wrote {run.out_dir / 'last.pt'} and model.pt of that "
                f"step; --resume {run.out_dir / 'last.pt'} continues from there")  # fmt: skip
        raise


def _steps(run: _TrainRun, log_file, window: dict, last: dict) -> tuple[bool, float]:
    """``_loop``'s steps (``last["lr"]``: the lr of the last step taken, for a log written on an interrupt). Only the
    wait for the next batch takes a Ctrl-C at once; each step with its log and checkpoint is whole or not taken."""
    config, schedule, preset, ctx = run.config, run.schedule, run.preset, run.ctx
    stopped_early = False
    last_loss = math.nan
    lr = math.nan
    timed = schedule.by_time or config.max_minutes is not None
    images_on = schedule.progress >= config.image_warmup
    while not schedule.done and not stopped_early:
        run.sampler.set_epoch(run.epoch)
        run.sampler.skip = run.epoch_step * run.config.batch_size  # resume: not the batches this epoch already used
        run.dataset.set_epoch(run.epoch)
        batches = iter(run.loader)
        stepped = run.epoch_step > 0  # whether this epoch took an optimizer step (a resumed one: before the cut)
        for batch in batches:
            last["in_progress"] = schedule.step + 1
            with sigint_deferred():
                batch = batch.to(run.device)
                if _skip_batch(run, batch):  # no sample with a pillar: no step, the data position moves on
                    run.epoch_step += 1
                    continue
                stepped = True
                lr = schedule.apply(run.optimizer)
                use_image = preset.use_image and schedule.progress >= config.image_warmup
                if run.warmup and use_image and not images_on:
                    run.say(f"step {schedule.step}: warm-up over ({config.image_warmup:.0%} of the schedule), the image lane joins")
                    images_on = True
                loss, parts = _step(run, batch, use_image)
                _update(run)
                schedule.advance(run.elapsed() if timed else run.elapsed_before + time.perf_counter() - run.t_start)
                run.epoch_step += 1
                last_loss = float(loss.detach()) / ctx.world_size  # this process's share of the global loss
                if _diverged(run, last_loss):
                    if window["n"]:  # the steps before this one, not logged yet: the run's last finite stretch
                        _log(window, schedule, last["lr"], run.epoch, ctx, run.say, log_file, step=schedule.step - 1)
                    raise _divergence_error(run, last_loss, lr)
                last["lr"] = lr
                window["samples"] += batch.num_samples
                window["slices"] += batch.num_slices
                window["dropped"] += batch.num_dropped
                run.dropped_targets += batch.num_dropped
                window["loss"] += last_loss
                for k, v in parts.items():  # unscaled local shares (normalised by the global counts): they sum to the part
                    window["parts"][k] = window["parts"].get(k, 0.0) + float(v)
                window["n"] += 1
                if schedule.step % config.log_every == 0:
                    _log(window, schedule, lr, run.epoch, ctx, run.say, log_file)
                if schedule.step % config.checkpoint_every == 0:
                    check_weights_finite(run.model, schedule.step)  # every process holds the same weights (DDP)
                    run.checkpoint()
                # with a step/epoch plan the limit is this invocation's wall time (a resumed run gets it again), as a
                # session-split run needs; a time plan (no steps) spends one budget over all of its resumes
                if not schedule.by_time and config.max_minutes is not None and schedule.elapsed_s - run.elapsed_before > 60 * config.max_minutes:
                    stopped_early = not schedule.done  # every process sees the same (reduced) elapsed time
                    break
                if schedule.done:
                    break
        else:
            if not stepped and run.skipped_steps:  # every batch was empty: another epoch would spin for ever
                raise ValueError(f"no sample of the train split of {run.data_dir} holds a usable LiDAR point in its "
                                 f"slices (every batch of epoch {run.epoch} was empty): nothing to train on")  # fmt: skip
            run.epoch += 1
            run.epoch_step = 0
    with sigint_deferred():  # the record and the window's reset together: a Ctrl-C between them logged it twice
        if window["n"]:
            _log(window, schedule, lr, run.epoch, ctx, run.say, log_file)
    return stopped_early, last_loss


# The samples skipped for want of a pillar named one by one, up to this many; the rest only counted (at the end).
MAX_SKIPS_NAMED = 5


def _skip_batch(run: _TrainRun, batch: Batch) -> bool:
    """Count (and name the first few of) the samples the collator left out of ``batch`` for holding no pillar (a
    sweep that is empty, all NaN or outside the grid: the model has nothing to read in it, while its boxes would
    still be targets). True when no sample is left on some process: then no process steps (under torchrun every
    one must join the same all-reduces), and the batch is skipped."""
    for i in batch.skipped:
        run.skipped_samples += 1
        if run.skipped_samples <= MAX_SKIPS_NAMED:
            token = run.dataset.store.tokens[i]
            run.say(f"step {run.schedule.step}: sample {token} holds no usable LiDAR point in its slices (an empty, "
                    f"all-NaN or out-of-grid sweep): left out of its batch"
                    + ("; further ones are counted at the end" if run.skipped_samples == MAX_SKIPS_NAMED else ""))  # fmt: skip
    empty = batch.num_samples == 0
    if run.ctx.initialised and run.ctx.world_size > 1:
        flag = all_reduce_sum(torch.tensor([1.0 if empty else 0.0], device=run.device), run.ctx)
        empty = float(flag[0]) > 0
    if empty:
        run.skipped_steps += 1
    return empty


def _diverged(run: _TrainRun, loss: float) -> bool:
    """Whether the loss is NaN or inf on any process: the update it drove left NaN weights, so the run stops before
    anything more is written (the last checkpoint predates it; the steps before it are logged first).

    Checked on the value the loop reads anyway (no extra device sync); summed over processes, so every process
    stops at the same step (one stopping alone would leave the others waiting in the next all-reduce)."""
    finite = math.isfinite(loss)
    if run.ctx.initialised and run.ctx.world_size > 1:
        flag = all_reduce_sum(torch.tensor([0.0 if finite else 1.0], device=run.device), run.ctx)
        finite = float(flag[0]) == 0.0
    return not finite


def _divergence_error(run: _TrainRun, loss: float, lr: float) -> ValueError:
    """The ValueError of a diverged run, naming the step and the loss."""
    value = loss * run.ctx.world_size if not math.isfinite(loss) else "NaN or inf on another process"
    return ValueError(f"training diverged: the loss is {value} at step {run.schedule.step} (lr {lr:.3g}); stopped "
                      f"there, no weights written for it (lower --lr or the loss weights, or resume from an earlier "
                      f"last.pt)")  # fmt: skip


def _step(run: _TrainRun, batch: Batch, use_image: bool) -> tuple[torch.Tensor, dict]:
    """One step on one batch up to its update (``_update``): forward, loss over the global batch, backward, clipped
    gradients. Nothing the checkpoint holds changes here."""
    keep = _camera_keep(run, batch) if use_image else None
    with run.amp:
        lifted = run.model.image_bev(batch, use_image) if run.shared_lane else None  # frozen: no graph, read by both
        task_maps, image_class = run.wrapped(batch, use_image=use_image, lifted=lifted, camera_keep=keep)
    task_maps = [tuple(m.float() for m in maps) for maps in task_maps]
    terms = loss_terms(task_maps, run.model.task_classes, batch.heatmap, batch.index, batch.mask, batch.label, batch.box)
    counts = all_reduce_sum(terms.num_objects, run.ctx)
    loss, parts = run.criterion(terms, counts, scale=float(run.ctx.world_size))
    if run.teacher is not None:
        with run.amp:
            teacher_maps = run.teacher.maps(batch, use_image, lifted)
        distill, distill_parts = distill_loss(task_maps, teacher_maps, counts, run.criterion.code_weights, run.config.distill)
        loss = loss + run.config.distill_weight * distill * float(run.ctx.world_size)
        parts.update(distill_parts)
    if image_class is not None:
        # per object, normalised by the global batch's object count like the heatmap term (every object is in
        # exactly one task, so the tasks' counts sum to it); objects whose cameras were dropped are not read
        image_loss = image_class_loss_sum(*image_class) / counts.sum().clamp(min=1.0)
        loss = loss + run.config.image_class_weight * image_loss * float(run.ctx.world_size)
        parts["image_class"] = image_loss.detach()
    run.optimizer.zero_grad(set_to_none=True)
    run.scaler.scale(loss).backward()
    run.scaler.unscale_(run.optimizer)
    torch.nn.utils.clip_grad_norm_(run.model.parameters(), run.config.grad_clip)
    return loss, parts


def _update(run: _TrainRun) -> None:
    """The optimizer update of the gradients ``_step`` left (and the fp16 loss scaler's)."""
    run.scaler.step(run.optimizer)
    run.scaler.update()


def _camera_keep(run: _TrainRun, batch: Batch) -> torch.Tensor | None:
    """(B, J) bool cameras kept at this step when camera dropout drops cameras in it, else None (training/
    camera_dropout.py). Whether it drops is drawn from (seed, step), the same on every process (their BatchNorms then
    all use stored statistics); which cameras from (seed, step, process). A resumed run drops what the uninterrupted
    one would."""
    p = run.config.camera_dropout
    if p == 0 or batch.images is None or not drops_cameras(p, step_generator(run.config.seed, run.schedule.step)):
        return None
    num_cameras = batch.images.shape[0] // batch.num_samples
    gen = step_generator(run.config.seed, run.schedule.step, run.ctx.rank)
    return draw_camera_keep(batch.num_samples, num_cameras, gen, device=batch.images.device)


def _log(window: dict, schedule: OneCycle, lr: float, epoch: int, ctx: DistContext, say, log_file,
         step: int | None = None) -> None:  # fmt: skip
    """One record of the window's steps (``step``: the last of them, default the schedule's)."""
    step = schedule.step if step is None else step
    now = time.perf_counter()
    dt = max(now - window["t"], 1e-9)
    n = window["n"]
    # the local shares of the loss summed over processes make the global batch's loss
    stats = all_reduce_sum(torch.tensor([window["loss"]] + list(window["parts"].values()), dtype=torch.float64), ctx)
    loss = float(stats[0]) / n
    parts = {k: float(v) / n for k, v in zip(window["parts"], stats[1:].tolist())}
    counts = all_reduce_sum(torch.tensor([window["samples"], window["slices"], window.get("dropped", 0)], dtype=torch.float64),
                            ctx)  # every process's  # fmt: skip
    samples_s = float(counts[0]) / dt
    slices_s = float(counts[1]) / dt
    dropped = int(counts[2])
    if schedule.by_time:
        total, eta = "time", schedule.budget_s - schedule.elapsed_s
    else:
        total, eta = str(schedule.total_steps), (schedule.total_steps - step) * dt / n
    say(
        f"step {step:>6}/{total} ep {epoch:>3} loss {loss:7.4f} (hm {parts.get('heatmap', math.nan):.4f} "
        f"reg {parts.get('reg', math.nan):.4f}) lr {lr:.2e} {samples_s:5.2f} samples/s {slices_s:6.1f} slices/s "
        f"elapsed {schedule.elapsed_s / 60:5.1f} min eta {max(eta, 0.0) / 60:5.1f} min"
    )
    if log_file is not None:
        record = {"step": step, "epoch": epoch, "loss": loss, **parts, "lr": lr, "samples_per_s": samples_s,
                  "slices_per_s": slices_s, "elapsed_s": schedule.elapsed_s}  # fmt: skip
        if dropped:  # only where it happened: a record of every run would carry a 0 that nothing reads
            record["dropped_targets"] = dropped
        log_file.write(json.dumps(record) + "\n")
        log_file.flush()
    window.update(t=now, samples=0, slices=0, loss=0.0, parts={}, n=0, dropped=0)
