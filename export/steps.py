"""The export's steps, one list for the fused and the LiDAR-only export, and the numbered progress lines.

``export_steps`` lists what an export of a preset with these options does, in order; the progress numbers each
step "[k/N]" with N the length of that list. The graphs come from ``onnx_export.graph_ios``: three for the fused
model, the slice graph alone for the LiDAR-only one (no LUT, no images).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial

from streamdet.export import graph_steps as gs
from streamdet.export import int8_steps
from streamdet.export import onnx_export as ox
from streamdet.export.export_run import ExportRun
from streamdet.export.options import ExportOptions
from streamdet.export.staging import commit_staging_dir, commit_target
from streamdet.models.presets import Preset

Report = Callable[[str], None]


@dataclass(frozen=True)
class Step:
    label: str  # the progress line's text
    run: Callable[[ExportRun], None]


# each graph's fp32 export and parity against PyTorch
FP32_STEPS: dict[str, tuple[Step, ...]] = {
    "image_encoder": (
        Step("exporting image_encoder.onnx", gs.export_image_encoder),
        Step("parity image_encoder (onnxruntime fp32 vs PyTorch)", gs.parity_image_encoder),
    ),
    "volumetric_lifter": (Step("exporting volumetric_lifter.onnx and checking parity", gs.export_volumetric_lifter),),
    "slice_head": (Step("exporting slice_head.onnx and checking parity", gs.export_slice_head),),
}


def export_steps(preset: Preset, opts: ExportOptions, size: tuple[int, int]) -> list[Step]:
    """Every step of an export of ``preset`` (with its use_image) at ``size`` (W, H) with these options."""
    opts = opts.with_defaults(preset.lifter.lut_heights_per_voxel)  # "auto" -> the preset's; None -> the default
    graphs = tuple(ox.graph_ios(preset.use_image, preset.slice_crop, opts.image_layout, opts.lut_layout))
    fused = preset.use_image
    lidar = "LiDAR-only model: slice graph only" + ("" if preset.slice_crop else ", whole-grid maps (no quadrant crop)")
    steps = [Step("loading weights" if fused else f"loading weights ({lidar})", gs.load_weights)]
    if fused:
        steps.append(Step(f"building the LUT for {size[0]}x{size[1]}", gs.build_lut_file))
    steps.append(Step(f"preparing the parity inputs (bundled sample{'' if fused else ', LiDAR only'})", gs.prepare_parity_inputs))
    steps.extend(step for name in graphs for step in FP32_STEPS[name])
    steps.append(Step("counting GMAC", gs.count_gmacs))
    if opts.fp16:
        steps.extend(Step(f"converting {name} to fp16", partial(gs.convert_fp16, name=name)) for name in graphs)
        what = "graph by graph and whole pipeline" if fused else "(the slice graph is the whole pipeline)"
        steps.append(Step(f"parity fp16 vs fp32{',' if fused else ''} {what}", gs.parity_fp16))
    if opts.int8:
        what = "the fp32 encoder and lifter on real samples" if fused else "pillarised slices of real samples"
        steps.append(Step(f"int8: calibration inputs ({what})", int8_steps.calibration_inputs))
        steps.extend(Step(f"int8: quantizing {name}", partial(int8_steps.quantize, name=name)) for name in graphs)
        what = ("relative L2 of every output, decoded boxes of all slices" if fused
                else "slice graph on every slice of the bundled sample")  # fmt: skip
        steps.append(Step(f"int8: parity against fp32 ({what})", int8_steps.parity))
    steps.append(Step("writing manifest.json", gs.write_manifest))
    steps.append(Step("moving the export into place", _commit))
    return steps


def _commit(run: ExportRun) -> None:
    run.committed_dir = commit_target(run.out_dir, run.parity_passed)
    if run.committed_dir != run.out_dir:
        run.note(f"parity FAILED: {run.out_dir} keeps the export it held; this one goes to {run.committed_dir}")
    commit_staging_dir(run.tmp, run.committed_dir)


class Progress:
    """Numbered progress lines with the time each step took."""

    def __init__(self, report: Report, total: int) -> None:
        self.report, self.total, self.i = report, total, 0

    @contextmanager
    def __call__(self, what: str) -> Iterator[None]:
        self.i += 1
        self.report(f"[{self.i}/{self.total}] {what} ...")
        t = time.perf_counter()
        yield
        self.report(f"      done in {time.perf_counter() - t:.1f} s")

    def note(self, text: str) -> None:
        self.report(f"      {text}")
