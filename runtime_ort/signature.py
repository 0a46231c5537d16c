"""The manifest checked against the graphs themselves, before any slice runs.

A manifest can be well-formed (``manifest.schema.json``) and still describe other graphs than the files beside
it, or graphs the runtime cannot feed: a lifter graph copied over ``slice_head.onnx`` with its sha256 updated,
``max_points_per_pillar`` edited after export, class names reordered. Each of these used to load and fail at the
first slice (or silently mislabel boxes). Here every graph's real signature, read from its onnxruntime session
(names, dtypes, ranks and fixed dimensions; no ``onnx`` import), must equal both the manifest's record of it and
what the runtime feeds and reads, which follows from the preset and grid. Any difference is a ManifestError that
names the graph file, the tensor and both values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from streamdet.calibration.grid import GridSpec
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.image_layout import image_map_chw
from streamdet.core.lut_layout import LUT_COMPACT
from streamdet.runtime_ort.manifest import GraphEntry, Manifest, ManifestError, TensorSpec
from streamdet.runtime_ort.pillarize import PILLAR_FEATURE_DIM


@dataclass(frozen=True)
class TensorSignature:
    """One input or output as a graph declares it: None for a dynamic dimension."""

    name: str
    dtype: str  # numpy dtype name ("float32"), or the onnxruntime type string when it has none
    shape: tuple[int | None, ...]


def check_runtime_fields(manifest: Manifest) -> None:
    """The manifest fields the runtime relies on beyond the schema: its label table and the per-class NMS list."""
    if tuple(manifest.class_names) != CLASS_NAMES:
        raise ManifestError(
            f"manifest class_names {list(manifest.class_names)} differ from the runtime's label table {list(CLASS_NAMES)} "
            "(the slice graph's labels index it; reordered or truncated names would mislabel every box)"
        )
    img = manifest.image
    if img is not None:
        want = (math.ceil(img.width / img.feature_stride), math.ceil(img.height / img.feature_stride))
        if (img.feature_width, img.feature_height) != want:
            raise ManifestError(
                f"manifest image.feature_width/height {img.feature_width}x{img.feature_height} do not follow from "
                f"{img.width}x{img.height} at stride {img.feature_stride} (expected {want[0]}x{want[1]})"
            )
    preset_grid = manifest.preset.get("grid")
    if preset_grid is not None and _grid_or_none(preset_grid) != _grid_or_none(manifest.grid):
        raise ManifestError(
            f"manifest grid {manifest.grid} differs from the grid its preset was trained on, preset.grid {preset_grid} "
            "(the same cell counts over other ranges would pass every graph check and put every box in the wrong place)"
        )
    ious = manifest.post.get("nms_iou_threshold")
    if ious is not None and len(ious) != len(manifest.class_names):
        raise ManifestError(
            f"manifest post.nms_iou_threshold holds {len(ious)} values, expected one per class ({len(manifest.class_names)})"
        )


def check_parity(manifest: Manifest, lanes: dict[str, str]) -> None:
    """Refuse graphs in use (``lanes``: graph name -> precision) whose export-time parity check failed: the exporter
    still writes such an export (and exits 2), but its graph does not compute what the model does."""
    failed = [f"{p.graph} {p.precision} {p.output}" for p in manifest.parity if not p.passed and lanes.get(p.graph) == p.precision]
    pipeline = manifest.pipeline_parity
    if pipeline is not None and not pipeline.passed and "fp16" in lanes.values():
        failed.append("the fp16 pipeline")
    if failed:
        raise ManifestError(f"the export's parity check FAILED for {', '.join(failed)} (recorded in its manifest): "
                            "those graphs do not compute what the model does; re-export (or run another precision)")  # fmt: skip


def _grid_or_none(d: object) -> GridSpec | None:
    try:
        return GridSpec.from_dict(d)
    except (ValueError, TypeError, KeyError):
        return None


def expected_io(manifest: Manifest, grid: GridSpec, name: str) -> tuple[tuple[TensorSignature, ...], tuple[TensorSignature, ...]]:
    """(inputs, outputs) the runtime feeds to and reads from graph ``name``, with the dimensions it fixes."""
    c = int(manifest.preset["channels"])
    m = int(manifest.preset["pillars"]["max_points_per_pillar"])
    yq, xq, z = grid.quadrant_ny, grid.quadrant_nx, grid.nz
    # what the lifter hands the slice graph: the image BEV or the precomputed image half (core/image_layout.py)
    image_map = TensorSignature(manifest.image_layout, "float32", (None, *image_map_chw(manifest.preset, (yq, xq), manifest.image_layout)))
    if name == "image_encoder":
        return (
            (TensorSignature("images", "uint8", (None, None, None, 3)),),
            (TensorSignature("features", "float32", (None, c, None, None)),),
        )
    if name == "volumetric_lifter":
        if manifest.lut_layout == LUT_COMPACT:  # the valid (voxel, camera) pairs (core/lut_layout.py)
            lut = (
                TensorSignature("multi_index", "int32", (None, None)),
                TensorSignature("multi_weight", "float32", (None, None)),
                TensorSignature("final_index", "int32", (None, z, yq, xq)),
                TensorSignature("final_weight", "float32", (None, z, yq, xq)),
            )
        else:
            lut = (
                TensorSignature("lut_index", "int32", (None, None, z, yq, xq)),
                TensorSignature("lut_weight", "float32", (None, None, z, yq, xq)),
            )
        return (TensorSignature("features", "float32", (None, c, None, None)), *lut), (image_map,)
    pillars = (
        TensorSignature("pillar_features", "float32", (None, m, PILLAR_FEATURE_DIM)),
        TensorSignature("pillar_mask", "float32", (None, m)),
        TensorSignature("pillar_index", "int64", (None,)),
    )
    # K, the boxes decoded per map: the export records it (post.top_k_per_quadrant; older manifests do not)
    k = manifest.post.get("top_k_per_quadrant")
    if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise ManifestError(f"manifest post.top_k_per_quadrant must be a positive integer (the boxes each map decodes), got {k!r}")
    outputs = (
        TensorSignature("det_boxes", "float32", (None, k, BOX_DIM)),
        TensorSignature("det_scores", "float32", (None, k)),
        TensorSignature("det_labels", "int64", (None, k)),
    )
    if not manifest.slice_crop:  # LiDAR-only on one whole-grid map per slice: the pillar tensors alone
        return pillars, outputs
    context = image_map if manifest.use_image else TensorSignature("quadrants", "int64", (None,))
    return (*pillars, context), outputs


def check_graph(
    entry: GraphEntry,
    inputs: tuple[TensorSignature, ...],
    outputs: tuple[TensorSignature, ...],
    manifest: Manifest,
    grid: GridSpec,
) -> None:
    """Raise ManifestError unless the graph's real ``inputs``/``outputs`` match its manifest entry and the runtime."""
    want_in, want_out = expected_io(manifest, grid, entry.name)
    for kind, real, recorded, wanted in (
        ("input", inputs, entry.inputs, want_in),
        ("output", outputs, entry.outputs, want_out),
    ):
        where = f"{entry.file} ({entry.name}, {entry.precision})"
        real_names = [t.name for t in real]
        if real_names != [t.name for t in recorded]:
            raise ManifestError(
                f"{where}: the graph's {kind}s are {real_names}, the manifest records {[t.name for t in recorded]}"
            )
        if real_names != [t.name for t in wanted]:
            raise ManifestError(
                f"{where}: the graph's {kind}s are {real_names}; a {entry.name} graph has {[t.name for t in wanted]}"
            )
        for got, rec, want in zip(real, recorded, wanted):
            _compare(where, got, _from_spec(rec), "the manifest records")
            _compare(where, got, want, "the runtime feeds/reads")
            if kind == "input":  # the runtime feeds varying sizes where it leaves a dimension open
                _check_open(where, got, want)


def _check_open(where: str, got: TensorSignature, want: TensorSignature) -> None:
    for axis, (g, w) in enumerate(zip(got.shape, want.shape)):
        if w is None and g is not None:
            raise ManifestError(
                f"{where}: input {got.name!r} fixes dimension {axis} at {g}, which the runtime varies (cameras, pillars, "
                "quadrants, image size): every run of another size would fail (a graph exported without its dynamic axes?)"
            )


def _from_spec(spec: TensorSpec) -> TensorSignature:
    return TensorSignature(spec.name, spec.dtype, tuple(d if isinstance(d, int) else None for d in spec.shape))


def _compare(where: str, got: TensorSignature, want: TensorSignature, whose: str) -> None:
    if got.dtype != want.dtype:
        raise ManifestError(f"{where}: tensor {got.name!r} is {got.dtype} in the graph, {whose} {want.dtype}")
    if len(got.shape) != len(want.shape):
        raise ManifestError(f"{where}: tensor {got.name!r} has rank {len(got.shape)} in the graph, {whose} rank {len(want.shape)}")
    for axis, (g, w) in enumerate(zip(got.shape, want.shape)):
        if w is not None and g != w:
            shown = "dynamic" if g is None else g
            raise ManifestError(
                f"{where}: tensor {got.name!r} has dimension {axis} = {shown} in the graph, {whose} {w} "
                "(a manifest field edited after export, or another model's graph)"
            )
