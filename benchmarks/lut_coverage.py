"""Own-footprint coverage of the projection LUT on a synthetic dataset with masks, per class and heights per voxel.

    python -m streamdet.benchmarks.lut_coverage DATA [--preset small] [--heights 1,2,4] [--max-samples N]

For every sample and every ground-truth object of the classes asked, within ``--range`` metres: is the object
visible in some camera (its mask id present), and does the LUT column under its BEV centre read one of its
feature cells (``calibration.lut_coverage``)? Prints, per heights-per-voxel, the covered share of the visible
objects per class, the LUT's slots K and its size in bytes. Results go to docs (issue 19), not docstrings.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import cv2
import numpy as np

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.lut_coverage import object_coverage
from streamdet.cli_utils import FiniteFloatRange
from streamdet.core.classes import CLASS_NAMES
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.synth_masks import mask_path, read_mask
from streamdet.models.presets import get_preset
from streamdet.progress import progressbar

DEFAULT_CLASSES = "pedestrian,traffic_cone,barrier,bicycle"


def sample_masks(sample, size: tuple[int, int]) -> tuple[list[np.ndarray], dict[str, int]]:
    """Per camera the instance mask resized (nearest) to ``size`` (W, H), and instance token -> mask id."""
    masks, ids = [], {}
    for name in sample.rig.names:
        cam = sample.rig.camera(name)
        _, inst, mask_ids, tokens = read_mask(mask_path(sample.image_paths[name]), cam.height, cam.width)
        ids.update({str(t): int(i) for t, i in zip(tokens, mask_ids)})
        masks.append(cv2.resize(inst, size, interpolation=cv2.INTER_NEAREST))
    return masks, ids


def measure(data: Path, preset_name: str, heights: list[int], classes: list[str], range_m: float,
            max_samples: int | None, version: str = DEFAULT_TABLE_VERSION) -> dict:  # fmt: skip
    preset = get_preset(preset_name)
    size = (preset.image.width_px, preset.image.height_px)
    reader = NuScenesReader(data, version)
    wanted = [CLASS_NAMES.index(c) for c in classes]
    counts = {h: {c: [0, 0] for c in classes} for h in heights}  # covered, visible
    luts: dict = {}
    n = len(reader) if max_samples is None else min(max_samples, len(reader))
    with progressbar(range(n), label="samples") as bar:
        for i in bar:
            sample = reader.get(i)
            masks, ids = sample_masks(sample, size)
            keep = np.isin(sample.gt_labels, wanted) & (np.hypot(sample.gt_boxes[:, 0], sample.gt_boxes[:, 1]) < range_m)
            rows = np.flatnonzero(keep)
            obj_ids = np.array([ids.get(sample.instance_tokens[r], -1) for r in rows])
            for h in heights:
                key = (sample.rig.sha256(), h)
                if key not in luts:
                    luts[key] = build_lut(sample.rig, preset.grid, preset.image.feature_stride, size, heights_per_voxel=h)
                cov = object_coverage(luts[key], masks, sample.gt_boxes[rows, :2], obj_ids)
                for r, vis, hit in zip(rows.tolist(), cov.visible.tolist(), cov.covered.tolist()):
                    if vis:
                        c = counts[h][CLASS_NAMES[sample.gt_labels[r]]]
                        c[0] += hit
                        c[1] += 1
    out = {"data": str(data), "preset": preset_name, "image_size": list(size), "samples": n, "range_m": range_m,
           "heights": {}}  # fmt: skip
    for h in heights:
        lut = next(v for (s, hh), v in luts.items() if hh == h)
        out["heights"][str(h)] = {
            "num_slots": lut.num_slots, "lut_bytes": int(lut.index.nbytes + lut.weight.nbytes),
            "coverage": {c: {"covered": cv, "visible": vis, "share": cv / vis if vis else None}
                         for c, (cv, vis) in counts[h].items()},
        }  # fmt: skip
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--preset", "preset_name", default="small", show_default=True, help="Preset whose grid and image size the LUT uses.")
@click.option("--heights", default="1,2,4", show_default=True, help="Heights per voxel to compare, comma separated.")
@click.option("--classes", default=DEFAULT_CLASSES, show_default=True, help="Classes to measure, comma separated.")
@click.option("--range", "range_m", type=FiniteFloatRange(min=0.0, min_open=True), default=40.0, show_default=True,
              help="Objects within this distance (m, > 0).")
@click.option("--max-samples", type=click.IntRange(min=1), default=None, help="Only the first N samples.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write JSON here.")
def main(data: Path, preset_name: str, heights: str, classes: str, range_m: float, max_samples: int | None,
         json_path: Path | None) -> None:  # fmt: skip
    """Own-footprint coverage of the LUT per class, for several heights per voxel."""
    try:
        hs = [int(h) for h in heights.split(",")]
    except ValueError:
        raise click.BadParameter(f"{heights!r} is not a comma-separated list of integers", param_hint="--heights") from None
    names = [c.strip() for c in classes.split(",") if c.strip()]
    bad = [c for c in names if c not in CLASS_NAMES]
    if bad or not names:
        raise click.BadParameter(f"unknown class {bad[:1]}", param_hint="--classes")
    try:
        out = measure(data, preset_name, hs, names, range_m, max_samples)
    except (FileNotFoundError, KeyError, ValueError) as e:
        raise click.ClickException(str(e).splitlines()[0]) from None
    for h, r in out["heights"].items():
        cov = "  ".join(f"{c} {v['share']:.2f} ({v['covered']}/{v['visible']})" if v["share"] is not None else f"{c} n/a"
                        for c, v in r["coverage"].items())  # fmt: skip
        click.echo(f"heights {h}: K={r['num_slots']}  LUT {r['lut_bytes'] / 1e6:.1f} MB  {cov}")
    if json_path is not None:
        json_path.write_text(json.dumps(out, indent=1) + "\n")
        click.echo(f"wrote {json_path}")


if __name__ == "__main__":
    main()
