"""One export run: weights -> ONNX graphs (+ fp16 / int8 siblings), lut.npz, parity checks, manifest.json.

``run_export`` checks the options, stages the export (export/staging.py: a temporary directory beside the target,
renamed into place at the end with the manifest written last, so a failed or interrupted export never leaves a
directory that looks complete) and runs the steps of ``steps.export_steps`` in order:

- a fused checkpoint exports the three graphs (export/graph_steps.py), each checked against PyTorch on real inputs
  (export/parity_inputs.py), with lut.npz for the rig;
- a LiDAR-only checkpoint (preset use_image=False, the paper's streaming baseline; recognised from the
  checkpoint's preset) exports the slice graph alone (``onnx_export.LIDAR_SLICE_HEAD_IO``: no image_bev input)
  and a manifest without image spec, normalisation or LUT: no rig, no images; one trained without the quadrant
  crop (preset slice_crop=False) takes the pillar tensors alone (``LIDAR_FULL_MAP_SLICE_HEAD_IO``);
- with ``fp16`` each graph gets an fp16 sibling checked against fp32; with ``int8`` an int8 sibling calibrated on
  real samples (a ``--calibration-data`` dataset, else the bundled sample) with its parity against fp32
  (export/int8_steps.py).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from streamdet.core.constants import BUNDLED_CALIBRATION_SOURCE, EXPORTS_ROOT
from streamdet.core.sectors import check_num_slices
from streamdet.export import int8 as q8
from streamdet.export import onnx_export as ox
from streamdet.export.export_run import ExportRun, manifest_parity_passed
from streamdet.export.graph_steps import TORCH_REF_IMAGES, load_rig  # noqa: F401 (public here)
from streamdet.export.int8_data import calibration_split
from streamdet.export.options import (  # noqa: F401 (public here)
    DEFAULT_PRESET, STEM_STRIDE, ExportError, ExportOptions, ExportUsageError, check_resolution, resolve_lut_layout)
from streamdet.export.staging import (
    check_out_dir_name, check_parity_failed_dir, check_replaceable, discard_staging_dir, make_staging_dir)
from streamdet.export.steps import Progress, Report, export_steps
from streamdet.export.weights import (
    bundled_checkpoint,
    checkpoint_lifter,
    checkpoint_preset,
    checkpoint_slice_crop,
    checkpoint_use_image,
)
from streamdet.models.presets import Preset, get_preset, preset_names
from streamdet.runtime_ort.manifest import Manifest

BUNDLED_CALIBRATION = BUNDLED_CALIBRATION_SOURCE


@dataclass(frozen=True)
class ExportResult:
    out_dir: Path
    manifest: Manifest
    seconds: float

    kept_dir: Path | None = None  # the --out that kept the export it held because this one failed its parity check

    @property
    def parity_passed(self) -> bool:
        return manifest_parity_passed(self.manifest)


def run_export(opts: ExportOptions, report: Report | None = None) -> ExportResult:
    """Run the whole export; raises ExportError (one line) for bad options or an unusable target directory."""
    report = report or (lambda _msg: None)
    t_start = time.perf_counter()
    if opts.out_dir is not None:
        check_out_dir_name(opts.out_dir)  # '.', '/', '..': before the checkpoint is read
    preset, width, height = _resolve_preset(opts, report)
    _check_options(opts, preset)  # on the options as given: None is "not given"
    opts = opts.with_defaults(preset.lifter.lut_heights_per_voxel)
    out_dir = Path(opts.out_dir) if opts.out_dir is not None else Path(EXPORTS_ROOT) / preset.name
    if out_dir.is_symlink():  # replace the folder it points to and keep the link (committing moved the link aside)
        out_dir = out_dir.resolve()
        check_out_dir_name(out_dir)  # a link to '/' or to the current folder
    steps = export_steps(preset, opts, (width, height))
    progress = Progress(report, total=len(steps))
    if _holds_entries(out_dir):  # a failed export would go beside it (commit_target): check that folder now
        check_replaceable(out_dir)  # out_dir's own refusal first (make_staging_dir makes it again)
        check_parity_failed_dir(out_dir)
    tmp = make_staging_dir(out_dir)
    run = ExportRun(tmp, out_dir, preset, (width, height), opts, progress.note)
    try:
        with torch.no_grad():
            for step in steps:
                with progress(step.label):
                    step.run(run)
    except BaseException:
        discard_staging_dir(tmp)
        raise
    kept = out_dir.resolve() if run.committed_dir != out_dir else None
    return ExportResult(run.committed_dir.resolve(), run.manifest, time.perf_counter() - t_start, kept)


def _holds_entries(out_dir: Path) -> bool:
    """Whether ``out_dir`` is a directory with something in it (an unlistable one counts: make_staging_dir says why)."""
    try:
        return out_dir.is_dir() and any(out_dir.iterdir())
    except OSError:
        return False


def _check_options(opts: ExportOptions, preset: Preset) -> None:
    """Fail before any work on options that cannot be used, or that this export would ignore (``preset``: the one
    ``_resolve_preset`` settled, whose use_image says whether the export has an image lane). ``opts`` as given:
    None is an option not given."""
    try:
        check_num_slices(opts.num_slices)
    except ValueError as e:
        raise ExportUsageError(f"--slices: {e}") from None
    lo, hi = ox.OPSET_RANGE
    if isinstance(opts.opset, bool) or not isinstance(opts.opset, int) or not lo <= opts.opset <= hi:
        raise ExportError(f"--opset must be an integer in [{lo}, {hi}], got {opts.opset!r}")
    if opts.calibration_data is not None and not opts.int8:
        raise ExportUsageError(f"--calibration-data {opts.calibration_data} is the int8 calibration set: it needs --int8")
    if opts.calibration_samples is not None and not opts.int8:
        raise ExportUsageError(f"--calibration-samples {opts.calibration_samples!r} sizes the int8 calibration: it needs "
                               "--int8 (nothing is calibrated without it)")  # fmt: skip
    if opts.calibration_samples is not None and opts.calibration_data is None:
        raise ExportUsageError(f"--calibration-samples {opts.calibration_samples!r} draws from --calibration-data; without "
                               "it the int8 graphs calibrate on the bundled sample, which is one sample: give "
                               "--calibration-data DIR, or drop --calibration-samples")  # fmt: skip
    counts = {"--calibration-samples": opts.calibration_samples, "--top-k": opts.top_k}
    for flag, value in counts.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):  # None: default
            raise ExportError(f"{flag} must be a positive integer, got {value!r}")
    if not preset.use_image:
        _check_lidar_only_options(opts)
    _check_seed(opts, preset)
    if opts.int8 and opts.calibration_data is not None:
        try:
            q8.dataset_version(opts.calibration_data)
            calibration_split(opts.calibration_data)  # a splits.json without a train split: before any work
        except q8.Int8CalibrationDataError as e:
            raise ExportError(f"--calibration-data: {e}") from None


def _check_lidar_only_options(opts: ExportOptions) -> None:
    """A LiDAR-only checkpoint exports the slice graph alone: no image encoder, no lifter, no LUT, no image. The
    options that shape those would be ignored (the manifest recorded the default image layout whatever was asked),
    so each one given is refused."""
    given = [flag for flag, value in (("--image-layout", opts.image_layout), ("--lut-layout", opts.lut_layout),
                                      ("--resolution", opts.resolution), ("--calibration", opts.calibration))
             if value is not None]  # fmt: skip
    if given:
        raise ExportUsageError(
            f"--checkpoint {opts.checkpoint} is a LiDAR-only model (use_image false): its export is the slice graph "
            f"alone, with no image lane, lifter or LUT, so {', '.join(given)} would be ignored; drop "
            f"{'it' if len(given) == 1 else 'them'}"
        )  # fmt: skip


def _check_seed(opts: ExportOptions, preset: Preset) -> None:
    """``--seed`` draws the fixed-seed initial weights (no checkpoint file: none given and none bundled for the
    preset) and the parity check's noise images (a --calibration naming cameras the bundled sample lacks, whose
    images the check cannot use). Given where the export does neither, it would be ignored: refused."""
    if opts.seed is None:
        return
    weights = opts.checkpoint if opts.checkpoint is not None else bundled_checkpoint(preset.name)
    if weights is None:
        return  # the seed draws the weights
    if preset.use_image and opts.calibration is not None:
        rig, _ = load_rig(opts.calibration)  # an unreadable file: the ExportError the LUT step would give
        bundled, _ = load_rig(None)  # the bundled sample's cameras, whose images the parity check reads
        if not set(rig.names) <= set(bundled.names):
            return  # the seed draws the parity check's noise images
    what = f"--checkpoint {opts.checkpoint}" if opts.checkpoint is not None else f"the bundled checkpoint {weights}"
    images = ("a LiDAR-only export reads no image" if not preset.use_image
              else "this one reads the bundled sample's images: its cameras are the sample's")  # fmt: skip
    raise ExportUsageError(f"--seed {opts.seed!r} would be ignored: it seeds the untrained weights (this export loads "
                           f"{what}) and the parity check's noise images ({images}); drop it")  # fmt: skip


def _resolve_preset(opts: ExportOptions, report: Report | None = None) -> tuple[Preset, int, int]:
    """The preset the export writes (``opts.preset``, else the checkpoint's) with the export's image size, top-K and
    what the checkpoint says of its lanes and lifter; and the image width and height. ``report``: where a note goes
    (a --top-k beyond a map's classes x cells, which the graph cannot decode)."""
    name = opts.preset
    if name is None:
        saved = checkpoint_preset(opts.checkpoint)
        name = saved.get("name") if saved is not None and saved.get("name") in preset_names() else DEFAULT_PRESET
    try:
        preset = get_preset(name)
    except ValueError as e:
        raise ExportError(str(e)) from None
    width, height = opts.resolution if opts.resolution is not None else (preset.image.width_px, preset.image.height_px)
    check_resolution(width, height)
    image = dataclasses.replace(preset.image, width_px=width, height_px=height)
    # A LiDAR-only checkpoint of this preset has no image lane: export it as such (its weights would not load into
    # the fused model anyway). The image size stays in the preset dict but names no graph input.
    use_image = preset.use_image and checkpoint_use_image(opts.checkpoint) is not False
    # likewise a LiDAR-only checkpoint trained without the quadrant crop (one whole-grid map per slice)
    slice_crop = checkpoint_slice_crop(opts.checkpoint)
    # and the lifter it was trained with (small_v2 moved to the flat lifter, so its older checkpoints are volume;
    # the residual conv and the LUT's heights per voxel are the model's too)
    lifter = checkpoint_lifter(opts.checkpoint) or preset.lifter
    post = preset.post if opts.top_k is None else dataclasses.replace(preset.post, top_k=opts.top_k)
    try:
        preset = dataclasses.replace(preset, image=image, use_image=use_image, slice_crop=slice_crop, lifter=lifter, post=post)
    except ValueError as e:
        raise ExportError(f"checkpoint {opts.checkpoint}: {e}") from None
    if opts.top_k is not None and preset.top_k < opts.top_k and report is not None:  # Preset.top_k clamps it
        report(f"note: --top-k {opts.top_k} exceeds the {preset.top_k} classes x cells of a quadrant's head map: the "
               f"graph decodes {preset.top_k} per quadrant (the manifest's post.top_k)")  # fmt: skip
    return preset, width, height
