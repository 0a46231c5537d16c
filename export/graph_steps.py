"""The export's steps up to the manifest: weights, LUT, parity inputs, each fp32 graph with its parity against
PyTorch, GMAC, the fp16 siblings with their parity against fp32 (export/steps.py puts them in order).

Each graph's PyTorch reference sees the same inputs as its onnxruntime counterpart, and the fp32 pipeline (encoder
-> lifter with the LUT -> slice graph) is onnxruntime's: each graph is fed by the fp32 graph before it. The fp16
pipeline check runs the runtime itself on the staged graphs at both precisions (export/staged_detector.py).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.compact_lut import lifter_lut_feeds
from streamdet.calibration.lut import check_rig_fits
from streamdet.calibration.lut_build import build_lut
from streamdet.core.constants import BUNDLED_CALIBRATION_SOURCE
from streamdet.core.image_layout import IMAGE_HALF
from streamdet.core.lut_layout import LUT_COMPACT
from streamdet.export import onnx_export as ox
from streamdet.export.export_run import ExportRun, Feeds
from streamdet.export.fp16 import convert_model_to_fp16
from streamdet.export.gmac import graph_gmacs
from streamdet.export.options import ExportError
from streamdet.export.parity import (
    FEW_COMPARED,
    FP16_SCALE_FLOOR,
    FP16_TOL_REL,
    TORCH_SCALE_FLOOR,
    TORCH_TOL_REL,
    cell_centres,
    compare_dense,
    compare_detections,
    detection_margins,
    peak_margins,
    pipeline_parity,
)
from streamdet.export.parity_inputs import parity_inputs, scatter_cameras
from streamdet.export.record import format_parity
from streamdet.export.staged_detector import run_manifest, staged_detector
from streamdet.export.staging import save_checked
from streamdet.export.weights import bundled_checkpoint, load_detector
from streamdet.models.decode import decode_head_maps
from streamdet.models.export_form import to_export_form
from streamdet.models.presets import Preset
from streamdet.runtime_ort.detector import SliceResult, StreamingDetector
from streamdet.runtime_ort.manifest import LUT_NAME, graph_file_name
from streamdet.runtime_ort.manifest_records import ParityRecord
from streamdet.runtime_ort.manifest import write_manifest as write_manifest_file
from streamdet.runtime_ort.sessions import ort_session

TORCH_REF_IMAGES = 2  # images the PyTorch encoder reference runs on (onnxruntime runs all J)
DENSE_GRAPHS = ("image_encoder", "volumetric_lifter")  # compared element-wise; the slice graph's outputs are detections


def load_rig(calibration: str | None) -> tuple[Rig, str]:
    """The rig and a description of where it came from."""
    if calibration is None:
        res = importlib.resources.files("streamdet.data") / "nuscenes_sample" / "calibration.json"
        return Rig.from_calibration_json(res), BUNDLED_CALIBRATION_SOURCE
    path = Path(calibration)
    if not path.is_file():
        raise ExportError(f"calibration file {path} " + ("is not a regular file (a folder, FIFO or device?)" if path.exists()
                                                         else "does not exist"))  # fmt: skip
    try:
        return Rig.from_calibration_json(path), str(path)
    except CalibrationError as e:  # its message names the file as given, mostly: never twice
        raise ExportError(str(e) if str(path) in str(e) else f"calibration {path}: {e}") from None


# ---- set-up ---------------------------------------------------------------------------------------------------


def load_weights(run: ExportRun) -> None:
    opts = run.opts
    checkpoint = opts.checkpoint if opts.checkpoint is not None else bundled_checkpoint(run.preset.name)
    try:
        run.det, run.source = load_detector(run.preset, checkpoint, opts.seed)
    except ValueError as e:
        raise ExportError(str(e)) from None
    run.note(run.source.describe())


def build_lut_file(run: ExportRun) -> None:
    run.rig, run.calibration_source = load_rig(run.opts.calibration)
    try:  # --resolution of another aspect than the cameras': streamdet-calib would refuse this export's rig later
        check_rig_fits(run.rig, run.rig.names, *run.size)
    except CalibrationError as e:
        raise ExportError(f"--resolution {run.size[0]}x{run.size[1]} does not fit the calibration ({run.calibration_source}): "
                          f"{e}; give a size of the cameras' aspect") from None  # fmt: skip
    run.lut = build_lut(run.rig, run.preset.grid, run.preset.image.feature_stride, run.size,
                        heights_per_voxel=run.preset.lifter.lut_heights_per_voxel)  # fmt: skip
    run.lut.save(run.tmp / LUT_NAME)
    run.note(f"{len(run.rig)} cameras, K = {run.lut.num_slots} slots, from {run.calibration_source}")


def prepare_parity_inputs(run: ExportRun) -> None:
    run.inputs = parity_inputs(run.rig, run.lut, run.preset, run.size, run.opts.num_slices, run.opts.seed)
    run.note(run.inputs.describe())


# ---- fp32: each graph exported and checked against PyTorch ----------------------------------------------------


def chained_feeds(run: ExportRun, name: str, upstream: np.ndarray | None) -> Feeds:
    """Graph ``name``'s parity feeds with ``upstream``, the first output of the graph before it, in place."""
    inputs = run.inputs
    if name == "image_encoder":
        return {"images": inputs.images_read}  # (J', H, W, 3)
    if name == "volumetric_lifter":
        lut_index, lut_weight = run.lut.for_quadrants(inputs.quadrants)
        features = scatter_cameras(upstream, inputs.cameras, len(inputs.images))  # (J, C, Hf, Wf)
        j, _, hf, wf = features.shape  # the LUT in the export's layout (core/lut_layout.py)
        return {"features": features, **lifter_lut_feeds(lut_index, lut_weight, j * hf * wf, run.opts.lut_layout == LUT_COMPACT)}
    if run.preset.use_image:  # the image BEV, or its image half (the export's image layout names the input)
        return {**inputs.pillars.as_feeds(), run.graph_io("slice_head").inputs[3]: upstream}
    if not run.preset.slice_crop:
        return inputs.pillars.as_feeds()  # the pillar tensors alone: one map of the whole grid
    return inputs.pillars.as_feeds(inputs.quadrants)  # the pillar tensors and the quadrant ids


def _session(run: ExportRun, name: str, precision: str):
    return ort_session(str(run.tmp / graph_file_name(name, precision)))


def _run_fp32(run: ExportRun, name: str) -> tuple[Feeds, list[np.ndarray]]:
    """Feed graph ``name`` (fp32, written) by the fp32 graph before it; remember feeds and outputs."""
    upstream = run.outputs32[run.graphs[run.graphs.index(name) - 1]][0] if name != run.graphs[0] else None
    feeds = chained_feeds(run, name, upstream)
    run.feeds32[name] = feeds
    run.outputs32[name] = _session(run, name, "fp32").run(None, feeds)
    return feeds, run.outputs32[name]


def _note_parity(run: ExportRun, records: list[ParityRecord]) -> None:
    run.parity.extend(records)
    for p in records:
        run.note(format_parity(p))
    # a detection check that compared few detections, or none, passes on little evidence: say so once
    # (export/parity.py; the note of a record that compared nothing starts with NOT_COMPARED, then the warning)
    warned = next((p for p in records if p.passed and (p.note.startswith(FEW_COMPARED) or math.isnan(p.max_abs_diff))), None)
    if warned is not None:
        run.note(f"{warned.graph} {warned.precision}: {warned.note}")


@torch.no_grad()
def export_image_encoder(run: ExportRun) -> None:
    model = ox.export_image_encoder(run.det, torch.from_numpy(run.inputs.images_read), run.opts.opset)
    save_checked(model, run.tmp, "image_encoder", "fp32")


@torch.no_grad()
def parity_image_encoder(run: ExportRun) -> None:
    # Only the cameras the LUT reads for the parity quadrants are encoded; the others' rows are never gathered,
    # so zeros there give the lifter the same output (and halve the encoder's share of the time).
    feeds, (features_read,) = _run_fp32(run, "image_encoder")
    # PyTorch on at most TORCH_REF_IMAGES of them: the encoder treats images independently, and the paper preset's
    # ResNet-50 at full resolution is costly on a CPU shared with the rest of the export.
    n_ref = min(TORCH_REF_IMAGES, len(run.inputs.cameras))
    ref = run.det.image_encoder(torch.from_numpy(feeds["images"][:n_ref])).numpy()
    _note_parity(run, [compare_dense("image_encoder", "fp32", "torch", "features", features_read[:n_ref], ref, TORCH_TOL_REL,
                                     TORCH_SCALE_FLOOR)])


@torch.no_grad()
def export_volumetric_lifter(run: ExportRun) -> None:
    feeds = chained_feeds(run, "volumetric_lifter", run.outputs32["image_encoder"][0])
    # the K-slot LUT: what the trained lifter (the reference) reads, whatever the graph's LUT layout
    args = (torch.from_numpy(feeds["features"]), *(torch.from_numpy(a) for a in run.lut.for_quadrants(run.inputs.quadrants)))
    layout = run.opts.image_layout
    model = ox.export_volumetric_lifter(run.det, *args, run.opts.opset, layout, run.opts.lut_layout)
    save_checked(model, run.tmp, "volumetric_lifter", "fp32")
    _, (image_map,) = _run_fp32(run, "volumetric_lifter")
    ref = run.det.lifter(*args)  # (Q, C, Yq, Xq)
    if layout == IMAGE_HALF:  # the BEV encoder's image half of PyTorch's image BEV (the export form's conv, no bias)
        ref = to_export_form(run.det, layout).slice_head.slice_net.image_conv(ref)  # (Q, C0, Yh, Xh)
    _note_parity(run, [compare_dense("volumetric_lifter", "fp32", "torch", layout, image_map, ref.numpy(), TORCH_TOL_REL,
                                     TORCH_SCALE_FLOOR)])


@torch.no_grad()
def export_slice_head(run: ExportRun) -> None:
    upstream = run.outputs32["volumetric_lifter"][0] if run.preset.use_image else None
    feeds = chained_feeds(run, "slice_head", upstream)
    args = tuple(torch.from_numpy(feeds[n]) for n in run.graph_io("slice_head").inputs)
    save_checked(ox.export_slice_head(run.det, args, run.opts.opset, run.opts.image_layout), run.tmp, "slice_head", "fp32")
    _, dets = _run_fp32(run, "slice_head")
    image_bev = args[3] if run.preset.use_image else None  # a LiDAR-only net reads the map count only
    if run.preset.use_image and run.opts.image_layout == IMAGE_HALF:
        # PyTorch's SliceNet takes the image BEV: PyTorch's own lift of the lifter's parity feeds, so the graphs'
        # split (image half in the lifter graph, added in the slice graph) is checked against the trained modules
        features = torch.from_numpy(run.feeds32["volumetric_lifter"]["features"])
        lut = (torch.from_numpy(a) for a in run.lut.for_quadrants(run.inputs.quadrants))  # the K-slot LUT
        image_bev = run.det.lifter(features, *lut)  # (Q, C, Yq, Xq)
    maps = run.det.slice_net(*args[:3], image_bev, num_quadrants=run.inputs.num_maps)
    ref = reference_decode(maps, run.preset)
    run.margins_of = ref  # the fp16 checks read its near-tie margins and its (K+1)-th scores too
    _note_parity(run, compare_detections("slice_head", "fp32", "torch", dets, ref.dets, TORCH_TOL_REL, ref(ref.dets),
                                         TORCH_SCALE_FLOOR, first_left_out=ref.first_left_out))


@dataclass(frozen=True, eq=False)
class ReferenceDecode:
    """PyTorch's decode of the slice graph's head maps on the parity inputs: its top-K detections (det_boxes,
    det_scores, det_labels), each quadrant's best score left out of the top K (the (K+1)-th, decoded for it; -inf
    where the top K holds every cell), and the peak margins and cell centres the near-tie exclusions read. Called on
    decoded detections, it gives their peak margins (``detection_margins``).

    The set comparisons (export/parity.py) compare a detection when its score clears the (K+1)-th by the tolerance;
    the K-th score in its place would leave the K-th detection itself out, and with --top-k 1 every detection. The
    fp16 check's reference is the fp32 graph, whose (K+1)-th score is not in its outputs: PyTorch's stands in, within
    the fp32 tolerance of it, a hundredth of the fp16 one."""

    dets: list[np.ndarray]
    first_left_out: np.ndarray  # (Q,) float64
    margins: np.ndarray  # (Q, C, Hh, Wh) ``peak_margins``
    centres: np.ndarray  # (Q, 2, Hh, Wh) ``cell_centres``

    def __call__(self, dets: Sequence[np.ndarray]) -> np.ndarray:
        return detection_margins(dets[0], dets[2], self.margins, self.centres)


def reference_decode(maps, preset: Preset) -> ReferenceDecode:
    """PyTorch's decoded detections of the head maps, one more than the graph's K where the map has it."""
    k = preset.top_k
    heatmap = maps[0]
    cells = int(heatmap.shape[1]) * int(heatmap.shape[2]) * int(heatmap.shape[3])  # classes x cells of a map
    decoded = [t.numpy() for t in decode_head_maps(maps, preset.head_cell_m, min(k + 1, cells))]
    scores = decoded[1]
    first_left_out = scores[:, k].astype(np.float64) if scores.shape[1] > k else np.full(scores.shape[0], -np.inf)
    return ReferenceDecode(
        dets=[a[:, :k] for a in decoded],
        first_left_out=first_left_out,
        margins=peak_margins(heatmap.numpy()),
        centres=cell_centres(maps[1].numpy(), preset.head_cell_m),
    )


def count_gmacs(run: ExportRun) -> None:
    # the K-slot LUT the trained lifter reads (the compact layout's graph reads fewer rows, the convolutions dominate)
    lut_index, lut_weight = run.lut.for_quadrants(run.inputs.quadrants) if run.preset.use_image else (None, None)
    run.gmacs = graph_gmacs(run.det, run.inputs, lut_index, lut_weight, run.opts.image_layout)
    run.note(", ".join(f"{k} {v:.2f}" for k, (v, _) in run.gmacs.items()))


# ---- fp16 -----------------------------------------------------------------------------------------------------


def convert_fp16(run: ExportRun, name: str) -> None:
    model32 = onnx.load(str(run.tmp / graph_file_name(name, "fp32")))
    keep = fp32_nodes(model32) if name == "slice_head" else set()
    model16, kept = convert_model_to_fp16(model32, lambda n: n.name in keep)
    save_checked(model16, run.tmp, name, "fp16")
    if kept:
        run.note(f"{len(kept)} nodes kept in fp32 (decode and heatmap logits)")


def fp32_nodes(model: onnx.ModelProto) -> set[str]:
    """Nodes of the slice graph kept in fp32: the decode and the convs that make the heatmap logits."""
    return {n.name for n in model.graph.node if ox.is_decode_node(n)} | set(ox.heatmap_producers(model))


def parity_fp16(run: ExportRun) -> None:
    """Each fp16 graph against its fp32 graph on the same inputs, then the fp16 pipeline against the fp32 pipeline:
    the parity slice through the runtime at each precision (``driver_slice``); for a LiDAR-only export the slice
    graph is the pipeline."""
    sessions16 = {name: _session(run, name, "fp16") for name in run.graphs}
    for name in run.graphs:
        got = sessions16[name].run(None, run.feeds32[name])
        ref = run.outputs32[name]
        if name in DENSE_GRAPHS:  # the output's name is the layout's (image_bev or image_half), as in the fp32 record
            _note_parity(run, [compare_dense(name, "fp16", "onnx-fp32", run.graph_io(name).outputs[0], got[0], ref[0],
                                             FP16_TOL_REL, FP16_SCALE_FLOOR)])
        else:
            _note_parity(run, compare_detections(name, "fp16", "onnx-fp32", got, ref, FP16_TOL_REL, run.margins_of(ref),
                                                   FP16_SCALE_FLOOR, first_left_out=run.margins_of.first_left_out))
    if not all(p.passed for p in run.parity if p.precision == "fp32"):
        # the runtime refuses those graphs; the export is recorded as failed either way (and kept apart: staging.py)
        run.note("fp16 pipeline check not run: the fp32 graphs failed their check against PyTorch")
        return
    result, dets = driver_slice(staged_detector(run, "fp32"), run)
    _, dets16 = driver_slice(staged_detector(run, "fp16"), run)
    run.pipeline = _pipeline_check(run, result, dets, dets16)


def driver_slice(detector: StreamingDetector, run: ExportRun) -> tuple[SliceResult, tuple[np.ndarray, ...]]:
    """The parity slice through the runtime as a vehicle feeds it: the parity images (those of the cameras that see
    the slice's quadrants are encoded and lifted), then the slice's points; the detector's result and its slice
    graph's outputs (det_boxes, det_scores, det_labels)."""
    inputs = run.inputs
    with detector.recording() as recording:
        if detector.uses_images:
            images = dict(zip(detector.camera_names, inputs.images))
            detector.update_images(images, timestamp=0.0, quadrants=sorted(inputs.quadrants))
        result = detector.detect_slice(inputs.points, inputs.slice_index, timestamp=0.0, num_slices=run.opts.num_slices)
    runs = recording.outputs("slice_head")
    if not runs:
        raise ExportError(f"the parity slice {inputs.slice_index} holds no pillar: no pipeline to compare")
    return result, runs[0]


def _pipeline_check(run: ExportRun, result: SliceResult, dets: Sequence[np.ndarray], dets16: Sequence[np.ndarray]):
    """The decoded boxes of the fp32 and fp16 pipelines compared (``pipeline_parity``), reported in one line."""
    outputs = ox.SLICE_HEAD_IO.outputs
    pipeline = pipeline_parity(
        dict(zip(outputs, dets)),
        dict(zip(outputs, dets16)),
        slice_index=result.slice_index,
        num_slices=result.num_slices,
        num_points=result.num_points,
        num_pillars=result.num_pillars,
        cell_m=run.preset.head_cell_m,
        margins32=run.margins_of(dets),
        margins16=run.margins_of(dets16),
    )
    run.note(
        f"pipeline: {pipeline.count_fp32} vs {pipeline.count_fp16} boxes >= {pipeline.score_threshold}, "
        f"{pipeline.excluded_in_band} in the +-{pipeline.score_band:.2g} band, {pipeline.excluded_at_top_k} "
        f"at the top-K cut, {pipeline.excluded_near_ties} near-ties, max centre diff "
        f"{pipeline.max_centre_diff_m:.3g} m: {'ok' if pipeline.passed else 'FAILED'}"
    )
    run.note(f"pipeline: {pipeline.note}")  # the other box columns' differences, and a warning if few were compared
    return pipeline


# ---- the manifest ---------------------------------------------------------------------------------------------


def write_manifest(run: ExportRun) -> None:
    manifest = run_manifest(run, run.opts.precisions, run.int8_record)
    # the seed of the parity check's noise images (a rig of cameras the bundled sample lacks), so the recorded parity
    # can be reproduced: source.seed is the weights' and None for a checkpoint; None here where the images are real
    noise = run.inputs.images is not None and not run.inputs.real_images
    run.manifest = dataclasses.replace(manifest, source={**manifest.source, "parity_seed": run.opts.seed if noise else None})
    write_manifest_file(run.manifest, run.tmp)
