"""PyTorch -> ONNX for the three graphs of docs/architecture.md ("The three graphs"), fp32; for a LiDAR-only preset
(use_image=False) the slice graph alone, without the image_bev input (``LIDAR_SLICE_HEAD_IO``).

Exporter choice: the TorchScript exporter (``torch.onnx.export(..., dynamo=False)``). It is several times faster to
run than the dynamo exporter here (the paper preset must export in minutes on a 2-core CPU), and it names every
node after the module scope it came from (``/slice_net/head/...``), which is what the fp16 conversion needs to keep
the decode in float32 by node name. Dynamic dimensions are declared with ``dynamic_axes``.

Node naming: in ``slice_head.onnx`` every node outside the ``/slice_net/`` scope belongs to the in-graph decode
(``decode_head_maps`` runs in SliceDecoder's own scope, whose nodes the exporter names ``/Sigmoid``, ``/TopK``, ...).
They are renamed to ``/decode/<op>...`` so they are recognisable in the file and in the fp16 block list.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import os
import warnings
from dataclasses import dataclass

import onnx
import torch
from torch import nn

from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import StreamDetector
from streamdet.models.export_form import LidarSliceDecoder, to_export_form  # noqa: F401 (LidarSliceDecoder: its old home)
from streamdet.calibration.compact_lut import lifter_lut_feeds
from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF, check_image_layout
from streamdet.core.image_layout import image_map_chw as layout_map_chw
from streamdet.core.lut_layout import COMPACT_INPUTS, LUT_COMPACT, LUT_SLOTS, SLOTS_INPUTS, check_lut_layout, lut_inputs
from streamdet.models.presets import Preset

DEFAULT_OPSET = 17
OPSET_RANGE = (14, 20)  # checked here end to end (14, 17, 18, 20); the TorchScript exporter stops at 20
DECODE_SCOPE = "/decode/"
TRACE_PIXELS = 64  # image crop the encoder is traced on (H, W dynamic)
TRACE_CELLS = 16  # quadrant crop the lifter is traced on (declared static afterwards)


@dataclass(frozen=True)
class GraphIO:
    """Names and dynamic axes of one graph's inputs and outputs (the contract of docs/architecture.md)."""

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    dynamic_axes: dict  # tensor name -> {axis: dimension name}


IMAGE_ENCODER_IO = GraphIO(
    name="image_encoder",
    inputs=("images",),
    outputs=("features",),
    dynamic_axes={"images": {0: "J", 1: "H", 2: "W"}, "features": {0: "J", 2: "Hf", 3: "Wf"}},
)
# K (cameras per voxel) is dynamic: another rig may see a voxel from three cameras, and a new calibration
# must never need a re-export. Hf and Wf are dynamic so the graph follows the encoder at any image size.
VOLUMETRIC_LIFTER_IO = GraphIO(
    name="volumetric_lifter",
    inputs=("features", "lut_index", "lut_weight"),
    outputs=("image_bev",),
    dynamic_axes={
        "features": {0: "J", 2: "Hf", 3: "Wf"},
        "lut_index": {0: "Q", 1: "K"},
        "lut_weight": {0: "Q", 1: "K"},
        "image_bev": {0: "Q"},
    },
)
SLICE_HEAD_IO = GraphIO(
    name="slice_head",
    inputs=("pillar_features", "pillar_mask", "pillar_index", "image_bev"),
    outputs=("det_boxes", "det_scores", "det_labels"),
    dynamic_axes={
        "pillar_features": {0: "P"},
        "pillar_mask": {0: "P"},
        "pillar_index": {0: "P"},
        "image_bev": {0: "Q"},
        "det_boxes": {0: "Q"},
        "det_scores": {0: "Q"},
        "det_labels": {0: "Q"},
    },
)
GRAPH_IO: dict[str, GraphIO] = {g.name: g for g in (IMAGE_ENCODER_IO, VOLUMETRIC_LIFTER_IO, SLICE_HEAD_IO)}
# The image_half layout (models/image_half.py): the lifter graph also runs the BEV encoder's image half and outputs
# it, (Q, C0, Yh, Xh); the slice graph takes it in place of the image BEV.
IMAGE_HALF_LIFTER_IO = GraphIO(
    name="volumetric_lifter",
    inputs=VOLUMETRIC_LIFTER_IO.inputs,
    outputs=(IMAGE_HALF,),
    dynamic_axes={**{k: v for k, v in VOLUMETRIC_LIFTER_IO.dynamic_axes.items() if k != "image_bev"}, IMAGE_HALF: {0: "Q"}},
)
IMAGE_HALF_SLICE_HEAD_IO = GraphIO(
    name="slice_head",
    inputs=(*SLICE_HEAD_IO.inputs[:3], IMAGE_HALF),
    outputs=SLICE_HEAD_IO.outputs,
    dynamic_axes={**{k: v for k, v in SLICE_HEAD_IO.dynamic_axes.items() if k != "image_bev"}, IMAGE_HALF: {0: "Q"}},
)
IMAGE_HALF_GRAPH_IO: dict[str, GraphIO] = {g.name: g for g in (IMAGE_ENCODER_IO, IMAGE_HALF_LIFTER_IO, IMAGE_HALF_SLICE_HEAD_IO)}
# The compact LUT layout (core/lut_layout.py): the lifter reads the valid (voxel, camera) pairs; M (voxels seen by two
# or more cameras) is dynamic like K, the per-voxel arrays (Q, Z, Yq, Xq) have the preset's quadrant.
COMPACT_LUT_AXES = {"multi_index": {0: "K", 1: "M"}, "multi_weight": {0: "K", 1: "M"}, "final_index": {0: "Q"}, "final_weight": {0: "Q"}}


def compact_lifter_io(io_spec: GraphIO) -> GraphIO:
    """``io_spec`` (a lifter graph's) reading the compacted LUT instead of the K-slot arrays."""
    axes = {k: v for k, v in io_spec.dynamic_axes.items() if k not in SLOTS_INPUTS}
    return dataclasses.replace(io_spec, inputs=("features", *COMPACT_INPUTS), dynamic_axes={**axes, **COMPACT_LUT_AXES})
# The LiDAR-only baseline (preset use_image=False) exports this slice graph alone. It has no image BEV: the graph
# takes the slice's quadrant ids (Q,) int64 and reads their count (models/export_form.py: LidarSliceDecoder).
LIDAR_SLICE_HEAD_IO = GraphIO(
    name="slice_head",
    inputs=("pillar_features", "pillar_mask", "pillar_index", "quadrants"),
    outputs=SLICE_HEAD_IO.outputs,
    dynamic_axes={**{k: v for k, v in SLICE_HEAD_IO.dynamic_axes.items() if k != "image_bev"}, "quadrants": {0: "Q"}},
)

# The LiDAR-only baseline without the quadrant crop (preset slice_crop=False): every slice is one map of the whole
# grid, Q = 1, so the graph takes the pillar tensors alone (models/export_form.py: FullMapSliceDecoder).
LIDAR_FULL_MAP_SLICE_HEAD_IO = GraphIO(
    name="slice_head",
    inputs=("pillar_features", "pillar_mask", "pillar_index"),
    outputs=SLICE_HEAD_IO.outputs,
    dynamic_axes={k: v for k, v in SLICE_HEAD_IO.dynamic_axes.items() if k.startswith("pillar_")},
)


def graph_ios(use_image: bool, slice_crop: bool = True, image_layout: str = IMAGE_BEV, lut_layout: str = LUT_SLOTS) -> dict[str, GraphIO]:
    """The graphs an export of a preset with this ``use_image`` (and ``slice_crop``, ``image_layout``,
    ``lut_layout``) consists of, by name, in pipeline order."""
    if use_image:
        ios = IMAGE_HALF_GRAPH_IO if check_image_layout(image_layout) == IMAGE_HALF else GRAPH_IO
        if check_lut_layout(lut_layout) == LUT_SLOTS:
            return ios
        return {**ios, "volumetric_lifter": compact_lifter_io(ios["volumetric_lifter"])}
    return {"slice_head": LIDAR_SLICE_HEAD_IO if slice_crop else LIDAR_FULL_MAP_SLICE_HEAD_IO}


def export_module(module: nn.Module, args: tuple[torch.Tensor, ...], io_spec: GraphIO, opset: int = DEFAULT_OPSET) -> onnx.ModelProto:
    """Trace ``module(*args)`` into an ONNX model with the names and dynamic axes of ``io_spec``."""
    lo, hi = OPSET_RANGE
    if not isinstance(opset, int) or not lo <= opset <= hi:
        raise ValueError(f"opset must be an int in [{lo}, {hi}], got {opset!r}")
    module = module.eval()
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of dynamo (see the module doc for why we use it) and
        # warns about traced shape arithmetic that is in fact dynamic (checked by the dynamic-size tests).
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            args,
            buf,
            dynamo=False,
            opset_version=opset,
            input_names=list(io_spec.inputs),
            output_names=list(io_spec.outputs),
            dynamic_axes=io_spec.dynamic_axes,
            do_constant_folding=True,
        )
    model = onnx.load_from_string(buf.getvalue())
    _name_unnamed_nodes(model)
    return with_inferred_shapes(model)


def with_inferred_shapes(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with every intermediate shape ONNX can infer stored in the file, symbolic dimensions included.

    The exporter writes none. With data propagation, ONNX follows shape arithmetic (Shape -> Gather -> Concat ->
    Reshape) and finds, e.g., that the scattered point BEV has the image BEV's (Q, C, Yq, Xq). onnxruntime's
    blocked-layout (NCHWc) optimizer fuses an Add into the convolution that feeds it only where it can prove
    both inputs equal in shape: with the shapes stored it fuses the split convolutions' sums
    (models/slice_split.py); without them it adds through reshapes and runs the ReLU on its own.
    """
    return onnx.shape_inference.infer_shapes(model, data_prop=True)


def export_image_encoder(det: StreamDetector, images: torch.Tensor, opset: int = DEFAULT_OPSET) -> onnx.ModelProto:
    """``images`` (J, H, W, 3) uint8 -> features (J, C, Hf, Wf); normalisation inside.

    Traced on one TRACE_PIXELS x TRACE_PIXELS crop of the first image: J, H and W are dynamic, and a trace at
    1600 x 900 would run ResNet-50 (126 GMAC) once more for nothing. The export's parity check runs the graph at
    the export resolution.
    """
    if det.image_encoder is None:
        raise ValueError(f"preset {det.preset.name!r} has use_image=False: there is no image encoder to export")
    crop = images[:1, :TRACE_PIXELS, :TRACE_PIXELS].contiguous()  # (1, <=64, <=64, 3)
    # a copy: tracing puts the module in eval mode, and the caller's detector keeps its own modes (as to_export_form)
    return export_module(copy.deepcopy(det.image_encoder).eval(), (crop,), IMAGE_ENCODER_IO, opset)


def export_volumetric_lifter(
    det: StreamDetector, features: torch.Tensor, lut_index: torch.Tensor, lut_weight: torch.Tensor, opset: int = DEFAULT_OPSET,
    image_layout: str = IMAGE_BEV, lut_layout: str = LUT_SLOTS,
) -> onnx.ModelProto:
    """features (J, C, Hf, Wf), lut_index / lut_weight (Q, K, Z, Yq, Xq) -> image_bev (Q, C, Yq, Xq), or in the
    image_half layout image_half (Q, C0, Yh, Xh) (models/image_half.py).

    Traced on a TRACE_CELLS x TRACE_CELLS crop of the LUT with Yq and Xq dynamic, which are then declared static
    again (the preset's quadrant): a full-size trace would run the paper's 179-GMAC 3D convolutions once more for
    nothing. Full shape inference on the result checks the declared sizes; the parity check runs at full size.
    """
    if det.lifter is None:
        raise ValueError(f"preset {det.preset.name!r} has use_image=False: there is no lifter to export")
    g = det.preset.grid
    io_spec = graph_ios(True, True, image_layout, lut_layout)["volumetric_lifter"]
    (out,) = io_spec.outputs
    crop = (slice(None), slice(None), slice(None), slice(None, TRACE_CELLS), slice(None, TRACE_CELLS))
    traced_axes = {
        **io_spec.dynamic_axes,
        "lut_index": {0: "Q", 1: "K", 3: "Yq", 4: "Xq"},
        "lut_weight": {0: "Q", 1: "K", 3: "Yq", 4: "Xq"},
        "final_index": {0: "Q", 2: "Yq", 3: "Xq"},
        "final_weight": {0: "Q", 2: "Yq", 3: "Xq"},
        out: {0: "Q", 2: "Yo", 3: "Xo"},
    }
    spec = dataclasses.replace(io_spec, dynamic_axes={k: v for k, v in traced_axes.items() if k in (*spec_names(io_spec),)})
    index, weight = lut_index[crop].contiguous(), lut_weight[crop].contiguous()
    j, _, hf, wf = features.shape
    lut = lifter_lut_feeds(index.numpy(), weight.numpy(), j * hf * wf, lut_layout == LUT_COMPACT)
    args = (features, *(torch.from_numpy(lut[n]) for n in lut_inputs(lut_layout)))
    model = export_module(to_export_form(det, image_layout, lut_layout).volumetric_lifter, args, spec, opset)
    voxels = (g.nz, g.quadrant_ny, g.quadrant_nx)
    static = {"lut_index": (None, None, *voxels), "lut_weight": (None, None, *voxels), "final_index": (None, *voxels),
              "final_weight": (None, *voxels), out: (None, *image_map_chw(det.preset, image_layout))}
    _declare_static_dims(model, static)
    return model


def spec_names(io_spec: GraphIO) -> tuple[str, ...]:
    return (*io_spec.inputs, *io_spec.outputs)


def image_map_chw(preset: Preset, image_layout: str = IMAGE_BEV) -> tuple[int, int, int]:
    """(C, H, W) of one quadrant's map between the lifter and the slice graph in this layout."""
    g = preset.grid
    return layout_map_chw(preset.to_dict(), (g.quadrant_ny, g.quadrant_nx), image_layout)


def slice_decoder(det: StreamDetector, image_layout: str = IMAGE_BEV) -> SliceDecoder:
    """The module traced into slice_head.onnx (``to_export_form``)."""
    return to_export_form(det, image_layout).slice_head


def export_slice_head(det: StreamDetector, pillar_args: tuple[torch.Tensor, ...], opset: int = DEFAULT_OPSET,
                      image_layout: str = IMAGE_BEV) -> onnx.ModelProto:  # fmt: skip
    """(pillar_features, pillar_mask, pillar_index, image_bev) -> det_boxes, det_scores, det_labels (image_half in
    place of image_bev in that layout); for a LiDAR-only ``det`` (use_image=False) the inputs are (pillar_features,
    pillar_mask, pillar_index, quadrants), without the crop (slice_crop=False) the pillar tensors alone."""
    io_spec = graph_ios(det.preset.use_image, det.preset.slice_crop, image_layout)["slice_head"]
    return _finish_slice_head(export_module(slice_decoder(det, image_layout), pillar_args, io_spec, opset), det)


def _finish_slice_head(model: onnx.ModelProto, det: StreamDetector) -> onnx.ModelProto:
    """Rename the decode's nodes into DECODE_SCOPE and restore the static top-K dimensions."""
    decode = _decode_node_names(model)
    for node in model.graph.node:
        if node.name in decode:
            node.name = DECODE_SCOPE + node.name.lstrip("/")
    # The tracer loses the static K and 9 of det_boxes through the decode's concat/transpose; K is fixed by the preset.
    k = det.preset.top_k
    _declare_static_dims(model, {"det_boxes": (None, k, 9), "det_scores": (None, k), "det_labels": (None, k)})
    return model


def _declare_static_dims(model: onnx.ModelProto, sizes: dict[str, tuple[int | None, ...]]) -> None:
    """Set the named graph inputs' / outputs' dimensions to fixed sizes (None keeps a dimension as it is)."""
    for value in (*model.graph.input, *model.graph.output):
        for dim, size in zip(value.type.tensor_type.shape.dim, sizes.get(value.name, ())):
            if size is not None:
                dim.Clear()
                dim.dim_value = size


def _decode_node_names(model: onnx.ModelProto) -> set[str]:
    """The decode: nodes outside ``/slice_net/`` that consume (transitively) a slice_net output, plus the nodes
    (constants) that feed only those.

    The scope test alone is not enough: the exporter also puts the Identity nodes that share one initializer
    between two layers in the root scope, and those belong to the layers, not to the decode. The constants must
    come along, or the fp16 converter rounds the decode's cell size and offsets to float16.
    """
    nodes = list(model.graph.node)
    from_net = {o for n in nodes if n.name.startswith("/slice_net/") for o in n.output}
    names: set[str] = set()
    for node in nodes:  # exporter output is topologically sorted
        if not node.name.startswith("/slice_net/") and any(i in from_net for i in node.input):
            names.add(node.name)
            from_net.update(node.output)
    consumers: dict[str, list[str]] = {}
    for node in nodes:
        for i in node.input:
            consumers.setdefault(i, []).append(node.name)
    outputs = {o.name for o in model.graph.output}
    changed = True
    while changed:
        changed = False
        for node in nodes:
            if node.name in names or node.name.startswith("/slice_net/"):
                continue
            users = [u for o in node.output for u in consumers.get(o, [])]
            if users and all(u in names for u in users) and not any(o in outputs for o in node.output):
                names.add(node.name)
                changed = True
    return names


def is_decode_node(node: onnx.NodeProto) -> bool:
    return node.name.startswith(DECODE_SCOPE)


def heatmap_producers(model: onnx.ModelProto) -> list[str]:
    """Names of the nodes between the head's heatmap convs and the decode's Sigmoid, the convs included.

    With those in float32 the heatmap logits are computed from float32 weights, so the decode's peak test does
    not meet the flat ties a float16 logit map has (see fp16.py). Walks upstream from the Sigmoid's input through
    non-Conv nodes (the multi-head merge's Concat/Gather) and stops at each Conv.
    """
    sigmoids = [n for n in model.graph.node if is_decode_node(n) and n.op_type == "Sigmoid"]
    if len(sigmoids) != 1:
        raise ValueError(f"expected one decode Sigmoid in the slice graph, found {len(sigmoids)}")
    found = upstream_to_convs(model, [sigmoids[0].input[0]])
    if not any(producer_op == "Conv" for producer_op in (n.op_type for n in model.graph.node if n.name in found)):
        raise ValueError("found no Conv producing the heatmap logits in the slice graph")
    return found


def upstream_to_convs(model: onnx.ModelProto, tensors: list[str], stop_ops: tuple[str, ...] = ()) -> list[str]:
    """Names of the non-decode nodes from ``tensors`` upstream to (and including) the first Conv on each path; a
    path ends before a node of ``stop_ops``, without it."""
    producer = {out: n for n in model.graph.node for out in n.output}
    found: list[str] = []
    stack = list(tensors)
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in found or is_decode_node(node) or node.op_type in stop_ops:
            continue
        found.append(node.name)
        if node.op_type != "Conv":
            stack.extend(i for i in node.input if i in producer)
    return found


def save_model(model: onnx.ModelProto, path: str | os.PathLike) -> None:
    onnx.save_model(model, os.fspath(path))


def _name_unnamed_nodes(model: onnx.ModelProto) -> None:
    """The exporter leaves some nodes (constants it creates) unnamed or named like ``Constant_16``; fp16 casts are
    named after their node, so every node needs a unique name."""
    seen: set[str] = set()
    for i, node in enumerate(model.graph.node):
        if not node.name or node.name in seen:
            node.name = f"{node.name or node.op_type}_n{i}"
        seen.add(node.name)
