"""``streamdet-train-image``: pretrain the image encoder on the synthetic world's masks (``training/image_pretrain``).

Then ``streamdet-train --preset P --init OUT/detector_init.pt`` trains the detector from the pretrained encoder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from streamdet.cli_utils import FiniteFloatRange, dataset_inputs, not_a_file, version_option
from streamdet.core.errors import first_line
from streamdet.models.presets import preset_names
from streamdet.training.checkpoint import read_torch_file
from streamdet.training.cli import DEVICE_HELP, device_callback, progress_echo, refuse_out_over_inputs, take_resume_options
from streamdet.training.image_pretrain import PRETRAIN_RESUME_MAY_CHANGE, PretrainConfig, pretrain
from streamdet.training.train_config import MAX_LR, MAX_MINUTES, MAX_SEED, MAX_STEPS


def _check_stop_at_step(stop_at_step: int | None, steps: int) -> None:
    """A cut past the end of the schedule never happens: the run would silently train all --steps instead."""
    if stop_at_step is not None and stop_at_step > steps:
        raise click.BadParameter(f"{stop_at_step} is past the end of the --steps {steps} schedule: give at most {steps}",
                                 param_hint="--stop-at-step")  # fmt: skip


# The options a --resume takes from its checkpoint's config where they are not given (each named as its PretrainConfig
# field). --stop-at-step is not among them: the run's own cut lies at or before the step it resumes from.
PRETRAIN_RESUME_PARAMS = tuple((name, name) for name in ("preset", "steps", "batch_size", "lr", "range_m", "seed",
                                                         "eval_every", "checkpoint_every", "max_minutes"))  # fmt: skip


def _resumed_options(ctx: click.Context, resume: Path) -> dict[str, Any]:
    """The options of a --resume (``training.cli.take_resume_options``); a file that cannot be read or is no
    streamdet-train-image last.pt leaves the options as given: ``pretrain`` says what it is."""
    try:
        state = read_torch_file(resume, "--resume checkpoint", mmap=True)  # its config only: the tensors are mapped
    except ValueError:  # pretrain says what is wrong with it, after its checks of --out (the order they always had)
        state = None
    was = state.get("config") if isinstance(state, dict) and "preset" not in state else None
    if not isinstance(was, dict):
        return {name: ctx.params[name] for name, _ in PRETRAIN_RESUME_PARAMS}
    return take_resume_options(ctx, resume, was, PRETRAIN_RESUME_PARAMS, lambda key, _values: key in PRETRAIN_RESUME_MAY_CHANGE)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset root written by streamdet-synth (world version 2: images with .mask.npz beside them).")
@version_option(help="Name of the table folder.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder: last.pt, encoder.pt, detector_init.pt, metrics.jsonl, result.json, config.json. New, "
                   "empty, or a streamdet-train-image run's (--resume / --overwrite); never inside an input.")
@click.option("--preset", default="small", show_default=True, type=click.Choice(preset_names()),
              help="The detector preset whose image encoder is pretrained (its image size is used).")
@click.option("--steps", type=click.IntRange(min=1, max=MAX_STEPS), default=2000, show_default=True,
              help=f"Optimizer steps of the schedule, 1..{MAX_STEPS}.")
@click.option("--batch-size", type=click.IntRange(min=1), default=8, show_default=True, help="Images per step.")
@click.option("--lr", type=FiniteFloatRange(min=0, min_open=True, max=MAX_LR), default=2e-3, show_default=True,
              help=f"Peak AdamW learning rate, at most {MAX_LR:g}.")
@click.option("--range", "range_m", type=FiniteFloatRange(min=0, min_open=True), default=30.0, show_default=True,
              help="Evaluation: objects within this distance (m) count toward the mIoU.")
@click.option("--eval-every", type=click.IntRange(min=1), default=250, show_default=True, help="Steps between val mIoU evaluations.")
@click.option("--checkpoint-every", type=click.IntRange(min=1), default=100, show_default=True, help="Steps between checkpoints.")
@click.option("--seed", type=click.IntRange(min=0, max=MAX_SEED), default=0, show_default=True,
              help=f"Seed of the weights and the batches, 0..{MAX_SEED}.")
@click.option("--max-minutes", type=FiniteFloatRange(min=0, min_open=True, max=MAX_MINUTES), default=None,
              help="Stop with a checkpoint after this much wall time (at most 7 days); --resume continues the same schedule.")
@click.option("--stop-at-step", type=click.IntRange(min=1, max=MAX_STEPS), default=None,
              help="Stop with a checkpoint once this many steps of the --steps schedule are done (a session cut that, "
                   "unlike --max-minutes, is the same on every machine; at most --steps); --resume continues the same "
                   "schedule.")
@click.option("--resume", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Continue from a last.pt written by this command, in its own folder (--out) or a new or empty one, "
                   "on the same images; options not given take the run's values (not --stop-at-step), and only "
                   "--max-minutes, --stop-at-step, --eval-every, --checkpoint-every and --device may be given other "
                   "ones. Not with --overwrite.")
@click.option("--overwrite", is_flag=True,
              help="Pretrain into an --out that already holds a run (last.pt, encoder.pt, metrics.jsonl, ...), replacing it.")
@click.option("--max-samples", type=click.IntRange(min=1), default=None, help="Use only the first N samples of each split (tests).")
@click.option("--device", default="cpu", show_default=True, callback=device_callback, help=f"torch device: {DEVICE_HELP}.")
def main(data_dir: Path, version: str, out_dir: Path, preset: str, steps: int, batch_size: int, lr: float,
         range_m: float, eval_every: int, checkpoint_every: int, seed: int, max_minutes: float | None,
         stop_at_step: int | None, resume: Path | None, overwrite: bool, max_samples: int | None, device: str) -> None:  # fmt: skip
    """Pretrain the detector's image encoder with a segmentation head on per-pixel class masks; report val mIoU."""
    if not (data_dir / version).is_dir():
        raise click.ClickException(f"--data {data_dir}: no table folder {data_dir / version} (is --version right?)")
    if resume is not None and not resume.is_file():
        raise click.ClickException(f"--resume {resume} {not_a_file(resume)}")
    if resume is not None and overwrite:
        raise click.UsageError("--resume continues a run in its folder and --overwrite replaces one: give only one of them")
    if resume is not None:  # the options not given are the run's own: --resume alone continues it
        values = _resumed_options(click.get_current_context(), resume)
        preset, steps, batch_size, lr, range_m, seed, eval_every, checkpoint_every, max_minutes = (
            values[name] for name, _ in PRETRAIN_RESUME_PARAMS)  # fmt: skip
    _check_stop_at_step(stop_at_step, steps)
    # the dataset's symlinked entries too (its table folder above all): a run beside a link's target is in the dataset
    refuse_out_over_inputs(out_dir, [*dataset_inputs(data_dir), ("--resume", resume)])
    try:
        config = PretrainConfig(preset=preset, steps=steps, batch_size=batch_size, lr=lr, range_m=range_m,
                                eval_every=eval_every, checkpoint_every=checkpoint_every, seed=seed, max_minutes=max_minutes,
                                stop_at_step=stop_at_step)  # fmt: skip
        # progress and notes on stderr; the lines that describe the run (its images, how it ended) on stdout
        pretrain(config, data_dir, out_dir, version=version, resume=resume, device=device, echo=progress_echo,
                 max_samples=max_samples, overwrite=overwrite, report=click.echo)  # fmt: skip
    except (ValueError, FileNotFoundError, KeyError) as e:
        raise click.ClickException(first_line(e)) from None


if __name__ == "__main__":
    main()
