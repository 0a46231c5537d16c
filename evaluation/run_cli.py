"""`streamdet-run`: the onnxruntime detector on the bundled real nuScenes sample (or a sample in the same layout).

It lives beside ``streamdet-eval`` because it writes the sample's detections as a nuScenes results file; the sample
goes through the runtime as every tool feeds it (``runtime_ort.pipeline.detect_sample``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click
import numpy as np

from streamdet.cli_utils import (
    MAX_SLICES, PRECISION_CHOICES, check_folder_creatable, check_output_parent, check_results_folder, image_precision_option,
    providers_option, refuse_image_lane_options, refuse_output_over_inputs, require_export_dir, slices_callback)
from streamdet.runtime_ort.stats import format_latency
from streamdet.core import constants

DEFAULT_EXPORT_DIR = Path(constants.DEFAULT_EXPORT_DIR)
RESULTS_NAME = "results_nusc.json"
BEV_NAME = "bev.png"


def dataset_root(folder: Path) -> str | None:
    """What ``folder`` is when it is a nuScenes-format dataset root, as streamdet-synth tells one (``survey_root``:
    its splits.json, world.json, trajectories.npz or a table folder), else None. The results folders of run, eval
    and replay (``check_results_folder``) refuse one: a file of theirs there made `streamdet-synth --overwrite`
    refuse the dataset as holding other files, and sits among what the readers list."""
    from streamdet.data.synth_writer import LAYOUT_DIRS, survey_root  # only for a folder that exists

    try:
        marks = [e.name + ("/" if e.is_dir() else "") for e in survey_root(folder).dataset if e.name not in LAYOUT_DIRS]
    except OSError:  # unreadable: the write says why
        return None
    return f"a dataset ({', '.join(marks)})" if marks else None


# The folders a results folder must not be (besides an export, which check_results_folder knows). A training run is
# not among them: training/run_dir.py recognises one, and evaluation must not import the training side.
OTHER_TOOLS_FOLDERS = (dataset_root,)


def export_reads_images(export_dir: Path) -> bool | None:
    """The export's modality for ``cli_utils.refuse_image_lane_options`` (run, eval, bag run and replay): its manifest
    preset's use_image, or None when ``export_dir`` holds no readable manifest (the tool's own opening of the export
    then says what is wrong, as without the options). Only the manifest is read: the detector verifies the files."""
    from streamdet.runtime_ort.manifest import ManifestError, read_manifest

    try:
        return read_manifest(export_dir, verify_files=False).use_image
    except ManifestError:
        return None


def check_out_dir(out_dir: Path, inputs: list[tuple[str, Path | None]]) -> None:
    """Before any work: --out and the two files written in it (results_nusc.json, bev.png) must not be, lie inside
    or link into an input (``inputs``: option, path pairs), --out must be a folder or creatable as one, and each file
    a regular file or absent (a FIFO there would block the write, a folder fail it after the whole run)."""
    refuse_output_over_inputs(out_dir, "--out", inputs)
    check_folder_creatable(out_dir, "--out")
    if out_dir.is_dir():
        for name in (RESULTS_NAME, BEV_NAME):
            path = out_dir / name
            try:
                refuse_output_over_inputs(path, "--out", inputs)  # OUT/bev.png -> EXPORT/lut.npz
                check_output_parent(path, "--out")
            except click.BadParameter as e:  # the shared checks name the path first: say which file of --out it is
                shown = f"{str(path)!r} "
                reason = "it " + e.message[len(shown):] if e.message.startswith(shown) else e.message
                raise click.BadParameter(f"cannot write {path}: {reason}", param_hint="--out") from None
    else:  # made after the run: the highest folder of it that is missing must be creatable where it goes
        absolute = out_dir.absolute()
        missing = next((p for p in reversed([absolute, *absolute.parents]) if not p.exists()), None)
        if missing is not None:
            check_output_parent(missing, "--out")
    # last: the note that an earlier run's files are replaced comes only once nothing else is refused
    check_results_folder(out_dir, "--out", (RESULTS_NAME, BEV_NAME), "streamdet-run output", OTHER_TOOLS_FOLDERS)


def run_sample(
    export_dir: Path, sample_dir: Path | None, num_slices: int | None, out_dir: Path, precision: str,
    image_precision: str | None = None, providers: tuple[str, ...] | None = None,
) -> dict:
    """Detect every slice of one sample through the runtime; write results JSON and a BEV picture. Returns a summary."""
    import cv2

    from streamdet.core.classes import CLASS_NAMES
    from streamdet.data.preview import draw_bev
    from streamdet.data.sample import load_bundled_sample
    from streamdet.evaluation.results import boxes_to_results, write_results_json
    from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
    from streamdet.runtime_ort.pipeline import detect_sample

    from streamdet.core.cpu import cpu_info
    from streamdet.core.file_output import atomic_write_file

    cpu = cpu_info()  # before any work: a CPUID mask variable not in effect is refused here
    sample = load_bundled_sample(sample_dir)
    config = DetectorConfig(precision=precision, image_lane_precision=image_precision, num_slices=num_slices, providers=providers)
    det = StreamingDetector(export_dir, config)
    # A LiDAR-only export (the streaming baseline) has no image lane: the sample's images are not read.
    run = detect_sample(det, sample)
    missing = () if run.images is None else run.images.cameras_missing
    n = det.num_slices
    slices = run.sweep.points
    results = run.sweep.slices
    merged = run.detections

    entries = boxes_to_results(sample.token, merged.boxes, merged.scores, merged.labels, sample.lidar2ego, sample.ego2global)
    results_path = out_dir / RESULTS_NAME
    slice_of_point = np.concatenate([np.full(len(p), k) for k, p in enumerate(slices)])
    pts = np.concatenate(slices)
    picture = draw_bev(
        pts[:, :5] if pts.shape[1] > 5 else pts,
        boxes=sample.gt_boxes,
        labels=sample.gt_labels,
        slice_of_point=slice_of_point,
        n_slices=n,
        det_boxes=merged.boxes,
        det_scores=merged.scores,
    )
    png_path = out_dir / BEV_NAME
    # encoded before anything is written (cv2 reports a failure only by its return value), then both files written
    # atomically: a reader never sees half a file, and a link at either path is replaced, never written through
    try:
        encoded, png = cv2.imencode(".png", picture)
    except cv2.error as e:
        raise OSError(f"cannot encode {png_path}: {e}") from None
    if not encoded:
        raise OSError(f"cannot encode {png_path} as PNG")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_results_json(results_path, {sample.token: entries}, {"use_camera": det.uses_images, "use_lidar": True})
    try:
        atomic_write_file(png_path, lambda f: f.write(png.tobytes()))
    except OSError as e:
        raise OSError(f"cannot write {png_path}: {e.strerror or e}; {results_path} was written") from None
    counts = {CLASS_NAMES[c]: int((merged.labels == c).sum()) for c in np.unique(merged.labels)}
    return {
        "sample": sample.token,
        "num_slices": n,
        "precision": det.precision_label,
        "providers": list(det.providers),
        "cpu": cpu,
        "uses_images": det.uses_images,
        "cameras_missing": list(missing),
        "detections": len(merged),
        "per_class": counts,
        "per_slice": [len(r.detections) for r in results],
        "latency_ms": det.stats.summary(),
        "results_json": str(results_path),
        "bev_png": str(png_path),
    }


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--export-dir", type=click.Path(path_type=Path), default=DEFAULT_EXPORT_DIR, show_default=True,
              help="Export directory written by streamdet-export (holds manifest.json).")
@click.option("--sample", "sample_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="A sample folder in the bundled layout (calibration.json, boxes.json, .pcd.bin, CAM_*.jpg). "
                   "Default: the bundled real nuScenes sample.")
@click.option("--slices", "num_slices", type=click.IntRange(1, MAX_SLICES), default=None, callback=slices_callback,
              help=f"Slices per sweep (1, 2 or a multiple of 4, up to {MAX_SLICES}). Default: the number the export was "
                   "made for.")
@click.option("--precision", type=click.Choice(PRECISION_CHOICES), default="fp32", show_default=True,
              help="Which graphs of the export to run.")
@image_precision_option()
@providers_option()
@click.option("--out", "out_dir", type=click.Path(path_type=Path, file_okay=False), default=Path("out") / "run",
              show_default=True, help="Where to write results_nusc.json and bev.png. An earlier run's files there are replaced (a "
              "note on stderr says so); an export or a dataset folder is refused.")
@click.option("-v", "--verbose", is_flag=True, help="Log providers and sessions.")
def main(
    export_dir: Path, sample_dir: Path | None, num_slices: int | None, precision: str, image_precision: str | None,
    providers: tuple[str, ...] | None, out_dir: Path, verbose: bool,
) -> None:
    """Run the streaming detector (onnxruntime, no PyTorch) on one sample: every slice, then the sweep merged."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")
    require_export_dir(export_dir)
    refuse_image_lane_options(click.get_current_context(), export_dir, ("image_precision",), export_reads_images)
    from streamdet.data.sample import bundled_sample_dir

    # --out inside the sample (the bundled one by default) or the export would add files to what others read; a
    # FIFO or a link into an input at OUT/bev.png or OUT/results_nusc.json is refused now, not after the run
    check_out_dir(out_dir, [("--export-dir", export_dir), ("--sample", sample_dir or bundled_sample_dir())])
    try:
        summary = run_sample(export_dir, sample_dir, num_slices, out_dir, precision, image_precision, providers)
    except (ValueError, KeyError, FileNotFoundError, OSError) as e:
        raise click.ClickException(str(e)) from None
    except MemoryError:  # not an input error to run_edge: say what ran out, not a traceback
        raise click.ClickException(f"out of memory running {export_dir} on the sample: try fewer --slices") from None
    click.echo(
        f"sample {summary['sample']}: {summary['detections']} detections over {summary['num_slices']} slices "
        f"({summary['precision']}, {', '.join(summary['providers'])}{'' if summary['uses_images'] else ', LiDAR only: no images used'})"
    )
    from streamdet.core.cpu import cpu_line

    click.echo(f"CPU: {cpu_line(summary['cpu'])}")
    if summary["cameras_missing"]:
        click.echo(f"cameras missing (zero features): {summary['cameras_missing']}")
    click.echo("per class: " + (json.dumps(summary["per_class"]) if summary["per_class"] else "none"))
    click.echo("per slice: " + " ".join(map(str, summary["per_slice"])))
    click.echo(format_latency(summary["latency_ms"]))
    click.echo(f"wrote {summary['results_json']}")
    click.echo(f"wrote {summary['bev_png']}")
