"""``streamdet-export``: a thin click wrapper over ``streamdet.export.exporter.run_export``."""

from __future__ import annotations

import sys
from pathlib import Path

import click


from streamdet.cli_utils import (
    GIVEN_SOURCES,
    MAX_SLICES, RESOLUTION_RANGE_HELP, dataset_inputs, refuse_output_over_inputs, resolution_callback, slices_callback)
from streamdet.core.image_layout import IMAGE_LAYOUTS
from streamdet.core.lut_layout import LUT_LAYOUTS
from streamdet.export.exporter import STEM_STRIDE, ExportError, ExportOptions, ExportUsageError, run_export
from streamdet.export.int8 import DEFAULT_CALIBRATION_SAMPLES
from streamdet.export.options import DEFAULT_IMAGE_LAYOUT, DEFAULT_LUT_LAYOUT, DEFAULT_PRESET, LUT_AUTO
from streamdet.runtime_ort.manifest import LUT_NAME, MANIFEST_NAME
from streamdet.export.onnx_export import DEFAULT_OPSET, OPSET_RANGE
from streamdet.models.presets import preset_names

# Upper bounds of the numeric options, far past any documented use: the calibration draws its samples from a
# dataset (default 8); the slice graph decodes at most classes x cells per quadrant (the paper's 500); torch seeds are
# 64-bit (torch.manual_seed refuses more, after the model is built, with a bare 'Overflow when unpacking long long').
MAX_CALIBRATION_SAMPLES = 10_000
MAX_TOP_K = 100_000
MAX_SEED = 2**63 - 1
# options passed to the exporter only when typed: None there is "not given", and an option this export would ignore
# (an image option of a LiDAR-only checkpoint, --calibration-samples without --int8, --seed with a checkpoint) is
# refused only when given; their defaults are still shown in --help
_GIVEN_ONLY = ("calibration_samples", "seed", "image_layout", "lut_layout")


def _not_empty(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    """An empty path ('') is refused (exit 2): as a Path it is the current folder, which no path option means."""
    if value == "":
        raise click.BadParameter("'' is empty: give a path, or leave the option out for its default")
    return value


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--preset", default=None, type=click.Choice(preset_names()),
              help=f"Model preset to export. Default: the preset --checkpoint names, else {DEFAULT_PRESET} (the shipped model's).")
@click.option("--checkpoint", type=click.Path(dir_okay=False), default=None, callback=_not_empty,
              help="Checkpoint of that preset (torch.load weights_only). Default: the bundled fused checkpoint of the "
                   "preset (a file in models/weights/ whose saved preset has that name), else fixed-seed untrained weights.")
@click.option("--calibration", type=click.Path(dir_okay=False), default=None, callback=_not_empty,
              help="calibration.json for lut.npz. Default: the bundled nuScenes sample's, intrinsics scaled to --resolution. "
                   "Refused for a LiDAR-only checkpoint (no LUT).")
@click.option("--resolution", callback=resolution_callback(multiple_of=STEM_STRIDE), default=None, metavar="WxH",
              help=f"Camera image size in pixels, e.g. 800x450; width and height must be even, {RESOLUTION_RANGE_HELP}. "
                   "Default: the preset's. Refused for a LiDAR-only checkpoint (no images).")
@click.option("--slices", "num_slices", type=click.IntRange(1, MAX_SLICES), default=8, show_default=True, callback=slices_callback,
              help=f"Slices per sweep (1, 2 or a multiple of 4 up to {MAX_SLICES}); picks the LiDAR slice used for the parity checks.")
@click.option("--fp16", is_flag=True, help="Also write fp16 siblings (*.fp16.onnx; inputs and outputs stay fp32) and check them.")
@click.option("--int8", is_flag=True,
              help="Also write int8 siblings (*.int8.onnx: static QDQ, int8 weights, uint8 activations; inputs and "
                   "outputs stay fp32), calibrated on real samples, with their parity against fp32 in the manifest.")
@click.option("--calibration-data", type=click.Path(), default=None, metavar="DIR", callback=_not_empty,
              help="nuScenes-format dataset (e.g. streamdet-synth output) whose train split calibrates the int8 graphs. "
                   "Default: the bundled nuScenes sample.")
@click.option("--calibration-samples", type=click.IntRange(1, MAX_CALIBRATION_SAMPLES), default=DEFAULT_CALIBRATION_SAMPLES,
              show_default=True, help=f"Samples drawn evenly from --calibration-data (each gives all its camera images and "
                                      f"slices; 1..{MAX_CALIBRATION_SAMPLES}). Needs --int8.")
@click.option("--opset", type=click.IntRange(*OPSET_RANGE), default=DEFAULT_OPSET, show_default=True, help=f"ONNX opset ({OPSET_RANGE[0]}..{OPSET_RANGE[1]}).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output directory (replaced if it holds an older export). Not the current folder ('.'): the export is "
                   "staged beside --out and renamed into place. Default: ./exports/<preset>.")
@click.option("--seed", type=click.IntRange(0, MAX_SEED), default=0, show_default=True,
              help="Torch seed (0..2**63-1) of the untrained weights when no checkpoint is used (none given, none bundled "
                   "for the preset), and of the parity check's noise images when --calibration names cameras the "
                   "bundled sample lacks. Refused where the export uses neither.")
@click.option("--image-layout", type=click.Choice(IMAGE_LAYOUTS), default=DEFAULT_IMAGE_LAYOUT, show_default=True,
              help="What the lifter graph hands the slice graph: the image BEV, or the BEV encoder's image half computed "
                   "once per lift in the lifter graph (models/image_half.py; recorded as the manifest's image_layout). "
                   "Refused for a LiDAR-only checkpoint (no lifter).")
@click.option("--lut-layout", type=click.Choice((LUT_AUTO, *LUT_LAYOUTS)), default=DEFAULT_LUT_LAYOUT, show_default=True,
              help="How the lifter graph reads the LUT: K slots per voxel, or the compacted valid (voxel, camera) pairs "
                   "(models/compact_lifter.py; recorded as the manifest's lut_layout). auto: compact for a model with "
                   "one LUT height per voxel, slots for several (where compacting does not pay). Refused for a LiDAR-only "
                   "checkpoint (no lifter).")
@click.option("--top-k", type=click.IntRange(1, MAX_TOP_K), default=None,
              help=f"Detections per quadrant the slice graph decodes, 1..{MAX_TOP_K} (default: the preset's, the paper's 500; "
                   "at most a head map's classes x cells, which a larger value is cut to, with a note). Fewer make "
                   "each slice run cheaper; the runtime's score threshold keeps far fewer anyway, and the detector counts "
                   "the runs whose K-th score passed it (StreamingDetector.slice_runs_at_top_k: the cap cut boxes).")
def main(preset, checkpoint, calibration, resolution, num_slices, fp16, int8, calibration_data, calibration_samples,
         opset, out_dir, seed, image_layout, lut_layout, top_k) -> None:
    """Export the detector as three ONNX graphs plus lut.npz and manifest.json, checking each against PyTorch.

    A LiDAR-only checkpoint (trained with use_image=False) exports its slice graph only, with no image_bev input."""
    # an export written into the calibration dataset (or onto an input) would sit among, or replace, what it reads
    # (its linked table folder included: docs/trust.md)
    inputs = [("--checkpoint", checkpoint), ("--calibration", calibration)]
    refuse_output_over_inputs(None if out_dir is None else Path(out_dir), "--out",
                              [(option, None if path is None else Path(path)) for option, path in inputs]
                              + dataset_inputs(None if calibration_data is None else Path(calibration_data),
                                               "--calibration-data"))  # fmt: skip
    ctx = click.get_current_context()
    given = {name: ctx.get_parameter_source(name) in GIVEN_SOURCES for name in _GIVEN_ONLY}
    opts = ExportOptions(
        preset=preset, checkpoint=checkpoint, calibration=calibration, resolution=resolution, num_slices=num_slices,
        fp16=fp16, int8=int8, calibration_data=calibration_data,
        calibration_samples=calibration_samples if given["calibration_samples"] else None, opset=opset,
        out_dir=out_dir, seed=seed if given["seed"] else None, image_layout=image_layout if given["image_layout"] else None,
        lut_layout=lut_layout if given["lut_layout"] else None, top_k=top_k,
    )  # fmt: skip
    try:
        result = run_export(opts, report=lambda msg: click.echo(msg, err=True))
    except ExportUsageError as e:  # options that do not go together (one this export would ignore): exit 2
        raise click.UsageError(str(e)) from None
    except ExportError as e:
        raise click.ClickException(str(e)) from None
    m = result.manifest
    click.echo(f"wrote {result.out_dir} in {result.seconds:.1f} s ({m.source.get('checkpoint') or 'untrained fixed-seed weights'}):")
    for g in m.graphs:
        size = (result.out_dir / g.file).stat().st_size / 1e6
        click.echo(f"  {g.file:<28} {size:8.2f} MB  {g.gmac:8.2f} GMAC  {g.precision}")
    if m.lut is not None:  # a LiDAR-only export has no image lane, hence no LUT
        click.echo(f"  {LUT_NAME:<28} {(result.out_dir / LUT_NAME).stat().st_size / 1e6:8.2f} MB  ({m.lut.calibration_source})")
    click.echo(f"  {MANIFEST_NAME}")
    if m.int8 is not None:
        # int8 is an approximation: its differences are measured and recorded, never a failure of the export
        c = m.int8.calibration
        click.echo(f"int8 calibrated on {c.num_images} images, {c.num_volumes} volumes, {c.num_slices} slices of {c.source}; "
                   f"against fp32{' (held-out sample)' if c.parity_held_out else ''}:")
        for p in m.int8.parity:
            click.echo(f"  {p.graph:<18} {p.output:<10} {p.inputs:<8} relative L2 error {p.rel_l2_error:.4f}")
        if m.int8.boxes is not None:
            b = m.int8.boxes
            click.echo(f"  boxes >= {b.score_threshold}: {b.count_fp32} fp32, {b.count_int8} int8, {b.matched} matched, "
                       f"max centre diff {b.max_centre_diff_m:.3g} m")
    if not result.parity_passed:
        failed = [f"{p.graph} {p.precision} {p.output}" for p in m.parity if not p.passed]
        if m.pipeline_parity is not None and not m.pipeline_parity.passed:
            failed.append("fp16 pipeline")
        click.echo(f"error: parity FAILED for {', '.join(failed)} (recorded in {MANIFEST_NAME})", err=True)
        if result.kept_dir is not None:
            click.echo(f"{result.kept_dir} keeps the export it held; the one that failed is in {result.out_dir}", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
