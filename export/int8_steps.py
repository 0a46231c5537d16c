"""The export's int8 steps: calibration inputs from real samples, each fp32 graph quantized (export/int8.py), and
the int8 graphs' parity against fp32, recorded in the manifest's int8 record.

Calibration and parity run the staged export's runtime (export/staged_detector.py) over real samples and take the
graph feeds it records: a fused export calibrates the encoder on camera images, the lifter on the fp32 encoder's
features with each sample's LUT, the slice graph on pillarised slices with the fp32 lifter's image BEV; a
LiDAR-only export on the pillarised slices alone (no images, so any rig's data will do). The parity compares each
int8 graph with its fp32 graph on the fp32 detector's feeds, and the int8 detector's runs with the fp32 detector's
on the same samples: the bundled sample, held out when it was not a calibration sample (by token: a nuScenes
v1.0-mini copy given as --calibration-data holds it too, and the manifest's parity_held_out says so), unless the rig's
cameras are not the sample's (then the calibration samples, the only images of that rig there are).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from streamdet.data.sample import Sample, load_bundled_sample
from streamdet.export import int8 as q8
from streamdet.export.export_run import ExportRun
from streamdet.export.fp16 import check_model
from streamdet.export.options import ExportError
from streamdet.export.staged_detector import staged_detector
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.manifest import graph_file_name
from streamdet.runtime_ort.manifest_records import Int8Calibration, Int8GraphRecord, Int8Record
from streamdet.runtime_ort.recording import GraphRecording


@dataclass(eq=False)
class Int8Work:
    """What the int8 steps pass on: the calibration samples, the fp32 detector and what it recorded, the graphs done."""

    cfg: q8.Int8Config
    samples: q8.CalibrationSamples
    detector32: StreamingDetector  # the staged fp32 graphs, run by the runtime
    inputs: GraphRecording  # the fp32 detector's graph runs over the calibration samples
    started_s: float
    records: list[Int8GraphRecord] = field(default_factory=list)


def _camera_names(run: ExportRun) -> tuple[str, ...]:
    return tuple(run.rig.names) if run.rig is not None else ()


def calibration_inputs(run: ExportRun) -> None:
    started = time.perf_counter()
    opts = run.opts
    detector32 = staged_detector(run, "fp32")
    try:
        cal = q8.load_calibration_samples(opts.calibration_data, opts.calibration_samples, _camera_names(run))
        inputs = q8.record_graph_inputs(detector32, cal.samples)
    except q8.Int8CalibrationDataError as e:
        raise ExportError(str(e)) from None
    num_slices = len(inputs.of("slice_head"))
    if not num_slices:
        raise ExportError(f"int8 calibration: the {len(cal.samples)} samples of {cal.source} hold no LiDAR point inside the grid")
    images = f"{_num_images(inputs)} images, {len(inputs.of('volumetric_lifter'))} volumes, "
    run.note(f"{len(cal.samples)} samples of {cal.source} ({cal.version}, split {cal.split}): "
             f"{images if run.preset.use_image else ''}{num_slices} slices")  # fmt: skip
    run.int8_work = Int8Work(q8.Int8Config(), cal, detector32, inputs, started)


def _num_images(inputs: GraphRecording) -> int:
    return sum(len(f["images"]) for f in inputs.feeds("image_encoder"))


def quantize(run: ExportRun, name: str) -> None:
    work: Int8Work = run.int8_work
    src, dst = run.tmp / graph_file_name(name, "fp32"), run.tmp / graph_file_name(name, "int8")
    graph = q8.quantize_graph(name, src, dst, work.inputs.feeds(name), work.cfg)
    check_model(graph.path)
    work.records.append(Int8GraphRecord(name, graph.quantized_ops, graph.float_nodes))
    run.note(f"int8 inputs: {graph.quantized_ops}; kept float: {sum(graph.float_nodes.values())} nodes")


def parity_samples(cal: q8.CalibrationSamples, bundled: Sample, camera_names: Sequence[str]
                   ) -> tuple[tuple[Sample, ...] | None, bool, str]:  # fmt: skip
    """The samples the int8 parity runs on (None: the calibration samples, whose recorded inputs serve), whether
    they were held out of the calibration, and the note that says which.

    The bundled sample where it has the rig's cameras, held out only when the calibration did not draw it (by token:
    a nuScenes v1.0-mini copy given as --calibration-data holds it too); else the calibration samples, the only
    images of that rig there are."""
    if not set(camera_names) <= set(bundled.image_paths):
        return None, False, "on the calibration samples (the bundled sample lacks this rig's cameras)"
    if bundled.token not in {s.token for s in cal.samples}:
        return (bundled,), True, "on the bundled nuScenes sample, held out"
    if cal.source == q8.BUNDLED_SOURCE:
        return None, False, "on the bundled nuScenes sample, the calibration sample itself"
    return (bundled,), False, f"on the bundled nuScenes sample, not held out: a calibration sample too (drawn from {cal.source})"


def parity(run: ExportRun) -> None:
    work: Int8Work = run.int8_work
    cal, inputs = work.samples, work.inputs
    calibration = Int8Calibration(
        source=cal.source,
        version=cal.version,
        split=cal.split,
        sample_tokens=tuple(s.token for s in cal.samples),
        num_images=_num_images(inputs),
        num_volumes=len(inputs.of("volumetric_lifter")),
        num_slices=len(inputs.of("slice_head")),
        method=work.cfg.calibrate_method.name,
        reduce_range=work.cfg.reduce_range,
        parity_held_out=False,
        seconds=round(time.perf_counter() - work.started_s, 1),
    )
    chosen, held_out, note = parity_samples(cal, load_bundled_sample(), _camera_names(run))
    samples = cal.samples
    if chosen is not None:
        samples = chosen
        inputs = q8.record_graph_inputs(work.detector32, samples)
    run.note(note)
    calibration = dataclasses.replace(calibration, parity_held_out=held_out)
    # the int8 detector's manifest lists its graphs with their record so far (no parity yet)
    detector8 = staged_detector(run, "int8", Int8Record(calibration, tuple(work.records), (), None))
    inputs8 = q8.record_graph_inputs(detector8, samples)
    lifter_output = run.graph_io("volumetric_lifter").outputs[0] if run.preset.use_image else "image_bev"
    result = q8.int8_parity(inputs, inputs8, detector8.sessions, run.preset.head_cell_m, lifter_output)
    for p in result.outputs:
        run.note(f"{p.graph} {p.output} ({p.inputs} inputs): relative L2 error {p.rel_l2_error:.4f}, max |diff| {p.max_abs_diff:.3g}")
    b = result.boxes
    run.note(
        f"boxes >= {b.score_threshold}: {b.count_fp32} fp32, {b.count_int8} int8, {b.matched} matched, centre diff "
        f"mean {b.mean_centre_diff_m:.3g} m, max {b.max_centre_diff_m:.3g} m"
    )
    run.int8_record = Int8Record(calibration, tuple(work.records), result.outputs, result.boxes)
