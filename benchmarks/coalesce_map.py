"""Offline mAP of coalesced slices (`LaneConfig.coalesce_slices`): a dataset's val split detected with every slice in
its own slice-graph run and with runs of R consecutive slices of one quadrant (what the slice lane does when it has
fallen behind), every sample's images fed at its own time (no clock: what coalescing does to accuracy).

    python -m streamdet.benchmarks.coalesce_map --data DATA --export-dir EXPORT [--runs 1,2] [--split all] [--samples N]

Results: docs/replay.md, "Coalesced slices".
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.evaluation.dataset_eval import evaluate_dataset
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.pipeline import sample_images, sample_time_s
from streamdet.runtime_ort.postprocess import aggregate_sweep


def runs_of(num_slices: int, most: int, start_deg: float = 0.0) -> list[list[int]]:
    """Slices 0..n-1 in scan order grouped into runs of at most ``most`` consecutive slices of one quadrant."""
    runs: list[list[int]] = []
    for k in range(num_slices):
        q = quadrants_of_sector(k, num_slices, start_deg)
        if runs and len(runs[-1]) < most and quadrants_of_sector(runs[-1][-1], num_slices, start_deg) == q:
            runs[-1].append(k)
        else:
            runs.append([k])
    return runs


def sweep_detector(export_dir: Path, image_precision: str | None, precision: str, num_slices: int, most: int):
    """``sample -> Detections``: the sample's images as one update, then its sweep in ``num_slices`` slices detected
    in runs of up to ``most`` slices."""
    det = StreamingDetector(export_dir, DetectorConfig(precision=precision, image_lane_precision=image_precision))
    runs = runs_of(num_slices, most, det.config.start_deg)

    def detect(sample):
        ts = sample_time_s(sample)
        if det.uses_images:
            det.update_images(sample_images(det, sample), ts)
        slices = split_sweep(np.asarray(sample.points, np.float32), num_slices, det.config.start_deg)
        results = [r for run in runs for r in det.detect_slices([slices[k] for k in run], run, [ts] * len(run), num_slices)]
        return aggregate_sweep([r.detections for r in results], det.config.nms)

    return detect


def _runs(ctx, param, value: str) -> tuple[int, ...]:
    try:
        out = tuple(int(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"a comma-separated list of ints >= 1, got {value!r}") from None
    if not out or min(out) < 1:
        raise click.BadParameter(f"a comma-separated list of ints >= 1, got {value!r}")
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", type=click.Path(path_type=Path, file_okay=False, exists=True), required=True,
              help="nuScenes-format dataset root with splits.json.")
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False, exists=True), required=True,
              help="The export to run.")
@click.option("--precision", type=click.Choice(["fp32", "fp16", "int8"]), default="fp32", show_default=True,
              help="The slice graph's precision.")
@click.option("--image-precision", type=click.Choice(["fp32", "int8"]), default="fp32", show_default=True,
              help="The image lane's graphs.")
@click.option("--slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices per sweep.")
@click.option("--runs", default="1,2", show_default=True, callback=_runs,
              help="Comma-separated: the most slices per run to score (1: every slice alone).")
@click.option("--split", type=click.Choice(["val", "train", "all"]), default="val", show_default=True,
              help="Which samples of the dataset's splits.json to score (all: every sample).")
@click.option("--samples", type=click.IntRange(min=1), default=None, help="Only the first N samples of the split.")
def main(data: Path, export_dir: Path, precision: str, image_precision: str, slices: int, runs: tuple[int, ...],
         split: str, samples: int | None) -> None:  # fmt: skip
    """Offline mAP / NDS of a split with slices detected alone and in coalesced runs."""
    if not (export_dir / "manifest.json").is_file():
        raise click.ClickException(f"{export_dir} holds no manifest.json")
    click.echo(f"{data} ({split} split), {export_dir}, {slices} slices, {image_precision} image lane + {precision} slices:")
    for most in runs:
        try:
            detect = sweep_detector(export_dir, image_precision, precision, slices, most)
            ev = evaluate_dataset(detect, data, split=None if split == "all" else split, max_samples=samples)
        except ValueError as e:
            raise click.ClickException(str(e)) from None
        m = ev.metrics
        click.echo(f"runs of up to {most} slice(s): {ev.num_samples} samples, mAP {100 * m.mean_ap:.2f}, NDS {100 * m.nd_score:.2f}")


if __name__ == "__main__":
    main()
