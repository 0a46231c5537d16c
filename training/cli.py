"""``streamdet-train``: train a preset on a nuScenes-format dataset (e.g. one written by ``streamdet-synth``).

Data parallel: ``torchrun --nproc_per_node 2 -m streamdet.training.cli --data DIR --out DIR ...`` (gloo on CPU).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from streamdet.cli_utils import (
    FiniteFloatRange, check_folder_creatable, dataset_inputs, not_a_file, refuse_output_over_inputs, version_option)
from streamdet.core.errors import first_line
from streamdet.core.json_input import short_repr
from streamdet.core.sectors import MAX_NUM_SLICES
from streamdet.models.presets import preset_names
from streamdet.training.checkpoint import check_checkpoint, read_torch_file
from streamdet.training.dataset import CAMERA_MODES, DataConfig
from streamdet.training.distributed import shutdown_distributed
from streamdet.training.image_pretrain import PRETRAIN_RUN_FILES
from streamdet.training.run_dir import CONFIG_FILE, NOT_A_RUN, RUN_FILES
from streamdet.training.train_config import (
    AMP_MODES, MAX_LR, MAX_MINUTES, MAX_SEED, MAX_STEPS, RESUME_MAY_CHANGE, TrainConfig, check_device, saved_config_values,
    show_option_value, values_differ)
from streamdet.training.trainer import train

MAX_WORKERS = 256  # DataLoader processes: a machine's cores at most, never thousands of forks
# The folders of a nuScenes-format dataset beside DATA/<version>: the files training reads. A cache written among
# them would sit in the dataset (and a later tool listing them would find it).
DATA_FILE_FOLDERS = ("samples", "sweeps", "maps")
DEVICE_HELP = "cpu, cuda, cuda:N or mps, where this machine has it"


def device_callback(ctx, param, value: str | None) -> str | None:
    """--device checked when parsed, before anything is made: one line naming the value, not torch's traceback at
    the first step after the run's files were written."""
    if value is None:
        return None
    try:
        check_device(value)
    except ValueError as e:
        raise click.BadParameter(str(e)) from None
    return value


def refuse_out_over_inputs(out_dir: Path, inputs: list[tuple[str, Path | None]]) -> None:
    """--out must not be (or lie inside) a folder or file the command reads: a run written into the dataset, the
    cache or beside a checkpoint it starts from mixes its files into that input."""
    refuse_output_over_inputs(out_dir, "--out", inputs)


def refuse_overwrite_of_inputs(out_dir: Path, overwrite: bool, run_files: tuple[str, ...],
                               inputs: list[tuple[str, Path | None]]) -> None:  # fmt: skip
    """With --overwrite, an input that is one of the run files it deletes (--init OUT/model.pt) is refused: the
    run would read it, then delete it, and a --resume of the new run could not find its --teacher again."""
    if not overwrite:
        return
    doomed = [out_dir / name for name in run_files if (out_dir / name).is_file()]
    for option, path in inputs:
        for file in doomed:
            if path is not None and _same_path(path, file):
                raise click.BadParameter(f"{str(path)!r} is the {file.name} of the run in --out that --overwrite deletes; "
                                         "copy it elsewhere first", param_hint=option)  # fmt: skip


def _check_cache_dir(cache_dir: Path | None, data_dir: Path, version: str) -> None:
    """An explicit --cache-dir must not be the dataset root nor lie in its table folder or file folders (the default,
    DATA/.streamdet_cache, is a folder of its own beside them): the cache's folders would sit among the tables,
    sample files or the dataset's top-level entries."""
    refuse_output_over_inputs(cache_dir, "--cache-dir", [("--data", data_dir / name) for name in (version, *DATA_FILE_FOLDERS)])
    if _same_path(cache_dir, data_dir):
        raise click.BadParameter(f"{str(cache_dir)!r} is the --data root: give a folder of its own (the default is "
                                 f"{data_dir / '.streamdet_cache'})", param_hint="--cache-dir")  # fmt: skip


# Files that tell a folder is no cache folder but an export, a saved evaluation, a dataset, or a training run of
# either tool (their config.json and run files): a cache written there puts train-* folders among their files, and
# an export holding one is refused by the next streamdet-export into it.
NOT_A_CACHE = (*NOT_A_RUN, *((name, "a training run") for name in dict.fromkeys((*RUN_FILES, *PRETRAIN_RUN_FILES, CONFIG_FILE))))


def _check_cache_folder(cache_dir: Path, option: str) -> None:
    """Before the split is read (minutes for a large one): the cache folder (--cache-dir, or the default
    DATA/.streamdet_cache) must be a folder that can be made (not a file, a broken link or a link loop: those failed
    only when the cache was written, as "Not a directory" or "File exists") and, where it exists, no export, saved
    evaluation, dataset or training run (``NOT_A_CACHE``)."""
    check_folder_creatable(cache_dir, option)
    if not cache_dir.is_dir():
        return
    for name, what in NOT_A_CACHE:
        if (cache_dir / name).exists() or (cache_dir / name).is_symlink():
            raise click.BadParameter(f"{str(cache_dir)!r} is {what} ({name}): the training cache must not be written "
                                     "into it; give a folder of its own", param_hint=option)  # fmt: skip


def _same_path(a: Path, b: Path) -> bool:
    """Whether two paths name one file or folder (through a symlink, a hard link or another spelling)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except (OSError, RuntimeError):  # a symlink loop: compare the spelling
        return a.absolute() == b.absolute()


def progress_echo(message: str) -> None:
    """A training tool's progress, notes and warnings: on stderr, as every tool's progress (toplevel/progress.py);
    stdout keeps the lines a script may read (what the run trains, how it ended)."""
    click.echo(message, err=True)


def given(ctx: click.Context, name: str) -> bool:
    """Whether the option ``name`` was given (on the command line or by its environment variable), even at its
    default value."""
    return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)


# streamdet-train's options that a --resume takes from its checkpoint where they are not given: the click parameter
# and its key in TrainConfig.to_dict (data.* nested). --no-image and --no-crop are the negations of theirs.
TRAIN_RESUME_PARAMS = (
    ("preset", "preset"), ("no_image", "use_image"), ("no_crop", "slice_crop"), ("steps", "steps"), ("epochs", "epochs"),
    ("batch_size", "batch_size"), ("lr", "lr"), ("num_slices", "data.num_slices"),
    ("max_slices_per_sample", "data.max_slices_per_sample"), ("camera_mode", "data.camera_mode"),
    ("image_warmup", "image_warmup"), ("image_class_weight", "image_class_weight"), ("camera_dropout", "camera_dropout"),
    ("teacher", "teacher"), ("distill_weight", "distill_weight"), ("freeze_camera_lane", "freeze_camera_lane"),
    ("balanced", "balanced"), ("workers", "workers"), ("seed", "seed"), ("max_minutes", "max_minutes"), ("amp", "amp"),
    ("log_every", "log_every"), ("checkpoint_every", "checkpoint_every"),
)  # fmt: skip
NEGATED_PARAMS = ("no_image", "no_crop")


def _train_may_change(key: str, values: dict[str, Any]) -> bool:
    """Whether a resumed streamdet-train run may be given another value of config ``key`` (train_config's
    RESUME_MAY_CHANGE): --max-minutes only where --steps or --epochs plan the schedule (alone it is the schedule);
    --teacher and --freeze-camera-lane never (the trainer's own check wants them as they were)."""
    if key == "max_minutes":
        return values.get("steps") is not None or values.get("epochs") is not None
    return key.split(".")[0] in RESUME_MAY_CHANGE and key not in ("teacher", "freeze_camera_lane")


def take_resume_options(ctx: click.Context, resume: Path, saved: dict[str, Any], params: tuple[tuple[str, str], ...],
                        may_change: Callable[[str, dict[str, Any]], bool]) -> dict[str, Any]:  # fmt: skip
    """The values of ``params`` (click parameter, config key) for a --resume of a checkpoint whose config holds
    ``saved`` (flat keys): an option not given takes the run's value, checked as the option checks a typed one (a
    checkpoint is input); a given one that the resume must keep (not ``may_change(key, values so far)``) and that
    differs is a usage error naming both values. A key the config lacks leaves its option as it is (the trainer
    reports what is missing)."""
    by_name = {p.name: p for p in ctx.command.params}
    values: dict[str, Any] = {}
    for name, key in params:
        param = by_name[name]
        flag = max(param.opts, key=len)
        if key not in saved:
            values[name] = ctx.params[name]
            continue
        was = _saved_option_value(ctx, param, saved[key], resume, key, negate=name in NEGATED_PARAMS)
        if not given(ctx, name):
            values[name] = was
            continue
        values[name] = now = ctx.params[name]
        if not may_change(key, values) and _option_values_differ(was, now):
            raise click.BadParameter(
                f"--resume {resume} was trained with {flag} {_show(was)}; given {flag} {_show(now)}: a resumed run "
                f"continues with its own settings; leave {flag} out to take the run's, or start a new run from its "
                f"weights with --init {resume}", param_hint=flag)  # fmt: skip
    return values


def _saved_option_value(ctx: click.Context, param: click.Parameter, value: Any, resume: Path, key: str, negate: bool) -> Any:
    """A checkpoint config's ``value`` of ``key`` as its option ``param`` would give it, checked as the option
    checks a typed value (its type, range and callback); ClickException naming the checkpoint and the key."""

    def bad(why: str) -> click.ClickException:
        return click.ClickException(f"--resume {resume}: its config's {key} is {short_repr(value, 40)}: {why}")

    if param.is_flag:
        if not isinstance(value, bool):
            raise bad("not on or off")
        return not value if negate else value
    if value is None:
        if param.default is None:
            return None
        raise bad(f"{max(param.opts, key=len)} needs a value")
    if isinstance(value, list) and param.name == "num_slices":  # the option's own spelling, parsed by its callback
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise bad("not slice counts")
        value = ",".join(str(v) for v in value)
    kind = param.type
    if isinstance(kind, click.types.IntParamType) and (isinstance(value, bool) or not isinstance(value, int)):
        raise bad("not an integer")  # click's int() would truncate 5.7 to 5
    if isinstance(kind, click.types.FloatParamType) and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise bad("not a number")
    if isinstance(kind, (click.Choice, click.Path, click.types.StringParamType)) and not isinstance(value, str):
        raise bad("not a string")
    try:
        out = kind.convert(value, param, ctx)
        return param.callback(ctx, param, out) if param.callback is not None else out
    except click.BadParameter as e:
        raise bad(e.format_message()) from None


def _option_values_differ(was: Any, now: Any) -> bool:
    if isinstance(was, Path) and isinstance(now, Path):
        return not _same_path(was, now)
    return values_differ(was, now)


def _show(value: Any) -> str:
    """An option's value as the user types it (``show_option_value``; a path as given)."""
    if isinstance(value, (Path, str)):
        return str(value)
    return show_option_value(list(value) if isinstance(value, tuple) else value)


def _check_combinations(teacher: Path | None, distill_weight: float, num_slices: tuple[int, ...],
                        max_slices_per_sample: int | None, no_image: bool = False, no_crop: bool = False) -> None:  # fmt: skip
    """Options that would be silently ignored in this combination are refused: the user meant something else."""
    ctx = click.get_current_context()
    if teacher is None and given(ctx, "distill_weight"):  # given, even at its default value
        raise click.BadParameter(f"{distill_weight:g} weighs the distillation loss, which needs --teacher WEIGHTS",
                                 param_hint="--distill-weight")  # fmt: skip
    # the image lane's options with --no-image, at a value that would change a fused run (config.json recorded an
    # ignored --image-warmup 0.5 as if it held), as TrainConfig refuses --camera-dropout and --image-class-weight.
    # Their defaults given explicitly stay accepted: they change nothing, and the docs/training scripts pass one
    # COMMON option string (--image-warmup 0 ...) to the fused and the LiDAR-only runs of a comparison.
    for name, option, default in (("image_warmup", "--image-warmup", 0.0), ("camera_mode", "--camera-mode", "all")):
        if no_image and ctx.params[name] != default:
            raise click.BadParameter(f"{ctx.params[name]!r} sets the image lane, which --no-image leaves out: drop one of "
                                     "them", param_hint=option)  # fmt: skip
    # the other way round: TrainConfig refuses --no-crop of a fused run too, but as a failed run (exit 1, no usage line)
    if no_crop and not no_image:
        raise click.BadParameter("training without the quadrant crop is supported for the LiDAR-only baseline only: add "
                                 "--no-image", param_hint="--no-crop")  # fmt: skip
    if max_slices_per_sample is not None and max_slices_per_sample > max(num_slices):
        raise click.BadParameter(f"{max_slices_per_sample} is more than the {max(num_slices)} slices of the largest "
                                 f"--num-slices {','.join(map(str, num_slices))}: it would change nothing",
                                 param_hint="--max-slices-per-sample")  # fmt: skip


def _parse_slices(ctx, param, value: str) -> tuple[int, ...]:
    entries = [v.strip() for v in value.split(",")]
    if any(not v for v in entries):
        raise click.BadParameter(f"an empty entry in {value!r}: give slice counts such as 8 or 8,32")
    try:
        counts = tuple(int(v) for v in entries)
    except ValueError:
        raise click.BadParameter(f"expected slice counts such as 8 or 8,32, got {value!r}") from None
    # a repeat is a weight, not a slip: each sample draws one entry uniformly (SliceDataset), so 8,8,32 trains two
    # samples at 8 slices for every one at 32 (the recipe of the shipped models, docs/training/)
    for n in counts:
        if n < 1 or n > MAX_NUM_SLICES or (n not in (1, 2) and n % 4):
            raise click.BadParameter(f"slice count {n} must be 1, 2 or a multiple of 4 up to {MAX_NUM_SLICES} (sectors aligned to quadrants)")
    return counts


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset root (tables in DATA/<version>/, scenes split by DATA/splits.json); the 'train' split is used.")
@version_option(help="Name of the table folder (the nuScenes 'version').")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder: last.pt (resumable), model.pt (weights for streamdet-export), metrics.jsonl, config.json. "
                   "New, empty, or a streamdet-train run's (--resume / --overwrite); never inside an input.")
@click.option("--preset", default="small", show_default=True, type=click.Choice(preset_names()), help="Model preset.")
@click.option("--steps", type=click.IntRange(min=1, max=MAX_STEPS), default=None,
              help=f"Optimizer steps of the one-cycle schedule, 1..{MAX_STEPS} (overrides --epochs).")
@click.option("--epochs", type=click.IntRange(min=1, max=MAX_STEPS), default=None,
              help="Passes over the training samples (when --steps is not given). Without both: --max-minutes, else 10.")
@click.option("--batch-size", type=click.IntRange(min=1), default=1, show_default=True,
              help="Samples per process per step; each sample brings all its slices (8 quadrant maps at 8 slices).")
@click.option("--lr", type=FiniteFloatRange(min=0, min_open=True, max=MAX_LR), default=2e-3, show_default=True,
              help=f"Peak learning rate of the one-cycle schedule (AdamW), at most {MAX_LR:g}.")
@click.option("--num-slices", default="8", show_default=True, callback=_parse_slices,
              help="Slice count per sweep, or several separated by commas (each sample draws one entry uniformly, so a "
                   "count given twice is drawn twice as often), e.g. 8,32 or 8,8,32.")
@click.option("--max-slices-per-sample", type=click.IntRange(min=1), default=None,
              help="Train on a random subset of at most this many slices of each sample (default: all of them). A cap: "
                   "with several --num-slices, a sample with fewer slices trains on all of them; more than the largest "
                   "count is refused.")
@click.option("--no-image", is_flag=True, help="Train the LiDAR-only streaming baseline (no camera lane).")
@click.option("--no-crop", is_flag=True,
              help="With --no-image: no quadrant crop, each slice runs on one map of the whole grid (the paper's LiDAR-only baselines' set-up).")
@click.option("--camera-mode", type=click.Choice(CAMERA_MODES), default="all", show_default=True,
              help="all: a quadrant's image BEV comes from every camera, as at run time; overlapping: a slice sees only the cameras overlapping its sector.")
@click.option("--image-warmup", type=FiniteFloatRange(0, 1, max_open=True), default=0.0, show_default=True,
              help="Fraction of the schedule trained with the image lane off (zero image BEV); the cheap LiDAR lane learns first.")
@click.option("--image-class-weight", type=FiniteFloatRange(min=0), default=0.0, show_default=True,
              help="Weight of an image-side loss beside detection: each object's class read linearly from the image BEV at its "
                   "centre (cross-entropy; a training-only classifier, never exported). 0: off.")
@click.option("--camera-dropout", type=FiniteFloatRange(0, 1, max_open=True), default=0.0, show_default=True,
              help="Probability that a training step drops cameras: each sample loses k of its J cameras, k uniform in 1..J, "
                   "lifted from zero features as the runtime lifts a camera without a frame (training/camera_dropout.py). 0: off.")
@click.option("--resume", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Continue from a last.pt written by this command, in its own folder (--out) or a new or empty one, "
                   "on the same data; options not given take the run's values, and only --max-minutes (with "
                   "--steps/--epochs), --log-every, --checkpoint-every, --workers, --amp, --device and --camera-dropout "
                   "may be given other ones. Not with --overwrite.")
@click.option("--overwrite", is_flag=True, help="Train into an --out that already holds a run (model.pt, last.pt, metrics.jsonl), replacing it.")
@click.option("--init", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Start from the weights of this checkpoint with a fresh optimizer and schedule: all of them for the same preset "
                   "(fine-tuning); for another preset, the parts configured alike (image encoder, lifter, pillar net; the rest from "
                   "--seed); or streamdet-train-image's encoder.pt (the image encoder; every other weight from --seed).")
@click.option("--teacher", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Distil from this trained detector (model.pt, last.pt or shipped weights; any preset whose head makes the same "
                   "maps): its heatmap and boxes become soft targets beside the labels (training/distill.py).")
@click.option("--distill-weight", type=FiniteFloatRange(min=0), default=1.0, show_default=True,
              help="Weight of the distillation loss beside the CenterPoint loss (needs --teacher).")
@click.option("--freeze-camera-lane", is_flag=True,
              help="Keep the image encoder and lifter as --init gave them (no gradient, fixed BatchNorm statistics); with a "
                   "--teacher of the same camera lane one lift per step serves both.")
@click.option("--balanced", is_flag=True, help="Class-balanced (CBGS) resampling of the training samples.")
@click.option("--workers", type=click.IntRange(min=0, max=MAX_WORKERS), default=0, show_default=True,
              help=f"DataLoader worker processes, 0..{MAX_WORKERS} (each a forked process).")
@click.option("--seed", type=click.IntRange(min=0, max=MAX_SEED), default=0, show_default=True,
              help=f"Seed of the weights and of the data order, 0..{MAX_SEED}.")
@click.option("--max-minutes", type=FiniteFloatRange(min=0, min_open=True, max=MAX_MINUTES), default=None,
              help="With --steps/--epochs: stop with a checkpoint after this much wall time of this invocation (--resume gets it again). Alone: the one-cycle "
                   "schedule runs over this much wall time (for a fixed budget on a shared machine; not step-reproducible). At most 7 days.")
@click.option("--amp", type=click.Choice(AMP_MODES), default="auto", show_default=True,
              help="Autocast: auto = fp16 on CUDA, off on CPU.")
@click.option("--cache-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Keep decoded, resized images and sweeps here as .npy, reused by the next run; a cache rebuilt for changed data "
                   "removes the one it replaces (default: DATA/.streamdet_cache).")
@click.option("--device", default=None, callback=device_callback,
              help=f"torch device: {DEVICE_HELP} (default: cuda if available, else cpu).")
@click.option("--log-every", type=click.IntRange(min=1), default=10, show_default=True, help="Steps between progress lines.")
@click.option("--checkpoint-every", type=click.IntRange(min=1), default=200, show_default=True, help="Steps between rewrites of last.pt.")
def main(data_dir: Path, version: str, out_dir: Path, preset: str, steps: int | None, epochs: int, batch_size: int,
         lr: float, num_slices: tuple[int, ...], max_slices_per_sample: int | None, no_image: bool, no_crop: bool, camera_mode: str,
         image_warmup: float, image_class_weight: float, camera_dropout: float, resume: Path | None, overwrite: bool, init: Path | None, teacher: Path | None, distill_weight: float,
         freeze_camera_lane: bool, balanced: bool, workers: int, seed: int, max_minutes: float | None, amp: str,
         cache_dir: Path | None, device: str | None, log_every: int, checkpoint_every: int) -> None:  # fmt: skip
    """Train the streaming camera + LiDAR detector (or its LiDAR-only baseline) with CenterPoint targets."""
    if not (data_dir / version).is_dir():
        raise click.ClickException(f"--data {data_dir}: no table folder {data_dir / version} (is --version right?)")
    if resume is not None and not resume.is_file():
        raise click.ClickException(f"--resume {resume} {not_a_file(resume)}")
    if resume is not None and overwrite:
        raise click.UsageError("--resume continues a run in its folder and --overwrite replaces one: give only one of them")
    if resume is not None:  # the options not given are the run's own: --resume alone continues it
        ctx = click.get_current_context()
        values = _resumed_options(ctx, resume)
        ctx.params.update(values)  # what _check_combinations reads
        (preset, no_image, no_crop, steps, epochs, batch_size, lr, num_slices, max_slices_per_sample, camera_mode,
         image_warmup, image_class_weight, camera_dropout, teacher, distill_weight, freeze_camera_lane, balanced, workers,
         seed, max_minutes, amp, log_every, checkpoint_every) = (values[name] for name, _ in TRAIN_RESUME_PARAMS)  # fmt: skip
    if init is not None and not init.is_file():
        raise click.ClickException(f"--init {init} {not_a_file(init)}")
    if teacher is not None and not teacher.is_file():
        raise click.ClickException(f"--teacher {teacher} {not_a_file(teacher)}")
    if freeze_camera_lane and init is None and resume is None:
        raise click.ClickException("--freeze-camera-lane keeps the camera lane --init gives: add --init WEIGHTS")
    if init is not None and resume is not None:
        raise click.ClickException("--init and --resume exclude each other: --resume continues a run, --init starts one from weights")
    _check_combinations(teacher, distill_weight, num_slices, max_slices_per_sample, no_image, no_crop)
    if cache_dir is not None:
        _check_cache_dir(cache_dir, data_dir, version)
        _check_cache_folder(cache_dir, "--cache-dir")
    else:
        cache_dir = data_dir / ".streamdet_cache"
        _check_cache_folder(cache_dir, "--cache-dir (the default, DATA/.streamdet_cache)")
    # the dataset's symlinked entries too (its table folder above all): a run beside a link's target is in the dataset
    refuse_out_over_inputs(out_dir, [*dataset_inputs(data_dir), ("--init", init), ("--resume", resume), ("--teacher", teacher),
                                     ("--cache-dir", cache_dir)])  # fmt: skip
    refuse_overwrite_of_inputs(out_dir, overwrite, RUN_FILES, [("--init", init), ("--teacher", teacher)])
    if steps is None and epochs is None and max_minutes is None:  # a resume has taken its run's plan by now
        epochs = 10
    try:
        config = TrainConfig(
            preset=preset, use_image=not no_image, slice_crop=not no_crop, steps=steps, epochs=epochs, batch_size=batch_size, lr=lr, amp=amp,
            image_warmup=image_warmup, image_class_weight=image_class_weight, camera_dropout=camera_dropout, balanced=balanced, workers=workers, seed=seed, max_minutes=max_minutes, log_every=log_every,
            checkpoint_every=checkpoint_every, teacher=str(teacher) if teacher is not None else None,
            distill_weight=distill_weight, freeze_camera_lane=freeze_camera_lane,
            data=DataConfig(num_slices=num_slices, max_slices_per_sample=max_slices_per_sample, camera_mode=camera_mode),
        )  # fmt: skip
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    finished = False
    try:
        # progress and notes on stderr; the lines that describe the run (what it trains, how it ended) on stdout
        train(config, data_dir, out_dir, version=version, resume=resume, init=init, cache_dir=cache_dir, device=device,
              echo=progress_echo, overwrite=overwrite, report=click.echo)  # fmt: skip
        finished = True
    except (ValueError, FileNotFoundError) as e:
        raise click.ClickException(first_line(e)) from None
    finally:
        shutdown_distributed(wait=finished)


def _resumed_options(ctx: click.Context, resume: Path) -> dict[str, Any]:
    """``take_resume_options`` of streamdet-train with the checkpoint's config; a file that cannot be read or holds
    no config (model.pt) leaves the options as given: the trainer says what it is."""
    try:
        # only its config is wanted here, and the trainer reads the whole file next: the tensors are mapped, not read
        state = check_checkpoint(read_torch_file(resume, "resume checkpoint", mmap=True), resume, "resume checkpoint")
    except ValueError:  # the trainer says what is wrong with it, after its checks of --out (the order they always had)
        state = {}
    was = state.get("config") if isinstance(state, dict) else None
    if not isinstance(was, dict):
        return {name: ctx.params[name] for name, _ in TRAIN_RESUME_PARAMS}
    return take_resume_options(ctx, resume, saved_config_values(was), TRAIN_RESUME_PARAMS, _train_may_change)


if __name__ == "__main__":
    main()
