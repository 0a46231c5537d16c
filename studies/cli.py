"""``streamdet-study``: the robustness studies of ``streamdet.studies`` from the command line.

``streamdet-study slices|drop-camera|calib-noise|resolution [--export-dir DIR | --checkpoint FILE] --data DIR
[--json PATH] [--plot PATH]`` prints the study's table, and writes every figure as JSON and a PNG plot
(matplotlib, Agg backend) where asked. Only ``--checkpoint`` / ``--baseline-checkpoint`` need PyTorch.
"""

from __future__ import annotations

import contextlib
import math
import re
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import click

from streamdet import studies as st
from streamdet.calibration.camera import MAX_CAMERA_OFFSET_M
from streamdet.cli_utils import (
    MAX_INTRA_OP_THREADS,
    MAX_SLICES,
    check_output_parent,
    check_plot_format,
    image_precision_option,
    json_output_option,
    providers_option,
    refuse_output_over_inputs,
    refuse_same_outputs,
    write_json_output,
    resolution_callback,
    split_list,

    version_option,
    dataset_inputs,
    require_export_dir,
)
from streamdet.core import constants
from streamdet.core.constants import PRECISIONS
from streamdet.core.sectors import check_num_slices
from streamdet.core.errors import first_line
from streamdet.progress import counted
from streamdet.studies.plots import plot_calib_noise, plot_drop_camera, plot_resolution, plot_slices

DEFAULT_EXPORT_DIR = Path(constants.DEFAULT_EXPORT_DIR)
ALL_SPLIT = "all"  # --split value that scores every sample of the dataset
# --seeds: each seed rebuilds the LUT and scores the split once per level; 1000 is far past a mean and std worth
# reporting, and 10^8 ran for days.
MAX_SEEDS = 1000
# --level's translation bound holds per axis, so a camera moves by up to sqrt(3) times it; the calibration checks
# refuse a camera more than MAX_CAMERA_OFFSET_M from the LiDAR, which `--level 1,1e308` hit only mid-study. Half
# that offset keeps every noisy camera inside it, with room for the rig's own camera-to-LiDAR distances.
MAX_NOISE_TRANSLATION_CM = 100.0 * MAX_CAMERA_OFFSET_M / 2


# ---- option parsing ----------------------------------------------------------------------------------------


def _slice_count(text: str) -> int:
    shown = text if len(text) <= 30 else text[:27] + "..."
    # ASCII digits only: int() also takes '8_000' and non-ASCII digits such as '٨', which no one means as a count
    if not re.fullmatch(r"[+-]?[0-9]+", text):
        raise click.BadParameter(f"expected comma-separated integers such as 1,4,8,16,32, got {shown!r}", param_hint="--counts")
    if len(text) > 12 or not 1 <= int(text) <= MAX_SLICES:
        raise click.BadParameter(f"slice count {shown} is not in 1..{MAX_SLICES}", param_hint="--counts")
    try:  # 6 is a usage error here, as `--slices 6` is in every tool, not a study that fails (exit 1)
        check_num_slices(int(text))
    except ValueError as e:
        raise click.BadParameter(f"slice count {shown}: {e}", param_hint="--counts") from None
    return int(text)


def _parse_ints(ctx, param, value: str) -> tuple[int, ...]:
    # "8,,16" or "8,08": an empty or repeated count (two identical columns whose JSON keys collide) is refused
    entries = split_list(value, "--counts", "slice count", key=_slice_count)
    return tuple(_slice_count(v) for v in entries)


_RESOLUTIONS = resolution_callback(min_px=16, max_px=4096)


def _parse_cameras(ctx, param, values: tuple[str, ...]) -> tuple[str, ...]:
    # a camera named twice would be scored twice under one JSON key: a usage error naming the option, before any work
    for k, name in enumerate(values):
        if name in values[:k]:
            raise click.BadParameter(f"camera {name!r} is given twice (each --camera is dropped once, on its own)",
                                     param_hint="--camera")  # fmt: skip
    return values


def _parse_resolutions(ctx, param, values: tuple[str, ...]) -> tuple[tuple[int, int], ...]:
    return _RESOLUTIONS(ctx, param, values) if values else st.DEFAULT_RESOLUTIONS


def _parse_levels(ctx, param, values: tuple[str, ...]) -> tuple[tuple[float, float], ...]:
    if not values:
        return st.DEFAULT_NOISE_LEVELS
    levels = []
    for text in values:
        try:
            deg, cm = (float(v) for v in text.split(","))
        except ValueError:
            raise click.BadParameter(f"expected DEG,CM such as 1,10, got {text!r}") from None
        if not (math.isfinite(deg) and math.isfinite(cm) and 0 <= deg < 180 and 0 <= cm <= MAX_NOISE_TRANSLATION_CM):
            raise click.BadParameter(f"angle must be in [0, 180) deg and translation in [0, {MAX_NOISE_TRANSLATION_CM:g}] "
                                     f"cm, got {text!r}")  # fmt: skip
        if (deg, cm / 100.0) in levels:  # the same level twice: two identical rows, twice the run time
            raise click.BadParameter(f"level {text!r} is given twice")
        levels.append((deg, cm / 100.0))
    return tuple(levels)


def _common(f: Callable) -> Callable:
    """Options every study takes: which model, which data, where the figures go."""
    options = [
        click.option("--export-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
                     help=f"Export directory made by streamdet-export (default {DEFAULT_EXPORT_DIR})."),
        click.option("--checkpoint", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="Camera + LiDAR checkpoint to export into a temporary directory first (needs PyTorch); "
                          "instead of --export-dir."),
        click.option("--data", "data_dir", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
                     help="Dataset root in the nuScenes layout (e.g. written by streamdet-synth)."),
        version_option(),
        click.option("--split", default="val", show_default=True,
                     help=f"Split of DATA/splits.json to score, or '{ALL_SPLIT}' for every sample."),
        click.option("--max-samples", type=click.IntRange(min=1), default=None,
                     help="Score only the first N samples of the split (bounds the run time)."),
        click.option("--precision", type=click.Choice(PRECISIONS), default="fp32", show_default=True,
                     help="Graphs to run; the export must hold them."),
        image_precision_option(),
        providers_option(),
        click.option("--threads", type=click.IntRange(1, MAX_INTRA_OP_THREADS), default=1, show_default=True,
                     help=f"Intra-op threads of each onnxruntime session, 1..{MAX_INTRA_OP_THREADS}: per session, not in "
                          "all (every session keeps its own pool; the studies run the lanes one after the other)."),
        json_output_option("Write every figure of the study here as JSON."),
        click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="Write a PNG plot of the study here."),
    ]  # fmt: skip
    for option in reversed(options):
        f = option(f)
    return f


def _slices_option(f: Callable) -> Callable:
    return click.option("--slices", "num_slices", type=click.IntRange(1, MAX_SLICES), default=None,
                        help=f"Slices per sweep (1, 2 or a multiple of 4, up to {MAX_SLICES}); default the export's.")(f)  # fmt: skip


# ---- running -----------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _running(label: str) -> Iterator[Callable[[int, int], None]]:
    """A progress bar over samples, opened on the first report (the sample count is known only then), and the
    library's errors as one-line click errors."""
    try:
        with counted(label) as progress:
            yield progress
    except st.StudyError as e:
        raise click.ClickException(str(e)) from None
    except (OSError, ValueError) as e:  # unreadable data: missing tables or files, a bad split
        raise click.ClickException(first_line(e)) from None
    except MemoryError:  # not an input error to run_edge: say what ran out, not a traceback
        raise click.ClickException(f"{label}: out of memory: try fewer or smaller slice counts, or --max-samples") from None


@contextlib.contextmanager
def _export(export_dir: Path | None, checkpoint: Path | None, runtime: st.RuntimeOptions) -> Iterator[Path]:
    """The export directory to run: the given one, the default, or a temporary export of --checkpoint."""
    if export_dir is not None and checkpoint is not None:
        raise click.UsageError("give --export-dir or --checkpoint, not both")
    if checkpoint is None:
        path = export_dir if export_dir is not None else DEFAULT_EXPORT_DIR
        require_export_dir(path, f"not an export directory (make it with `streamdet-export --out {path}`"
                                 + (" or pass --checkpoint)" if export_dir is None else ")"))
        yield path
        return
    if not checkpoint.is_file():
        raise click.BadParameter(f"{checkpoint} does not exist", param_hint="--checkpoint")
    with tempfile.TemporaryDirectory(prefix="streamdet-study-") as tmp:
        click.echo(f"exporting {checkpoint} ({runtime.label}) into a temporary directory ...", err=True)
        try:
            yield st.export_checkpoint(checkpoint, Path(tmp) / "export", runtime.precision, runtime.image_precision)
        except st.StudyError as e:
            raise click.ClickException(str(e)) from None


def _data(data_dir: Path, version: str, split: str, max_samples: int | None) -> st.StudyData:
    return st.StudyData(data_dir, version, None if split == ALL_SPLIT else split, max_samples)




def _check_outputs(json_path: Path | None, plot_path: Path | None, **inputs: Path | None) -> None:
    """Before any work: --json / --plot must not replace an input (``inputs``: option name -> path; the dataset's
    linked entries too, its table folder above all) nor each other, and each needs an existing folder (and --plot a
    format matplotlib writes)."""
    named = [("--" + k.replace("_", "-"), p) for k, p in inputs.items()]
    named += dataset_inputs(inputs.get("data"))[1:]
    refuse_output_over_inputs(json_path, "--json", named)
    refuse_output_over_inputs(plot_path, "--plot", named)
    refuse_same_outputs([("--json", json_path), ("--plot", plot_path)])
    check_output_parent(json_path, "--json")
    check_output_parent(plot_path, "--plot")
    if plot_path is not None:
        check_plot_format(plot_path)


def _inputs(export_dir: Path | None, checkpoint: Path | None, data_dir: Path) -> dict[str, Path | None]:
    """The model and data a study reads (``_export``'s rule: the default export unless --checkpoint is given)."""
    default = DEFAULT_EXPORT_DIR if export_dir is None and checkpoint is None else None
    return {"export_dir": export_dir or default, "checkpoint": checkpoint, "data": data_dir}


def _report(result, json_path: Path | None, plot_path: Path | None, plot: Callable) -> None:
    click.echo(result.format_table())
    if json_path is not None:
        write_json_output(json_path, result.to_dict())
        click.echo(f"wrote {json_path}")
    if plot_path is not None:
        try:
            plot(result, plot_path)
        except (OSError, ValueError) as e:  # ValueError: matplotlib refuses the file's extension
            raise click.ClickException(f"cannot write --plot {plot_path}: {getattr(e, 'strerror', None) or e}") from None
        click.echo(f"wrote {plot_path}")


# ---- commands ----------------------------------------------------------------------------------------------


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Robustness studies of a streaming export on a dataset (the paper's slices, missing camera, calibration
    noise and resolution studies), run through the onnxruntime runtime."""


@main.command()
@_common
@click.option("--counts", "slice_counts", default="1,4,8,16,32", show_default=True, callback=_parse_ints,
              help=f"Slice counts to score, comma-separated, each once (1, 2 or a multiple of 4, up to {MAX_SLICES}).")  # fmt: skip
@click.option("--baseline-export-dir", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="Export of the LiDAR-only baseline, scored beside the fused model.")  # fmt: skip
@click.option("--baseline-checkpoint", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Checkpoint of the LiDAR-only baseline, evaluated with PyTorch (needs PyTorch); or export it with "
                   "streamdet-export --checkpoint and pass --baseline-export-dir.")  # fmt: skip
def slices(export_dir, checkpoint, data_dir, version, split, max_samples, precision, image_precision, providers, threads,
           json_path, plot_path, slice_counts, baseline_export_dir, baseline_checkpoint) -> None:  # fmt: skip
    """mAP at 1, 4, 8, 16, 32 slices: the fused model beside the LiDAR-only baseline (the paper's Table 2)."""
    if baseline_export_dir is not None and baseline_checkpoint is not None:
        raise click.UsageError("give --baseline-export-dir or --baseline-checkpoint, not both")
    _check_outputs(json_path, plot_path, **_inputs(export_dir, checkpoint, data_dir), baseline_export_dir=baseline_export_dir,
                   baseline_checkpoint=baseline_checkpoint)  # fmt: skip
    runtime = st.RuntimeOptions(precision, threads, image_precision, providers)
    with _export(export_dir, checkpoint, runtime) as exp, _running("slices") as bar:
        fused = st.OnnxSlicedDetector(exp, runtime)
        if not fused.uses_images:  # it would be tabled as "fused (ours), PC+RGB"
            raise st.StudyError(f"export {exp} is LiDAR-only (preset use_image=false): pass it as --baseline-export-dir")
        baseline = None
        if baseline_export_dir is not None:
            baseline = st.OnnxSlicedDetector(baseline_export_dir, runtime)
            source = f"--baseline-export-dir {baseline_export_dir}"
        elif baseline_checkpoint is not None:
            baseline = st.torch_sliced_detector(baseline_checkpoint, threads)
            source = f"--baseline-checkpoint {baseline_checkpoint}"
        if baseline is not None and baseline.uses_images:  # it would be tabled as "LiDAR-only baseline, PC"
            raise st.StudyError(f"{source} is a camera + LiDAR model (preset use_image=true): the baseline must be "
                                "LiDAR-only; pass a camera + LiDAR export as --export-dir")  # fmt: skip
        result = st.slices_study(fused, _data(data_dir, version, split, max_samples), slice_counts, baseline, bar)
    _report(result, json_path, plot_path, plot_slices)


@main.command("drop-camera")
@_common
@_slices_option
@click.option("--camera", "cameras", multiple=True, default=(st.DEFAULT_DROPPED_CAMERA,), show_default=True,
              callback=_parse_cameras,
              help="Camera to remove at inference (repeat to study several, each on its own, each once).")  # fmt: skip
@click.option("--no-cameras", is_flag=True,
              help="Also score with every camera missing (the runtime's camera-less BEV): how much the model uses its cameras at all.")
def drop_camera(export_dir, checkpoint, data_dir, version, split, max_samples, precision, image_precision, providers, threads,
                json_path, plot_path, num_slices, cameras, no_cameras) -> None:  # fmt: skip
    """mAP and per-class AP with a named camera missing at inference (the back camera by default)."""
    _check_outputs(json_path, plot_path, **_inputs(export_dir, checkpoint, data_dir))
    runtime = st.RuntimeOptions(precision, threads, image_precision, providers)
    with _export(export_dir, checkpoint, runtime) as exp, _running("drop-camera") as bar:
        result = st.drop_camera_study(exp, _data(data_dir, version, split, max_samples), cameras, runtime, num_slices, bar,
                                      no_cameras)  # fmt: skip
    _report(result, json_path, plot_path, plot_drop_camera)


@main.command("calib-noise")
@_common
@_slices_option
@click.option("--level", "levels", multiple=True, callback=_parse_levels, metavar="DEG,CM",
              help="Noise bound: every Euler angle uniform in +-DEG and every translation axis in +-CM, per camera "
                   f"(repeat; DEG in [0, 180), CM in [0, {MAX_NOISE_TRANSLATION_CM:g}]; default 0.5,5 1,10 2,20 3,30 5,50, "
                   "this tool's choice beside the paper's levels). One draw per sample and seed serves every level, "
                   "scaled to its bound, so levels differ in size only.")  # fmt: skip
@click.option("--seeds", type=click.IntRange(1, MAX_SEEDS), default=3, show_default=True,
              help=f"Seeded draws per level (seeds 0..N-1), 1..{MAX_SEEDS}; mean and std are reported.")  # fmt: skip
def calib_noise(export_dir, checkpoint, data_dir, version, split, max_samples, precision, image_precision, providers, threads,
                json_path, plot_path, num_slices, levels, seeds) -> None:  # fmt: skip
    """mAP under uniform camera-extrinsic noise, the LUT rebuilt for each noisy calibration, the graphs untouched."""
    _check_outputs(json_path, plot_path, **_inputs(export_dir, checkpoint, data_dir))
    runtime = st.RuntimeOptions(precision, threads, image_precision, providers)
    with _export(export_dir, checkpoint, runtime) as exp, _running("calib-noise") as bar:
        result = st.calib_noise_study(exp, _data(data_dir, version, split, max_samples), levels, seeds, runtime, num_slices, bar)
    _report(result, json_path, plot_path, plot_calib_noise)


@main.command()
@_common
@_slices_option
@click.option("--resolution", "resolutions", multiple=True, callback=_parse_resolutions, metavar="WxH",
              help="Image size to feed the encoder (repeat; default 1600x900 1200x675 800x450).")  # fmt: skip
def resolution(export_dir, checkpoint, data_dir, version, split, max_samples, precision, image_precision, providers, threads,
               json_path, plot_path, num_slices, resolutions) -> None:  # fmt: skip
    """mAP and image-lane latency with the camera images resized to each size (same graphs, LUT per size)."""
    _check_outputs(json_path, plot_path, **_inputs(export_dir, checkpoint, data_dir))
    runtime = st.RuntimeOptions(precision, threads, image_precision, providers)
    with _export(export_dir, checkpoint, runtime) as exp, _running("resolution") as bar:
        result = st.resolution_study(exp, _data(data_dir, version, split, max_samples), resolutions, runtime, num_slices, bar)
    _report(result, json_path, plot_path, plot_resolution)


if __name__ == "__main__":
    main()
