"""The export's int8 steps: calibration inputs from real samples, each fp32 graph quantized (export/int8.py), and
the int8 graphs' parity against fp32, recorded in the manifest's int8 record.

A fused export calibrates the encoder on camera images, the lifter on the fp32 encoder's features with each
sample's LUT, the slice graph on pillarised slices with the fp32 lifter's image BEV; a LiDAR-only export on the
pillarised slices alone (no images, so any rig's data will do). The parity runs on the bundled sample, held out
when it was not a calibration sample, unless the rig's cameras are not the sample's (then on the calibration
samples, the only images of that rig there are).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

from streamdet.data.sample import load_bundled_sample
from streamdet.export import int8 as q8
from streamdet.export.export_run import ExportRun
from streamdet.export.fp16 import check_model
from streamdet.export.options import ExportError
from streamdet.runtime_ort.manifest import Int8Calibration, Int8GraphRecord, Int8Record, graph_file_name
from streamdet.runtime_ort.sessions import ort_session


@dataclass(eq=False)
class Int8Work:
    """What the int8 steps pass on: the calibration samples and inputs, the fp32 sessions, the graphs done."""

    cfg: q8.Int8Config
    samples: q8.CalibrationSamples
    inputs: q8.GraphInputs
    sessions32: dict[str, Any]
    started_s: float
    records: list[Int8GraphRecord] = field(default_factory=list)


def _camera_names(run: ExportRun) -> tuple[str, ...]:
    return tuple(run.rig.names) if run.rig is not None else ()


def calibration_inputs(run: ExportRun) -> None:
    started = time.perf_counter()
    sessions32 = {name: ort_session(run.tmp / graph_file_name(name, "fp32")) for name in run.graphs}
    names = _camera_names(run)
    opts = run.opts
    try:
        cal = q8.load_calibration_samples(opts.calibration_data, opts.calibration_samples, names)
        inputs = q8.graph_inputs(cal.samples, sessions32, names, run.size, run.preset, opts.num_slices)
    except q8.Int8CalibrationDataError as e:
        raise ExportError(str(e)) from None
    if not inputs.slice_head:
        raise ExportError(f"int8 calibration: the {len(cal.samples)} samples of {cal.source} hold no LiDAR point inside the grid")
    images = f"{sum(len(f['images']) for f in inputs.image_encoder)} images, {len(inputs.volumetric_lifter)} volumes, "
    run.note(f"{len(cal.samples)} samples of {cal.source} ({cal.version}, split {cal.split}): "
             f"{images if run.preset.use_image else ''}{len(inputs.slice_head)} slices")  # fmt: skip
    run.int8_work = Int8Work(q8.Int8Config(), cal, inputs, sessions32, started)


def quantize(run: ExportRun, name: str) -> None:
    work: Int8Work = run.int8_work
    src, dst = run.tmp / graph_file_name(name, "fp32"), run.tmp / graph_file_name(name, "int8")
    graph = q8.quantize_graph(name, src, dst, work.inputs.for_graph(name), work.cfg)
    check_model(graph.path)
    work.records.append(Int8GraphRecord(name, graph.quantized_ops, graph.float_nodes))
    run.note(f"int8 inputs: {graph.quantized_ops}; kept float: {sum(graph.float_nodes.values())} nodes")


def parity(run: ExportRun) -> None:
    work: Int8Work = run.int8_work
    cal, inputs = work.samples, work.inputs
    calibration = Int8Calibration(
        source=cal.source,
        version=cal.version,
        split=cal.split,
        sample_tokens=tuple(s.token for s in cal.samples),
        num_images=sum(len(f["images"]) for f in inputs.image_encoder),
        num_volumes=len(inputs.volumetric_lifter),
        num_slices=len(inputs.slice_head),
        method=work.cfg.calibrate_method.name,
        reduce_range=work.cfg.reduce_range,
        parity_held_out=False,
        seconds=round(time.perf_counter() - work.started_s, 1),
    )
    sample = load_bundled_sample()
    names = _camera_names(run)
    if set(names) <= set(sample.image_paths):
        held_out = cal.source != q8.BUNDLED_SOURCE
        if held_out:
            luts = None if run.lut is None else [run.lut]
            inputs = q8.graph_inputs([sample], work.sessions32, names, run.size, run.preset, run.opts.num_slices, luts=luts)
        run.note("on the bundled nuScenes sample" + (", held out" if held_out else ", the calibration sample itself"))
    else:
        held_out = False  # a foreign rig: the bundled images do not fit, the calibration samples are all there is
        run.note("on the calibration samples (the bundled sample lacks this rig's cameras)")
    sessions8 = {name: ort_session(run.tmp / graph_file_name(name, "int8")) for name in run.graphs}
    result = q8.int8_parity(work.sessions32, sessions8, inputs, run.preset.head_cell_m)
    for p in result.outputs:
        run.note(f"{p.graph} {p.output} ({p.inputs} inputs): relative L2 error {p.rel_l2_error:.4f}, max |diff| {p.max_abs_diff:.3g}")
    b = result.boxes
    run.note(
        f"boxes >= {b.score_threshold}: {b.count_fp32} fp32, {b.count_int8} int8, {b.matched} matched, centre diff "
        f"mean {b.mean_centre_diff_m:.3g} m, max {b.max_centre_diff_m:.3g} m"
    )
    calibration = dataclasses.replace(calibration, parity_held_out=held_out)
    run.int8_record = Int8Record(calibration, tuple(work.records), result.outputs, result.boxes)
