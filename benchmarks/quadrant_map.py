"""Offline mAP behind issue 22's accuracy target: a dataset's val split detected with full image updates and with four
per-quadrant updates, each through the lifter graph and from per-camera lifts (``DetectorConfig.camera_terms``), every sample's images fed at its own time (no clock: what the function per
quadrant does to accuracy, not what the schedule's timing does).

    python -m streamdet.benchmarks.quadrant_map --data DATA --export-dir EXPORT [--image-precision int8] [--samples N]

Results: docs/replay.md, "Per-camera lifts in the runtime".
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from streamdet.evaluation.dataset_eval import evaluate_dataset
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.pipeline import sample_images, sample_time_s, update_by_quadrant

VARIANTS = (("full update, lifter graph", False, False), ("per-quadrant, lifter graph", False, True),
            ("full update, per-camera lifts", True, False), ("per-quadrant, per-camera lifts", True, True))  # fmt: skip


def sweep_detector(export_dir: Path, image_precision: str | None, camera_terms: bool, per_quadrant: bool, num_slices: int):
    """``sample -> Detections``: the sample's images as one full update, or encoded once and lifted quadrant by
    quadrant (the phase-locked lane's calls), then its sweep in ``num_slices`` slices."""
    det = StreamingDetector(export_dir, DetectorConfig(precision="fp32", image_lane_precision=image_precision,
                                                       camera_terms=camera_terms))  # fmt: skip

    def detect(sample):
        ts = sample_time_s(sample)
        images = sample_images(det, sample)
        if per_quadrant:
            update_by_quadrant(det, images, ts)
        else:
            det.update_images(images, ts)
        return det.detect_sweep_slices(np.asarray(sample.points, np.float32), timestamp=ts, num_slices=num_slices).detections

    return detect


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", type=click.Path(path_type=Path, file_okay=False, exists=True), required=True,
              help="nuScenes-format dataset root with splits.json.")
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False, exists=True), required=True,
              help="The export to run (a fused model with the flat lifter for the per-camera row).")
@click.option("--image-precision", type=click.Choice(["fp32", "int8"]), default="fp32", show_default=True,
              help="The image lane's graphs (the slices run fp32).")
@click.option("--samples", type=click.IntRange(min=1), default=None, help="Only the first N val samples.")
@click.option("--slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices per sweep.")
def main(data: Path, export_dir: Path, image_precision: str, samples: int | None, slices: int) -> None:
    """Offline mAP / NDS of full vs per-quadrant image updates, lifter graph vs per-camera lifts, on the val split."""
    if not (export_dir / "manifest.json").is_file():
        raise click.ClickException(f"{export_dir} holds no manifest.json")
    click.echo(f"{data} (val split), {export_dir}:")
    for label, terms, per_quadrant in VARIANTS:
        try:
            detect = sweep_detector(export_dir, image_precision, terms, per_quadrant, slices)
            ev = evaluate_dataset(detect, data, split="val", max_samples=samples)
        except ValueError as e:
            raise click.ClickException(str(e)) from None
        m = ev.metrics
        click.echo(f"{image_precision} image lane + fp32 slices, {label}: {ev.num_samples} samples, "
                   f"mAP {100 * m.mean_ap:.2f}, NDS {100 * m.nd_score:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
