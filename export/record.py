"""What an export records: manifest.json's graph entries (files, hashes, input/output specs, GMAC) and the
one-line form of a parity record the progress shows."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import onnx
import onnxruntime as ort
import torch

from streamdet.core.classes import CLASS_NAMES
from streamdet.core.image_layout import IMAGE_BEV
from streamdet.core.lut_layout import LUT_SLOTS
from streamdet.export.parity import NON_FINITE, NOT_COMPARED
from streamdet.export.weights import WeightsSource
from streamdet.models.presets import Preset
from streamdet.runtime_ort.manifest import (
    GraphEntry,
    ImageSpec,
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

Gmacs = dict[str, tuple[float, dict]]  # graph name -> (GMAC, the sizes it was counted at)

_DTYPE_NAMES = {
    onnx.TensorProto.UINT8: "uint8",
    onnx.TensorProto.INT32: "int32",
    onnx.TensorProto.INT64: "int64",
    onnx.TensorProto.FLOAT16: "float16",
    onnx.TensorProto.FLOAT: "float32",
}


def write_export_manifest(tmp: Path, *args: Any, **kwargs: Any) -> Manifest:
    """``export_manifest`` of the export in ``tmp``, written there as manifest.json."""
    manifest = export_manifest(tmp, *args, **kwargs)
    write_manifest(manifest, tmp)
    return manifest


def export_manifest(
    tmp: Path, preset: Preset, num_slices: int, opset: int, precisions: tuple[str, ...], graph_names: tuple[str, ...],
    gmacs: Gmacs, parity: list[ParityRecord], pipeline: PipelineParity | None, int8_record: Int8Record | None,
    source: WeightsSource, parity_input: str, *, image: ImageSpec | None = None,
    normalisation: Normalisation | None = None, lut: LutEntry | None = None, image_layout: str = IMAGE_BEV,
    lut_layout: str = LUT_SLOTS,
) -> Manifest:  # fmt: skip
    """The manifest of an export in ``tmp``: every graph of ``graph_names`` in every precision written; image,
    normalisation and lut stay None for a LiDAR-only export. Also the staged export's draft, for the runtime the
    exporter runs on it before manifest.json is written (export/staged_detector.py)."""
    entries = [graph_entry(tmp, name, precision, opset, gmacs[name]) for precision in precisions for name in graph_names]
    manifest = Manifest(
        preset_name=preset.name,
        preset=preset.to_dict(),
        grid=preset.grid.to_dict(),
        class_names=tuple(CLASS_NAMES),
        num_slices=num_slices,
        image=image,
        normalisation=normalisation,
        # top_k: what the graph decodes (PostConfig.top_k clamped to a map's classes x cells), as top_k_per_quadrant
        post={**preset.to_dict()["post"], "top_k": preset.top_k, "top_k_per_quadrant": preset.top_k,
              "head_cell_m": preset.head_cell_m},
        graphs=tuple(entries),
        lut=lut,
        image_layout=image_layout,
        lut_layout=lut_layout,
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
    return manifest


def graph_entry(tmp: Path, name: str, precision: str, opset: int, gmac: tuple[float, dict]) -> GraphEntry:
    path = tmp / graph_file_name(name, precision)
    model = onnx.load(str(path), load_external_data=False)
    return GraphEntry(
        name=name,
        precision=precision,
        file=path.name,
        sha256=sha256_file(path),
        opset=opset,
        inputs=tensor_specs(model.graph.input),
        outputs=tensor_specs(model.graph.output),
        gmac=round(gmac[0], 4),
        gmac_at=gmac[1],
    )


def tensor_specs(values) -> tuple[TensorSpec, ...]:
    specs = []
    for v in values:
        t = v.type.tensor_type
        shape = tuple(d.dim_param if d.dim_param else int(d.dim_value) for d in t.shape.dim)
        specs.append(TensorSpec(v.name, shape, _DTYPE_NAMES[t.elem_type]))
    return tuple(specs)


def format_parity(p: ParityRecord) -> str:
    """The progress line of a parity record. A record that compared nothing (max |diff| NaN, export/parity.py) says
    so instead of a difference; a failed one whose note starts with its reason (non-finite values) gives it."""
    head = f"{p.graph} {p.precision} {p.output}"
    reason = f" ({NON_FINITE})" if p.note.startswith(NON_FINITE) else ""
    if math.isnan(p.max_abs_diff):
        return f"{head}: {NOT_COMPARED}" + ("" if p.passed else f": FAILED{reason}")
    status = "ok" if p.passed else f"FAILED{reason}"
    scale = p.output_range if p.output_scale is None else p.output_scale
    what = f"range {p.output_range:.3g}" if scale == p.output_range else f"scale {scale:.3g} (range {p.output_range:.3g})"
    return f"{head}: max |diff| {p.max_abs_diff:.3g} vs {p.tolerance_rel:g} x {what} = {p.tolerance_rel * scale:.3g}: {status}"
