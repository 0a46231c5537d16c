"""One export run: weights -> three ONNX graphs (+ fp16 siblings), lut.npz, parity checks, manifest.json.

Everything is written into a temporary directory beside the target and renamed into place at the end, with the
manifest written last, so a failed or interrupted export never leaves a directory that looks complete.

With ``int8``, ``export/int8.py`` quantizes the three fp32 graphs into ``*.int8.onnx``, calibrated on real samples
(a ``--calibration-data`` dataset, else the bundled sample), and records their calibration and parity against fp32.

A LiDAR-only checkpoint (preset use_image=False, the paper's streaming baseline; recognised from the checkpoint's
preset) exports the slice graph alone (``onnx_export.LIDAR_SLICE_HEAD_IO``: no image_bev input) with its fp16 /
int8 siblings and parity checks, and a manifest without image spec, normalisation or LUT: no rig, no images.

The parity inputs are real: the bundled nuScenes sample's six images (resized to the export resolution) and its
LiDAR sweep, cut into ``num_slices`` slices; the slice with the most points is pillarized with
``runtime_ort/pillarize.py``. The fp32 pipeline (encoder -> lifter with the LUT -> slice graph) is onnxruntime's,
and each graph's PyTorch reference sees the same inputs as its onnxruntime counterpart.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.resources
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.lut import Lut, build_lut
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.constants import BUNDLED_CALIBRATION_SOURCE
from streamdet.core.sectors import check_num_slices
from streamdet.data.sample import Sample, load_bundled_sample
from streamdet.data.slicing import slice_sample
from streamdet.export import onnx_export as ox
from streamdet.export import int8 as q8
from streamdet.export.fp16 import check_model, convert_model_to_fp16
from streamdet.export.parity import (
    FP16_TOL_REL,
    TORCH_TOL_REL,
    cell_centres,
    compare_dense,
    compare_detections,
    detection_margins,
    ort_session,
    peak_margins,
    pipeline_parity,
)
from streamdet.export.weights import (
    DEFAULT_SEED,
    WeightsSource,
    bundled_checkpoint,
    checkpoint_preset,
    checkpoint_use_image,
    load_detector,
)
from streamdet.models.decode import decode_head_maps
from streamdet.models.detector import StreamDetector
from streamdet.models.flops import count_gmac
from streamdet.models.image_encoder import IMAGENET_MEAN, IMAGENET_STD
from streamdet.models.presets import Preset, get_preset, preset_names
from streamdet.runtime_ort.manifest import (
    LUT_NAME,
    MANIFEST_NAME,
    GraphEntry,
    ImageSpec,
    Int8Calibration,
    Int8GraphRecord,
    Int8Record,
    LutEntry,
    Manifest,
    Normalisation,
    ParityRecord,
    PipelineParity,
    TensorSpec,
    graph_file_name,
    sha256_file,
    write_manifest,
)
from streamdet.runtime_ort.pillarize import Pillars, pillarize

BUNDLED_CALIBRATION = BUNDLED_CALIBRATION_SOURCE
DEFAULT_PRESET = "small"  # the shipped model's preset: what streamdet-export exports without arguments
STEM_STRIDE = 2  # the ResNet stem's stride: image sizes must be even
TORCH_REF_IMAGES = 2  # images the PyTorch encoder reference runs on (onnxruntime runs all J)


class ExportError(Exception):
    """A problem with the export's inputs or target, stated in one line."""


@dataclass(frozen=True)
class ExportOptions:
    preset: str | None = None  # None: the preset the checkpoint names, else DEFAULT_PRESET
    checkpoint: str | None = None  # None: models/weights/<preset>.pt if bundled, else fixed-seed weights
    calibration: str | None = None  # calibration.json path; None: the bundled nuScenes sample's
    resolution: tuple[int, int] | None = None  # (W, H) px of the camera images; None: the preset's
    num_slices: int = 8  # slices per sweep (the paper's headline model); picks the parity slice
    fp16: bool = False  # also write *.fp16.onnx siblings
    int8: bool = False  # also write *.int8.onnx siblings (static QDQ, calibrated on real samples)
    calibration_data: str | None = None  # nuScenes-format dataset for the int8 calibration; None: the bundled sample
    calibration_samples: int = q8.DEFAULT_CALIBRATION_SAMPLES  # samples drawn from calibration_data (its train split)
    opset: int = ox.DEFAULT_OPSET
    out_dir: str | None = None  # None: ./exports/<preset>
    seed: int = DEFAULT_SEED  # torch seed of the initial weights when there is no checkpoint


@dataclass(frozen=True)
class ExportResult:
    out_dir: Path
    manifest: Manifest
    seconds: float

    @property
    def parity_passed(self) -> bool:
        pipeline_ok = self.manifest.pipeline_parity is None or self.manifest.pipeline_parity.passed
        return pipeline_ok and all(p.passed for p in self.manifest.parity)


Report = Callable[[str], None]


def check_resolution(width: int, height: int) -> None:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0 or v % STEM_STRIDE:
            raise ExportError(
                f"resolution {width}x{height}: {name} {v!r} must be a positive even number of pixels "
                f"(the ResNet stem has stride {STEM_STRIDE}; features are ceil(size / 4))"
            )


def load_rig(calibration: str | None) -> tuple[Rig, str]:
    """The rig and a description of where it came from."""
    if calibration is None:
        res = importlib.resources.files("streamdet.data") / "nuscenes_sample" / "calibration.json"
        return Rig.from_calibration_json(res), BUNDLED_CALIBRATION
    path = Path(calibration)
    if not path.is_file():
        raise ExportError(f"calibration file {path} does not exist")
    try:
        return Rig.from_calibration_json(path), str(path)
    except CalibrationError as e:
        raise ExportError(f"calibration {path}: {e}") from None


def run_export(opts: ExportOptions, report: Report | None = None) -> ExportResult:
    """Run the whole export; raises ExportError (one line) for bad options or an unusable target directory."""
    report = report or (lambda _msg: None)
    t_start = time.perf_counter()
    preset, width, height = _resolve_preset(opts)
    try:
        check_num_slices(opts.num_slices)
    except ValueError as e:
        raise ExportError(f"--slices: {e}") from None
    lo, hi = ox.OPSET_RANGE
    if isinstance(opts.opset, bool) or not isinstance(opts.opset, int) or not lo <= opts.opset <= hi:
        raise ExportError(f"--opset must be an integer in [{lo}, {hi}], got {opts.opset!r}")
    _check_int8_options(opts)
    out_dir = Path(opts.out_dir) if opts.out_dir is not None else Path("exports") / preset.name
    tmp = _make_staging_dir(out_dir)
    if preset.use_image:
        steps = _Steps(report, total=10 + (4 if opts.fp16 else 0) + (5 if opts.int8 else 0))
    else:
        steps = _Steps(report, total=6 + (2 if opts.fp16 else 0) + (3 if opts.int8 else 0))
    export_into = _export_into if preset.use_image else _export_lidar_only_into
    try:
        manifest = export_into(tmp, preset, width, height, opts, steps)
        with steps("moving the export into place"):
            _commit(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ExportResult(out_dir.resolve(), manifest, time.perf_counter() - t_start)


# ---- the steps ---------------------------------------------------------------------------------------


def _export_into(tmp: Path, preset: Preset, width: int, height: int, opts: ExportOptions, steps: "_Steps") -> Manifest:
    det, source = _load_weights(preset, opts, steps, "loading weights")
    with steps(f"building the LUT for {width}x{height}"):
        rig, calib_source = load_rig(opts.calibration)
        lut = build_lut(rig, preset.grid, preset.image.feature_stride, (width, height))
        lut.save(tmp / LUT_NAME)
        steps.note(f"{len(rig)} cameras, K = {lut.num_slots} slots, from {calib_source}")
    with steps("preparing the parity inputs (bundled sample)"):
        inputs = _parity_inputs(rig, lut, preset, width, height, opts.num_slices, opts.seed)
        steps.note(inputs.describe())

    parity: list[ParityRecord] = []
    cams = list(inputs.cameras)
    images_read = inputs.images[cams]  # (J', H, W, 3): the cameras the parity quadrants read
    with torch.no_grad():
        with steps("exporting image_encoder.onnx"):
            model = ox.export_image_encoder(det, torch.from_numpy(images_read), opts.opset)
            _save_checked(model, tmp, "image_encoder", "fp32")
        with steps("parity image_encoder (onnxruntime fp32 vs PyTorch)"):
            enc = ort_session(str(tmp / graph_file_name("image_encoder", "fp32")))
            # Only the cameras the LUT reads for the parity quadrants are encoded; the others' rows are never
            # gathered, so zeros there give the lifter the same output (and halve the encoder's share of the time).
            (features_read,) = enc.run(None, {"images": images_read})
            features = _scatter_cameras(features_read, cams, len(inputs.images))  # (J, C, Hf, Wf)
            # PyTorch on at most TORCH_REF_IMAGES of them: the encoder treats images independently, and at the
            # paper's 1600x900 each ResNet-50 forward costs 126 GMAC on a CPU shared with the rest of the export.
            n_ref = min(TORCH_REF_IMAGES, len(cams))
            ref = det.image_encoder(torch.from_numpy(images_read[:n_ref])).numpy()
            parity.append(compare_dense("image_encoder", "fp32", "torch", "features", features_read[:n_ref], ref, TORCH_TOL_REL))
            steps.note(_fmt(parity[-1]))
            del ref
        with steps("exporting volumetric_lifter.onnx and checking parity"):
            lut_index, lut_weight = lut.for_quadrants(inputs.quadrants)
            lift_args = (torch.from_numpy(features), torch.from_numpy(lut_index), torch.from_numpy(lut_weight))
            model = ox.export_volumetric_lifter(det, *lift_args, opts.opset)
            _save_checked(model, tmp, "volumetric_lifter", "fp32")
            lifter_feeds = {"features": features, "lut_index": lut_index, "lut_weight": lut_weight}
            (image_bev,) = ort_session(str(tmp / graph_file_name("volumetric_lifter", "fp32"))).run(None, lifter_feeds)
            ref = det.lifter(*lift_args).numpy()
            parity.append(compare_dense("volumetric_lifter", "fp32", "torch", "image_bev", image_bev, ref, TORCH_TOL_REL))
            steps.note(_fmt(parity[-1]))
        with steps("exporting slice_head.onnx and checking parity"):
            pl = inputs.pillars
            slice_feeds = {**pl.as_feeds(), "image_bev": image_bev}
            slice_args = tuple(torch.from_numpy(slice_feeds[n]) for n in ox.SLICE_HEAD_IO.inputs)
            model = ox.export_slice_head(det, slice_args, opts.opset)
            _save_checked(model, tmp, "slice_head", "fp32")
            dets = ort_session(str(tmp / graph_file_name("slice_head", "fp32"))).run(None, slice_feeds)
            maps = det.slice_net(*slice_args)  # the reference head maps, for the decode and the near-tie test
            ref_dets, margins_of = _reference_decode(maps, preset)
            parity.extend(compare_detections("slice_head", "fp32", "torch", dets, ref_dets, TORCH_TOL_REL, margins_of(ref_dets)))
            for p in parity[-3:]:
                steps.note(_fmt(p))
        with steps("counting GMAC"):
            gmacs = _count_gmacs(det, inputs, lut_index, lut_weight)
            steps.note(", ".join(f"{k} {v:.2f}" for k, (v, _) in gmacs.items()))

    pipeline: PipelineParity | None = None
    if opts.fp16:
        sessions16 = {}
        for name in ox.GRAPH_IO:
            with steps(f"converting {name} to fp16"):
                model32 = onnx.load(str(tmp / graph_file_name(name, "fp32")))
                keep = _fp32_nodes(model32) if name == "slice_head" else set()
                model16, kept = convert_model_to_fp16(model32, lambda n: n.name in keep)
                _save_checked(model16, tmp, name, "fp16")
                sessions16[name] = ort_session(str(tmp / graph_file_name(name, "fp16")))
                if kept:
                    steps.note(f"{len(kept)} nodes kept in fp32 (decode and heatmap logits)")
        with steps("parity fp16 vs fp32, graph by graph and whole pipeline"):
            (features16_read,) = sessions16["image_encoder"].run(None, {"images": images_read})
            parity.append(compare_dense("image_encoder", "fp16", "onnx-fp32", "features", features16_read, features_read, FP16_TOL_REL))
            features16 = _scatter_cameras(features16_read, cams, len(inputs.images))
            (bev16_same,) = sessions16["volumetric_lifter"].run(None, lifter_feeds)
            parity.append(compare_dense("volumetric_lifter", "fp16", "onnx-fp32", "image_bev", bev16_same, image_bev, FP16_TOL_REL))
            dets16_same = sessions16["slice_head"].run(None, slice_feeds)
            parity.extend(compare_detections("slice_head", "fp16", "onnx-fp32", dets16_same, dets, FP16_TOL_REL, margins_of(dets)))
            # the fp16 pipeline: each fp16 graph fed by the previous fp16 graph
            (bev16,) = sessions16["volumetric_lifter"].run(None, {**lifter_feeds, "features": features16})
            dets16 = sessions16["slice_head"].run(None, {**pl.as_feeds(), "image_bev": bev16})
            for p in parity[-5:]:
                steps.note(_fmt(p))
            pipeline = _pipeline_check(ox.SLICE_HEAD_IO.outputs, dets, dets16, margins_of, inputs.slice_index,
                                       inputs.num_points, pl.num_pillars, preset, opts, steps)  # fmt: skip

    int8_record = _export_int8(tmp, preset, width, height, rig, lut, opts, steps) if opts.int8 else None

    with steps("writing manifest.json"):
        image = ImageSpec(width, height, preset.image.feature_stride, lut.feature_width, lut.feature_height, tuple(rig.names))
        return _write_manifest(
            tmp, preset, opts, tuple(ox.GRAPH_IO), gmacs, parity, pipeline, int8_record, source, inputs.describe(),
            image=image,
            normalisation=Normalisation(mean_rgb=tuple(IMAGENET_MEAN), std_rgb=tuple(IMAGENET_STD)),
            lut=LutEntry(LUT_NAME, sha256_file(tmp / LUT_NAME), lut.calibration_sha256, calib_source),
        )


def _export_lidar_only_into(tmp: Path, preset: Preset, width: int, height: int, opts: ExportOptions, steps: "_Steps") -> Manifest:
    """The LiDAR-only export: slice_head.onnx (+ fp16 / int8 siblings), its parity checks, manifest.json.

    The PyTorch reference is the slice net on a zero image BEV, exactly as ``training/torch_eval.py`` runs the
    baseline; the graph gets the quadrant ids instead (``onnx_export.LidarSliceDecoder``), so the check also covers
    that substitution. ``width`` and ``height`` are unused: there are no images.
    """
    det, source = _load_weights(preset, opts, steps, "loading weights (LiDAR-only model: slice graph only)")
    with steps("preparing the parity inputs (bundled sample, LiDAR only)"):
        pl, quadrants, slice_index, num_points = _busiest_slice(load_bundled_sample(), preset, opts.num_slices)
        parity_input = (f"LiDAR slice {slice_index} ({num_points} points, {pl.num_pillars} pillars, quadrants "
                        f"{list(quadrants)}) of the bundled nuScenes sample; no images (LiDAR-only model)")  # fmt: skip
        steps.note(parity_input)

    parity: list[ParityRecord] = []
    slice_feeds = pl.as_feeds(quadrants)  # the pillar tensors and the quadrant ids
    g = preset.grid
    with torch.no_grad():
        with steps("exporting slice_head.onnx and checking parity"):
            slice_args = tuple(torch.from_numpy(slice_feeds[n]) for n in ox.LIDAR_SLICE_HEAD_IO.inputs)
            model = ox.export_lidar_slice_head(det, slice_args, opts.opset)
            _save_checked(model, tmp, "slice_head", "fp32")
            dets = ort_session(str(tmp / graph_file_name("slice_head", "fp32"))).run(None, slice_feeds)
            zero_bev = torch.zeros(len(quadrants), preset.channels, g.quadrant_ny, g.quadrant_nx)
            maps = det.slice_net(*slice_args[:3], zero_bev)  # the reference head maps, for the decode and near-ties
            ref_dets, margins_of = _reference_decode(maps, preset)
            parity.extend(compare_detections("slice_head", "fp32", "torch", dets, ref_dets, TORCH_TOL_REL, margins_of(ref_dets)))
            for p in parity[-3:]:
                steps.note(_fmt(p))
        with steps("counting GMAC"):
            meta = torch.device("meta")
            on_meta = lambda a: torch.empty(a.shape, dtype=torch.from_numpy(a[:0]).dtype, device=meta)  # noqa: E731
            net = copy.deepcopy(det.slice_net).to(meta)
            gmac = count_gmac(net, on_meta(pl.features), on_meta(pl.mask), on_meta(pl.index), zero_bev.to(meta))
            gmacs = {"slice_head": (gmac, {"Q": len(quadrants), "P": pl.num_pillars})}
            steps.note(f"slice_head {gmac:.2f}")

    pipeline: PipelineParity | None = None
    if opts.fp16:
        with steps("converting slice_head to fp16"):
            model32 = onnx.load(str(tmp / graph_file_name("slice_head", "fp32")))
            keep = _fp32_nodes(model32)
            model16, kept = convert_model_to_fp16(model32, lambda n: n.name in keep)
            _save_checked(model16, tmp, "slice_head", "fp16")
            steps.note(f"{len(kept)} nodes kept in fp32 (decode and heatmap logits)")
        with steps("parity fp16 vs fp32 (the slice graph is the whole pipeline)"):
            dets16 = ort_session(str(tmp / graph_file_name("slice_head", "fp16"))).run(None, slice_feeds)
            parity.extend(compare_detections("slice_head", "fp16", "onnx-fp32", dets16, dets, FP16_TOL_REL, margins_of(dets)))
            for p in parity[-3:]:
                steps.note(_fmt(p))
            pipeline = _pipeline_check(ox.LIDAR_SLICE_HEAD_IO.outputs, dets, dets16, margins_of, slice_index,
                                       num_points, pl.num_pillars, preset, opts, steps)  # fmt: skip

    int8_record = _export_int8(tmp, preset, width, height, None, None, opts, steps) if opts.int8 else None

    with steps("writing manifest.json"):
        return _write_manifest(tmp, preset, opts, ("slice_head",), gmacs, parity, pipeline, int8_record, source, parity_input)


def _write_manifest(
    tmp: Path, preset: Preset, opts: ExportOptions, graph_names: tuple[str, ...], gmacs: dict[str, tuple[float, dict]],
    parity: list[ParityRecord], pipeline: PipelineParity | None, int8_record: Int8Record | None, source: WeightsSource,
    parity_input: str, *, image: ImageSpec | None = None, normalisation: Normalisation | None = None,
    lut: LutEntry | None = None,
) -> Manifest:
    """manifest.json of an export in ``tmp``: every graph of ``graph_names`` in every precision written; image,
    normalisation and lut stay None for a LiDAR-only export."""
    precisions = ("fp32",) + (("fp16",) if opts.fp16 else ()) + (("int8",) if opts.int8 else ())
    entries = [_graph_entry(tmp, name, precision, opts.opset, gmacs[name]) for precision in precisions for name in graph_names]
    manifest = Manifest(
        preset_name=preset.name,
        preset=preset.to_dict(),
        grid=preset.grid.to_dict(),
        class_names=tuple(CLASS_NAMES),
        num_slices=opts.num_slices,
        image=image,
        normalisation=normalisation,
        post={**preset.to_dict()["post"], "top_k_per_quadrant": preset.top_k, "head_cell_m": preset.head_cell_m},
        graphs=tuple(entries),
        lut=lut,
        parity=tuple(parity),
        pipeline_parity=pipeline,
        int8=int8_record,
        source={
            "checkpoint": source.checkpoint,
            "checkpoint_sha256": source.checkpoint_sha256,
            "seed": source.seed,
            "parity_input": parity_input,
            "torch": torch.__version__,
            "onnx": onnx.__version__,
            "onnxruntime": ort.__version__,
        },
    )
    write_manifest(manifest, tmp)
    return manifest


def _check_int8_options(opts: ExportOptions) -> None:
    """Fail before any work on int8 options that cannot be used."""
    if opts.calibration_data is not None and not opts.int8:
        raise ExportError("--calibration-data is the int8 calibration set: it needs --int8")
    n = opts.calibration_samples
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ExportError(f"--calibration-samples must be a positive integer, got {n!r}")
    if opts.int8 and opts.calibration_data is not None:
        try:
            q8.dataset_version(opts.calibration_data)
        except q8.CalibrationError as e:
            raise ExportError(f"--calibration-data: {e}") from None


def _export_int8(
    tmp: Path, preset: Preset, width: int, height: int, rig: Rig | None, lut: Lut | None, opts: ExportOptions, steps: "_Steps"
) -> Int8Record:
    """Quantize the fp32 graphs in ``tmp`` into ``*.int8.onnx``; calibration, parity, the manifest record.

    A LiDAR-only preset (no rig, no LUT) has the slice graph only, calibrated on pillarised slices without images.
    """
    if not preset.use_image:
        return _export_lidar_int8(tmp, preset, opts, steps)
    cfg = q8.Int8Config()
    size = (width, height)
    sessions32 = {name: ort_session(tmp / graph_file_name(name, "fp32")) for name in ox.GRAPH_IO}
    with steps("int8: calibration inputs (the fp32 encoder and lifter on real samples)"):
        t0 = time.perf_counter()
        try:
            cal = q8.load_calibration_samples(opts.calibration_data, opts.calibration_samples, rig.names)
            inputs = q8.graph_inputs(cal.samples, sessions32, rig.names, size, preset, opts.num_slices)
        except q8.CalibrationError as e:
            raise ExportError(str(e)) from None
        steps.note(
            f"{len(cal.samples)} samples of {cal.source} ({cal.version}, split {cal.split}): {sum(len(f['images']) for f in inputs.image_encoder)} "
            f"images, {len(inputs.volumetric_lifter)} volumes, {len(inputs.slice_head)} slices"
        )
    records = []
    for name in ox.GRAPH_IO:
        with steps(f"int8: quantizing {name}"):
            graph = q8.quantize_graph(name, tmp / graph_file_name(name, "fp32"), tmp / graph_file_name(name, "int8"), inputs.for_graph(name), cfg)
            check_model(graph.path)
            records.append(Int8GraphRecord(name, graph.quantized_ops, graph.float_nodes))
            steps.note(f"int8 inputs: {graph.quantized_ops}; kept float: {sum(graph.float_nodes.values())} nodes")
    calibration = Int8Calibration(
        source=cal.source,
        version=cal.version,
        split=cal.split,
        sample_tokens=tuple(s.token for s in cal.samples),
        num_images=sum(len(f["images"]) for f in inputs.image_encoder),
        num_volumes=len(inputs.volumetric_lifter),
        num_slices=len(inputs.slice_head),
        method=cfg.calibrate_method.name,
        reduce_range=cfg.reduce_range,
        parity_held_out=False,
        seconds=round(time.perf_counter() - t0, 1),
    )
    with steps("int8: parity against fp32 (relative L2 of every output, decoded boxes of all slices)"):
        sample = load_bundled_sample()
        if set(rig.names) <= set(sample.image_paths):
            held_out = cal.source != q8.BUNDLED_SOURCE
            if held_out:
                inputs = q8.graph_inputs([sample], sessions32, rig.names, size, preset, opts.num_slices, luts=[lut])
            steps.note("on the bundled nuScenes sample" + (", held out" if held_out else ", the calibration sample itself"))
        else:
            held_out = False  # a foreign rig: the bundled images do not fit, the calibration samples are all there is
            steps.note("on the calibration samples (the bundled sample lacks this rig's cameras)")
        sessions8 = {name: ort_session(tmp / graph_file_name(name, "int8")) for name in ox.GRAPH_IO}
        parity = q8.int8_parity(sessions32, sessions8, inputs, preset.head_cell_m)
        for p in parity.outputs:
            steps.note(f"{p.graph} {p.output} ({p.inputs} inputs): relative L2 error {p.rel_l2_error:.4f}, max |diff| {p.max_abs_diff:.3g}")
        b = parity.boxes
        steps.note(
            f"boxes >= {b.score_threshold}: {b.count_fp32} fp32, {b.count_int8} int8, {b.matched} matched, centre diff "
            f"mean {b.mean_centre_diff_m:.3g} m, max {b.max_centre_diff_m:.3g} m"
        )
    calibration = dataclasses.replace(calibration, parity_held_out=held_out)
    return Int8Record(calibration, tuple(records), parity.outputs, parity.boxes)


def _export_lidar_int8(tmp: Path, preset: Preset, opts: ExportOptions, steps: "_Steps") -> Int8Record:
    """int8 of a LiDAR-only export: the slice graph, calibrated on every non-empty slice of the samples (no images,
    so any rig's data will do), its parity against fp32 on the bundled sample (held out when it was not used)."""
    cfg = q8.Int8Config()
    src, dst = tmp / graph_file_name("slice_head", "fp32"), tmp / graph_file_name("slice_head", "int8")
    with steps("int8: calibration inputs (pillarised slices of real samples)"):
        t0 = time.perf_counter()
        try:
            cal = q8.load_calibration_samples(opts.calibration_data, opts.calibration_samples, ())
        except q8.CalibrationError as e:
            raise ExportError(str(e)) from None
        inputs = q8.graph_inputs(cal.samples, {}, (), (0, 0), preset, opts.num_slices)
        if not inputs.slice_head:
            raise ExportError(f"int8 calibration: the {len(cal.samples)} samples of {cal.source} hold no LiDAR point inside the grid")
        steps.note(f"{len(cal.samples)} samples of {cal.source} ({cal.version}, split {cal.split}): {len(inputs.slice_head)} slices")
    with steps("int8: quantizing slice_head"):
        graph = q8.quantize_graph("slice_head", src, dst, inputs.slice_head, cfg)
        check_model(graph.path)
        steps.note(f"int8 inputs: {graph.quantized_ops}; kept float: {sum(graph.float_nodes.values())} nodes")
    held_out = cal.source != q8.BUNDLED_SOURCE
    with steps("int8: parity against fp32 (slice graph on every slice of the bundled sample)"):
        if held_out:
            inputs = q8.graph_inputs([load_bundled_sample()], {}, (), (0, 0), preset, opts.num_slices)
        parity = q8.int8_parity({"slice_head": ort_session(src)}, {"slice_head": ort_session(dst)}, inputs, preset.head_cell_m)
        for p in parity.outputs:
            steps.note(f"{p.graph} {p.output}: relative L2 error {p.rel_l2_error:.4f}, max |diff| {p.max_abs_diff:.3g}")
    calibration = Int8Calibration(
        source=cal.source,
        version=cal.version,
        split=cal.split,
        sample_tokens=tuple(s.token for s in cal.samples),
        num_images=0,
        num_volumes=0,
        num_slices=graph.num_inputs,
        method=cfg.calibrate_method.name,
        reduce_range=cfg.reduce_range,
        parity_held_out=held_out,
        seconds=round(time.perf_counter() - t0, 1),
    )
    record = Int8GraphRecord("slice_head", graph.quantized_ops, graph.float_nodes)
    return Int8Record(calibration, (record,), parity.outputs, parity.boxes)


# ---- helpers -------------------------------------------------------------------------------------------


def _load_weights(preset: Preset, opts: ExportOptions, steps: "_Steps", label: str) -> tuple[StreamDetector, WeightsSource]:
    checkpoint = opts.checkpoint if opts.checkpoint is not None else bundled_checkpoint(preset.name)
    with steps(label):
        try:
            det, source = load_detector(preset, checkpoint, opts.seed)
        except ValueError as e:
            raise ExportError(str(e)) from None
        steps.note(source.describe())
    return det, source


def _pipeline_check(outputs, dets, dets16, margins_of, slice_index: int, num_points: int, num_pillars: int,
                    preset: Preset, opts: ExportOptions, steps: "_Steps") -> PipelineParity:  # fmt: skip
    """The decoded boxes of the fp32 and fp16 pipelines compared (``pipeline_parity``), reported in one line."""
    pipeline = pipeline_parity(
        dict(zip(outputs, dets)),
        dict(zip(outputs, dets16)),
        slice_index=slice_index,
        num_slices=opts.num_slices,
        num_points=num_points,
        num_pillars=num_pillars,
        cell_m=preset.head_cell_m,
        margins32=margins_of(dets),
        margins16=margins_of(dets16),
    )
    steps.note(
        f"pipeline: {pipeline.count_fp32} vs {pipeline.count_fp16} boxes >= {pipeline.score_threshold}, "
        f"{pipeline.excluded_in_band} in the +-{pipeline.score_band:.2g} band, {pipeline.excluded_at_top_k} "
        f"at the top-K cut, {pipeline.excluded_near_ties} near-ties, max centre diff "
        f"{pipeline.max_centre_diff_m:.3g} m: {'ok' if pipeline.passed else 'FAILED'}"
    )
    return pipeline


def _reference_decode(maps, preset: Preset):
    """PyTorch's decoded detections of the head maps, and the peak-margin lookup the near-tie exclusions use."""
    ref_dets = [t.numpy() for t in decode_head_maps(maps, preset.head_cell_m, preset.top_k)]
    margins = peak_margins(maps[0].numpy())  # (Q, C, Hh, Wh)
    centres = cell_centres(maps[1].numpy(), preset.head_cell_m)  # (Q, 2, Hh, Wh)
    return ref_dets, lambda d: detection_margins(d[0], d[2], margins, centres)


@dataclass(frozen=True, eq=False)
class _ParityInputs:
    images: np.ndarray  # (J, H, W, 3) uint8 in rig order
    real_images: bool  # False where the rig names cameras the bundled sample lacks (seeded noise instead)
    cameras: tuple[int, ...]  # rig indices of the cameras the LUT reads for `quadrants` (at least one)
    pillars: Pillars
    quadrants: tuple[int, ...]
    slice_index: int
    num_points: int

    def describe(self) -> str:
        imgs = "bundled nuScenes images" if self.real_images else "seeded noise images (the rig's cameras are not the sample's)"
        return (
            f"{self.images.shape[0]} {imgs} at {self.images.shape[2]}x{self.images.shape[1]} ({len(self.cameras)} read "
            f"by the parity quadrants and encoded), LiDAR slice "
            f"{self.slice_index} ({self.num_points} points, {self.pillars.num_pillars} pillars, quadrants {list(self.quadrants)})"
        )


def _parity_inputs(rig: Rig, lut: Lut, preset: Preset, width: int, height: int, num_slices: int, seed: int) -> _ParityInputs:
    sample: Sample = load_bundled_sample()
    if set(rig.names) <= set(sample.image_paths):
        from streamdet.data.sample import load_image

        images = np.stack([load_image(sample.image_paths[n], (width, height)) for n in rig.names])  # (J, H, W, 3)
        real = True
    else:
        images = np.random.default_rng(seed).integers(0, 256, (len(rig), height, width, 3), dtype=np.uint8)
        real = False
    pl, quadrants, k, num_points = _busiest_slice(sample, preset, num_slices)
    index, _ = lut.for_quadrants(quadrants)
    rows = np.unique(index[index != lut.sentinel])
    cams = tuple(int(j) for j in np.unique(rows // (lut.feature_width * lut.feature_height))) or (0,)
    return _ParityInputs(images, real, cams, pl, quadrants, k, num_points)


def _busiest_slice(sample: Sample, preset: Preset, num_slices: int) -> tuple[Pillars, tuple[int, ...], int, int]:
    """The pillars, quadrants, index and point count of the sample's slice with the most points (most pillars, most
    boxes): the parity slice."""
    slices = slice_sample(sample, num_slices)
    k = int(np.argmax([len(s.points) for s in slices]))
    sl = slices[k]
    pl = pillarize(sl.points, preset.grid, sl.quadrants, preset.pillars.max_points_per_pillar, preset.pillars.max_pillars)
    return pl, tuple(sl.quadrants), k, len(sl.points)


def _scatter_cameras(features_read: np.ndarray, cams: list[int], num_cameras: int) -> np.ndarray:
    """(J', C, Hf, Wf) features of cameras `cams` -> (J, C, Hf, Wf) with zeros for the cameras not read."""
    full = np.zeros((num_cameras, *features_read.shape[1:]), dtype=features_read.dtype)
    full[cams] = features_read
    return full


def _resolve_preset(opts: ExportOptions) -> tuple[Preset, int, int]:
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
    return dataclasses.replace(preset, image=image, use_image=use_image), width, height


def _make_staging_dir(out_dir: Path) -> Path:
    """A fresh temp dir beside out_dir (same filesystem, so the final rename is atomic); checks writability early."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"--out {out_dir} exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / MANIFEST_NAME).is_file():
        raise ExportError(f"--out {out_dir} is a non-empty directory that is not a streamdet export; refusing to overwrite it")
    parent = out_dir.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=parent))
    except OSError as e:
        raise ExportError(f"--out {out_dir}: cannot write into {parent}: {e.strerror or e}") from None
    tmp.chmod(0o755)  # mkdtemp makes it private; the export is an ordinary directory
    return tmp


def _commit(tmp: Path, out_dir: Path) -> None:
    """Replace out_dir (absent, empty, or an older export) by tmp."""
    out_dir = out_dir.absolute()
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
        os.replace(out_dir, old / "export")
    try:
        os.replace(tmp, out_dir)
    except OSError:
        if old is not None:
            os.replace(old / "export", out_dir)  # put the previous export back
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _save_checked(model: onnx.ModelProto, tmp: Path, name: str, precision: str) -> None:
    path = tmp / graph_file_name(name, precision)
    onnx.save_model(model, str(path))
    check_model(str(path))


def _fp32_nodes(model: onnx.ModelProto) -> set[str]:
    """Nodes of the slice graph kept in fp32: the decode and the convs that make the heatmap logits."""
    return {n.name for n in model.graph.node if ox.is_decode_node(n)} | set(ox.heatmap_producers(model))


def _count_gmacs(det: StreamDetector, inputs: _ParityInputs, lut_index: np.ndarray, lut_weight: np.ndarray) -> dict[str, tuple[float, dict]]:
    """GMAC of each graph at the export resolution, on the meta device (shapes only, no arithmetic).

    Encoder per image (J = 1); lifter and slice graph at the parity slice's Q quadrants and P pillars.
    """
    meta = torch.device("meta")
    q, p = len(inputs.quadrants), inputs.pillars.num_pillars
    j, h, w, _ = inputs.images.shape
    enc = copy.deepcopy(det.image_encoder).to(meta)
    lifter = copy.deepcopy(det.lifter).to(meta)
    net = copy.deepcopy(det.slice_net).to(meta)
    c, hf, wf = det.preset.channels, math.ceil(h / 4), math.ceil(w / 4)
    g = det.preset.grid
    on_meta = lambda a: torch.empty(a.shape, dtype=torch.from_numpy(a[:0]).dtype, device=meta)  # noqa: E731
    pl = inputs.pillars
    return {
        "image_encoder": (count_gmac(enc, torch.empty(1, h, w, 3, dtype=torch.uint8, device=meta)), {"J": 1, "H": h, "W": w}),
        "volumetric_lifter": (
            count_gmac(lifter, torch.empty(j, c, hf, wf, device=meta), on_meta(lut_index), on_meta(lut_weight)),
            {"J": j, "Q": q, "K": int(lut_index.shape[1])},
        ),
        "slice_head": (
            count_gmac(net, on_meta(pl.features), on_meta(pl.mask), on_meta(pl.index),
                       torch.empty(q, c, g.quadrant_ny, g.quadrant_nx, device=meta)),
            {"Q": q, "P": p},
        ),
    }


_DTYPE_NAMES = {
    onnx.TensorProto.UINT8: "uint8",
    onnx.TensorProto.INT32: "int32",
    onnx.TensorProto.INT64: "int64",
    onnx.TensorProto.FLOAT16: "float16",
    onnx.TensorProto.FLOAT: "float32",
}


def _tensor_specs(values) -> tuple[TensorSpec, ...]:
    specs = []
    for v in values:
        t = v.type.tensor_type
        shape = tuple(d.dim_param if d.dim_param else int(d.dim_value) for d in t.shape.dim)
        specs.append(TensorSpec(v.name, shape, _DTYPE_NAMES[t.elem_type]))
    return tuple(specs)


def _graph_entry(tmp: Path, name: str, precision: str, opset: int, gmac: tuple[float, dict]) -> GraphEntry:
    path = tmp / graph_file_name(name, precision)
    model = onnx.load(str(path), load_external_data=False)
    return GraphEntry(
        name=name,
        precision=precision,
        file=path.name,
        sha256=sha256_file(path),
        opset=opset,
        inputs=_tensor_specs(model.graph.input),
        outputs=_tensor_specs(model.graph.output),
        gmac=round(gmac[0], 4),
        gmac_at=gmac[1],
    )


def _fmt(p: ParityRecord) -> str:
    status = "ok" if p.passed else "FAILED"
    return (
        f"{p.graph} {p.precision} {p.output}: max |diff| {p.max_abs_diff:.3g} vs {p.tolerance_rel:g} x range "
        f"{p.output_range:.3g} = {p.tolerance_rel * p.output_range:.3g}: {status}"
    )


class _Steps:
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
