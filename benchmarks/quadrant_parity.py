"""Offline check behind the phase-locked schedule's accuracy: on a dataset's val scenes, the same sweeps and image
sets through one full image update and through four per-quadrant updates give the same image BEV and the same
detections. The replay's offline mAP of the two schedules can then differ only by what the clock did (slices
dropped, older images), never by the function per quadrant.

    python -m streamdet.benchmarks.quadrant_parity --data DATA --export-dir EXPORT [--image-precision int8]
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click
import numpy as np

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.cli_utils import camera_terms_option
from streamdet.replay.nuscenes_source import DatasetTables, load_drive
from streamdet.replay.run import split_scenes
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector


def quadrant_parity(data: Path, export_dir: Path, image_precision: str | None, every: int,
                    camera_terms: bool | None = False) -> dict:  # fmt: skip
    """{sweeps, identical (detections bit for bit), max_bev_diff, max_box_diff, max_score_diff, boxes_full,
    boxes_parts} over every ``every``-th sweep; ``camera_terms``: the per-quadrant detector's
    ``DetectorConfig.camera_terms`` (False: the lifter graph, bit for bit the full update's function)."""
    config = DetectorConfig(precision="fp32", image_lane_precision=image_precision)
    tables = DatasetTables(data, DEFAULT_TABLE_VERSION)
    full = StreamingDetector(export_dir, dataclasses.replace(config, camera_terms=False))
    parts = StreamingDetector(export_dir, dataclasses.replace(config, camera_terms=camera_terms))
    out = {"sweeps": 0, "identical": 0, "max_bev_diff": 0.0, "max_box_diff": 0.0, "max_score_diff": 0.0,
           "boxes_full": 0, "boxes_parts": 0, "camera_terms": parts.camera_terms}  # fmt: skip
    for scene in split_scenes(tables, "val", None):
        drive = load_drive(tables, scene, (full.image.width, full.image.height), 20.0, 12.0, None, lambda msg: None)
        if drive.rig is not None:
            full.set_calibration(drive.rig)
            parts.set_calibration(drive.rig)
        for sweep in drive.sweeps[::every]:
            sets = [s for s in drive.image_sets if s.capture_s <= sweep.start_s]
            if not sets:
                continue
            full.update_images(sets[-1].images, timestamp=0.0)
            for q in range(4):
                parts.update_images(sets[-1].images, timestamp=0.0, quadrants=[q])
            bev_diff = np.abs(full.image_state.bev - parts.image_state.bev).max()  # the cached image BEVs
            a, b = full.detect_sweep(sweep.points), parts.detect_sweep(sweep.points)
            same = a.boxes.shape == b.boxes.shape and np.array_equal(a.boxes, b.boxes) and np.array_equal(a.labels, b.labels)
            out["sweeps"] += 1
            out["identical"] += int(same)
            out["max_bev_diff"] = max(out["max_bev_diff"], float(bev_diff))
            out["boxes_full"] += len(a.boxes)
            out["boxes_parts"] += len(b.boxes)
            if a.boxes.shape == b.boxes.shape and len(a.boxes):
                out["max_box_diff"] = max(out["max_box_diff"], float(np.abs(a.boxes - b.boxes).max()))
                out["max_score_diff"] = max(out["max_score_diff"], float(np.abs(a.scores - b.scores).max()))
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="nuScenes-format dataset root with splits.json (the synthetic world's).")  # fmt: skip
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False), required=True, help="The export to run.")
@click.option("--image-precision", type=click.Choice(["fp32", "fp16", "int8"]), default=None,
              help="The image lane's graphs (default: fp32, as the slices).")  # fmt: skip
@click.option("--every", type=click.IntRange(min=1), default=10, show_default=True, help="Check every N-th sweep.")
@camera_terms_option(default="off")
def main(data: Path, export_dir: Path, image_precision: str | None, every: int, camera_terms: bool | None) -> None:
    """Full image update vs four per-quadrant updates on the val scenes: the same BEV and detections?"""
    if not (export_dir / "manifest.json").is_file():
        raise click.ClickException(f"{export_dir} holds no manifest.json")
    try:
        r = quadrant_parity(data, export_dir, image_precision, every, camera_terms)
    except (ValueError, OSError) as e:
        raise click.ClickException(str(e)) from None
    label = f"{image_precision or 'fp32'} image lane + fp32 slices" + (", per-camera lifts" if r["camera_terms"] else "")
    click.echo(f"{label}: {r['sweeps']} sweeps of the val scenes, detections bit-identical in {r['identical']}; "
               f"max |BEV diff| {r['max_bev_diff']:.3g}, max |box diff| {r['max_box_diff']:.3g}, max |score diff| "
               f"{r['max_score_diff']:.3g} (where the box counts agree); boxes {r['boxes_full']} full / "
               f"{r['boxes_parts']} per quadrant")  # fmt: skip


if __name__ == "__main__":
    main()
