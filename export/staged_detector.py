"""The runtime on the export being staged: a ``StreamingDetector`` over the staging directory's graphs with the
manifest they will get (not written yet), so the exporter's int8 calibration and its whole-pipeline parity checks
run the detector every user runs (``runtime_ort.pipeline``) and take the graph feeds it records
(``StreamingDetector.recording``): slicing, pillarisation, image loading, LUT, quadrant selection and crops are
the runtime's, defined there once.

The detector runs with the exporter's session settings (``sessions.EXPORT_SESSION``: the CPU, every core, since
nothing runs beside an export), as the per-graph parity sessions do.
"""

from __future__ import annotations

import dataclasses

from streamdet.core.image_layout import IMAGE_BEV
from streamdet.core.lut_layout import LUT_SLOTS
from streamdet.export.export_run import ExportRun
from streamdet.export.options import ExportError
from streamdet.export.record import export_manifest
from streamdet.models.image_encoder import IMAGENET_MEAN, IMAGENET_STD
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.manifest import LUT_NAME, ImageSpec, LutEntry, Manifest, Normalisation, sha256_file
from streamdet.runtime_ort.manifest_records import Int8Record
from streamdet.runtime_ort.sessions import EXPORT_SESSION

EXPORT_DETECTOR = DetectorConfig(providers=EXPORT_SESSION.providers, image_lane_threads=0, slice_lane_threads=0,
                                 camera_terms=False)  # the export runs full updates; its int8 lifter is still being made


def run_manifest(run: ExportRun, precisions: tuple[str, ...], int8_record: Int8Record | None = None) -> Manifest:
    """The manifest of the graphs of ``precisions`` staged so far, with the parity records gathered so far."""
    image = normalisation = lut = None
    if run.preset.use_image:
        w, h = run.size
        image = ImageSpec(w, h, run.preset.image.feature_stride, run.lut.feature_width, run.lut.feature_height, tuple(run.rig.names))
        normalisation = Normalisation(mean_rgb=tuple(IMAGENET_MEAN), std_rgb=tuple(IMAGENET_STD))
        lut = LutEntry(LUT_NAME, sha256_file(run.tmp / LUT_NAME), run.lut.calibration_sha256, run.calibration_source)
    opts = run.opts
    return export_manifest(
        run.tmp, run.preset, opts.num_slices, opts.opset, precisions, run.graphs, run.gmacs, run.parity, run.pipeline,
        int8_record, run.source, run.inputs.describe(), image=image, normalisation=normalisation, lut=lut,
        image_layout=opts.image_layout if run.preset.use_image else IMAGE_BEV,
        lut_layout=opts.lut_layout if run.preset.use_image else LUT_SLOTS,
    )  # fmt: skip


def staged_detector(run: ExportRun, precision: str, int8_record: Int8Record | None = None) -> StreamingDetector:
    """The detector of the staged graphs of ``precision`` (both lanes); ``int8_record`` (int8 only): the record of
    the int8 graphs so far (a manifest lists int8 graphs with their record)."""
    failed = [f"{p.graph} {p.output}" for p in run.parity if p.precision == "fp32" and not p.passed]
    if failed:  # the runtime refuses such graphs; say why here, in the exporter's words
        raise ExportError(f"the fp32 graphs failed their parity check against PyTorch ({', '.join(failed)}): int8 "
                          "calibration runs the pipeline through them, so no int8 graph can be made")  # fmt: skip
    precisions = ("fp32",) if precision == "fp32" else ("fp32", precision)
    manifest = run_manifest(run, precisions, int8_record)
    return StreamingDetector(run.tmp, dataclasses.replace(EXPORT_DETECTOR, precision=precision), manifest=manifest)
