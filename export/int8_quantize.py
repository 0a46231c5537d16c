"""int8 quantization of one exported graph: static QDQ, calibrated on real inputs (numpy + onnxruntime).

Format. ``onnxruntime.quantization.quantize_static`` in QDQ form: weights int8, symmetric, one scale per output
channel; activations **uint8**, asymmetric, one scale per tensor. onnxruntime's x86 CPU provider fuses
``DequantizeLinear -> Conv -> QuantizeLinear`` into its int8 convolution (QLinearConv, u8s8 GEMM) only with uint8
activations. The fusion needs the session at ORT_ENABLE_ALL (what the runtime uses): the int8 NHWC kernels come
with it (ENABLE_EXTENDED measured slower). ``quantize_dynamic`` is not a path: it makes ConvInteger, slower than
fp32. The measurements behind this docstring's choices: benchmarks/RESULTS.md, "Measurements behind design choices".

Weights are 7-bit (``reduce_range``) by default. x86 CPUs without VNNI (AVX2 only, like the AMD EPYC this was
measured on) multiply u8 x s8 with ``vpmaddubsw``, which adds two products into a saturating int16: 255 * 127 * 2
overflows it, 255 * 63 * 2 does not: measured on the small image encoder, 8-bit weights gave several times the
error of 7-bit ones. With 7-bit weights the graph computes the same thing on every x86 CPU, VNNI or not.

Pre-processing. The TorchScript exporter shares equal initializers (e.g. zero biases) through ``Identity`` nodes,
and the quantizer does not make a QDQ unit of a Conv whose bias is not an initializer (most convolutions of the
small image encoder would stay float). ``quant_pre_process`` (shape inference and onnxruntime's basic
optimisations, which fold those Identities) runs first.

What stays float, and why (``float_nodes``):

- slice graph, the decode and the heatmap convolution: peak picking keeps a cell that equals the max of its 3x3
  neighbourhood. A uint8 heatmap has 256 levels over the logit range, so neighbouring cells of one object round
  to the same level, each of them is a "peak", and one object yields several boxes. The heatmap logits are
  computed in float (their last conv excluded) and the sigmoid / max-pool / equality / top-k / box arithmetic run
  in float on them. The other head outputs (centre offset, z, log size, yaw, velocity) are float too: the decode
  turns them into box values directly. The single head's are computed inside the decode at its peaks, from the
  (quantized) hidden features of their branches (models/peak_head.py); a multi-head's come from float convs.
- slice graph, the pillar net and scatter: ``pillar_features`` holds x and y (up to +-51 m) beside offsets of a
  few centimetres and reflectance in 0..1; one uint8 scale per tensor (0.4 m steps) would erase all but x and y.
  The PointNet is a single 11-input linear layer, which int8 would not speed up.
- image encoder, the input normalisation (cast, scale, shift of the full image), rewritten as one float
  BatchNormalization (``normalisation_as_batchnorm``, export/int8_rewrites.py, bit-identical in fp32). onnxruntime runs the int8 convolutions
  in NHWC and moves the graph's NHWC -> NCHW transpose of the image past the Mul and Add, which then broadcast
  their per-channel constants over the innermost axis of size 3: slow in float, slower quantized, while the
  BatchNormalization (which the transpose is not moved past) costs next to nothing.
- lifter, z pooling and the max over z: QLinearAveragePool measured slower than the float AveragePool with the
  DequantizeLinear before it.
- lifter, the BEV encoder's image half in the image_half layout (models/image_half.py): the fp32 slice graph of the
  other layout runs it in float; quantized (input and output in uint8) it raised the error the int8 image lane
  brings to the fp32 slices' scores several-fold (measured in docs/replay.md). A small conv next to the 3D convolutions.
- lifter, the LUT gather and weighted sum (``Int8Config.quantize_lifter_gather``, off): quantized, the feature
  table is quantized once, gathered and weighted as uint8 (QLinearMul), and the gathered (Q, K, Z, Yq, Xq, C)
  rows, K = 2 times the volume, are dequantized before the sum. Measured, that costs what the float gather,
  weighting and sum with one QuantizeLinear of the volume cost, and quantizing the features before the camera
  average adds error, so the gather stays float and the volume is quantized once, before the first 3D convolution.
- ConvTranspose (the BEV encoder's upsampling) does not stay: onnxruntime runs it in float NCHW between a
  DequantizeLinear and a QuantizeLinear, so before quantizing, every ConvTranspose whose kernel equals its stride
  becomes the 1x1 Conv + DepthToSpace it equals (``transposed_convs_as_depth_to_space``, export/int8_rewrites.py),
  which run in int8 (QLinearConv, uint8 DepthToSpace). Only the int8 graph: the fp32 slice graph measured faster
  with the ConvTranspose (benchmarks/RESULTS.md, "Upsampling as DepthToSpace in the int8 slice graph").
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import onnx
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from streamdet.export.int8_rewrites import first_node as _first
from streamdet.export.int8_rewrites import normalisation_as_batchnorm, transposed_convs_as_depth_to_space
from streamdet.export.onnx_export import heatmap_producers, is_decode_node, upstream_to_convs
from streamdet.runtime_ort.recording import Feeds

log = logging.getLogger(__name__)

ACTIVATION_TYPE = QuantType.QUInt8  # the only activation type x86 onnxruntime runs as fused int8 convolutions
WEIGHT_TYPE = QuantType.QInt8
INPUT_NORM_NOTE = "input normalisation: quantized it costs 50x a float BatchNormalization on the NCHW image"
LIFTER_POOL_NOTE = "z pooling: QLinearAveragePool costs 2x the float AveragePool with its DequantizeLinear"
IMAGE_HALF_NOTE = ("image half (image_half layout): the slice graph's first conv, float as in the fp32 slice graph; "
                   "quantized, its output's uint8 steps reach the fp32 slices (docs/replay.md)")
IMAGE_HALF_SCOPE = "/image_conv/"  # ImageHalfLifter.image_conv's nodes (models/image_half.py)
LIFTER_GATHER_NOTE = "LUT gather and weighted sum: dequantizing K x the volume costs what the uint8 gather saves"
HEAD_OUTPUT_NOTE = "head outputs: the decode reads them as box values; uint8 steps would show in the boxes"
PILLAR_NOTE = "pillar net and scatter: metres and centimetre offsets in one tensor do not share a uint8 scale"


@dataclass(frozen=True)
class Int8Config:
    calibrate_method: CalibrationMethod = CalibrationMethod.MinMax  # Percentile / Entropy hold histograms in memory
    reduce_range: bool = True  # 7-bit weights: no int16 saturation on x86 without VNNI (module doc)
    per_channel: bool = True  # one weight scale per output channel
    quantize_lifter_gather: bool = False  # measured no faster than the float gather, and less accurate (module doc)


# ---- what stays float ---------------------------------------------------------------------------------------


def _ancestors(model: onnx.ModelProto, tensor: str) -> set[str]:
    """Names of the nodes the tensor depends on (transitively)."""
    producer = {o: n for n in model.graph.node for o in n.output}
    found: set[str] = set()
    stack = [tensor]
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in found:
            continue
        found.add(node.name)
        stack.extend(node.input)
    return found


def _head_outputs(model: onnx.ModelProto) -> set[str]:
    """The last layers of the head: nodes from the decode's inputs upstream to (and including) the first Conv. A
    path ends at a ReLU: past it are hidden features, which the peak head (models/peak_head.py) hands to the decode
    to compute the regression outputs at the peaks in float, quantized like the rest of the head."""
    decode_inputs = [i for n in model.graph.node if is_decode_node(n) for i in n.input]
    return set(upstream_to_convs(model, decode_inputs, stop_ops=("Relu",)))


def float_nodes(graph: str, model: onnx.ModelProto, cfg: Int8Config = Int8Config()) -> dict[str, str]:
    """Node name -> why it stays float, for one of the three graphs (pre-processed, see the module doc)."""
    keep: dict[str, str] = {}
    if graph == "image_encoder":
        for name in _ancestors(model, _first(model, "Conv").input[0]):
            keep[name] = INPUT_NORM_NOTE
    elif graph == "volumetric_lifter":
        if not cfg.quantize_lifter_gather:
            for name in _ancestors(model, _first(model, "Conv").input[0]):
                keep[name] = LIFTER_GATHER_NOTE
        for n in model.graph.node:
            if n.op_type in ("AveragePool", "ReduceMax"):
                keep[n.name] = LIFTER_POOL_NOTE
            elif n.name.startswith(IMAGE_HALF_SCOPE):
                keep[n.name] = IMAGE_HALF_NOTE
    elif graph == "slice_head":
        for n in model.graph.node:
            if is_decode_node(n):
                keep[n.name] = "decode: peak picking on a uint8 heatmap multiplies the peaks"
        for name in heatmap_producers(model):
            keep.setdefault(name, "heatmap logits: computed in float for the peak picking")
        for name in _head_outputs(model):
            keep.setdefault(name, HEAD_OUTPUT_NOTE)
        for name in _ancestors(model, _first(model, "ScatterND").output[0]):
            keep.setdefault(name, PILLAR_NOTE)
    else:
        raise ValueError(f"unknown graph {graph!r}; expected image_encoder, volumetric_lifter or slice_head")
    return keep


# ---- quantizing one graph -----------------------------------------------------------------------------------


class _FeedReader(CalibrationDataReader):
    """onnxruntime's calibration reader over a sequence of feed dicts."""

    def __init__(self, feeds: Iterable[Feeds]) -> None:
        self._it: Iterator[Feeds] = iter(feeds)

    def get_next(self) -> Feeds | None:
        return next(self._it, None)


@dataclass(frozen=True)
class QuantizedGraph:
    path: Path
    num_inputs: int  # calibration feeds
    quantized_ops: dict[str, int]  # op type -> nodes onnxruntime can run in int8 (``quantized_ops``)
    float_nodes: dict[str, int]  # reason -> nodes kept float for it
    seconds: float


def _pre_process(src: str | Path, pre: Path) -> None:
    """``quant_pre_process`` (module doc); its symbolic shape inference is skipped where it fails: onnxruntime's
    raises a TypeError on the slice graph at opsets 18-20 (``Shape`` with ``start`` / ``end``), and ONNX's own shape
    inference, which still runs, gives the quantizer what it needs there."""
    try:
        quant_pre_process(str(src), str(pre))
    except Exception as e:  # noqa: BLE001  # onnxruntime.tools' symbolic inference has no error type of its own
        log.info("int8: symbolic shape inference failed on %s (%s: %s); pre-processing without it", src, type(e).__name__, e)
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)


def quantize_graph(
    graph: str, src: str | Path, dst: str | Path, feeds: Sequence[Feeds], cfg: Int8Config = Int8Config()
) -> QuantizedGraph:
    """Write the int8 QDQ version of the fp32 graph ``src`` (one of the three) to ``dst``, calibrated on ``feeds``."""
    if not feeds:
        raise ValueError(f"{graph}: no calibration inputs")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="streamdet_int8_") as tmp:
        pre = Path(tmp) / "pre.onnx"
        with _quiet_quantizer():
            _pre_process(src, pre)
            model = onnx.load(str(pre))
            rewritten = graph == "image_encoder" and normalisation_as_batchnorm(model)
            rewritten = transposed_convs_as_depth_to_space(model) > 0 or rewritten
            if rewritten:
                onnx.save_model(model, str(pre))
            keep = float_nodes(graph, model, cfg)
            quantize_static(
                str(pre),
                str(dst),
                _FeedReader(feeds),
                quant_format=QuantFormat.QDQ,
                per_channel=cfg.per_channel,
                reduce_range=cfg.reduce_range,
                activation_type=ACTIVATION_TYPE,
                weight_type=WEIGHT_TYPE,
                nodes_to_exclude=sorted(keep),
                calibrate_method=cfg.calibrate_method,
                calibration_providers=["CPUExecutionProvider"],
            )
    _restore_io(Path(dst), onnx.load(str(src), load_external_data=False))
    model = onnx.load(str(dst))
    if shapes_of_quantized(model):
        onnx.save_model(model, str(dst))
    reasons: dict[str, int] = {}
    for why in keep.values():
        reasons[why] = reasons.get(why, 0) + 1
    return QuantizedGraph(Path(dst), len(feeds), quantized_ops(onnx.load(str(dst))), reasons, time.perf_counter() - t0)


def shapes_of_quantized(model: onnx.ModelProto) -> int:
    """Point every ``Shape`` that reads a DequantizeLinear's output at that node's quantized input (the same shape)
    and drop the DequantizeLinear nodes no one reads any more. In place; returns how many Shapes moved.

    The QDQ quantizer hands a quantized tensor's every consumer a dequantized copy, a Shape too: the slice graph
    reads the quadrant count off ``image_bev``, and onnxruntime dequantized the whole map once per slice for it.
    """
    producer = {o: n for n in model.graph.node for o in n.output}
    moved = 0
    for node in model.graph.node:
        source = producer.get(node.input[0]) if node.op_type == "Shape" and node.input else None
        if source is not None and source.op_type == "DequantizeLinear":
            node.input[0] = source.input[0]
            moved += 1
    read = {i for n in model.graph.node for i in n.input} | {o.name for o in model.graph.output}
    dead = [n for n in model.graph.node if n.op_type == "DequantizeLinear" and not any(o in read for o in n.output)]
    for n in dead:
        model.graph.node.remove(n)
    return moved


def _restore_io(path: Path, original: onnx.ModelProto) -> None:
    """Give the quantized graph the original's input and output declarations: symbolic shape inference renames
    the dynamic dimensions ("Hf" becomes "floor(floor(H/2 - 1/2)/2) + 1"), and the manifest names them."""
    model = onnx.load(str(path))
    by_name = {v.name: v for v in (*original.graph.input, *original.graph.output)}
    for v in (*model.graph.input, *model.graph.output):
        if v.name not in by_name:
            raise ValueError(f"the quantized graph has an input or output {v.name!r} the original lacks")
        v.type.CopyFrom(by_name[v.name].type)
    onnx.save_model(model, str(path))


def quantized_ops(model: onnx.ModelProto) -> dict[str, int]:
    """Op type -> number of nodes that onnxruntime can run in int8: every input a DequantizeLinear output (or a
    constant) and every output read only by QuantizeLinear nodes (the QDQ node units it fuses)."""
    producer = {o: n for n in model.graph.node for o in n.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for n in model.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    graph_outputs = {o.name for o in model.graph.output}
    counts: dict[str, int] = {}
    for n in model.graph.node:
        if n.op_type in ("QuantizeLinear", "DequantizeLinear"):
            continue
        ins = [producer.get(i) for i in n.input if i]
        if not any(p is not None and p.op_type == "DequantizeLinear" for p in ins):
            continue
        if any(p is not None and p.op_type not in ("DequantizeLinear", "Constant") for p in ins):
            continue
        users = [u for o in n.output for u in consumers.get(o, [])]
        if not users or any(o in graph_outputs for o in n.output) or any(u.op_type != "QuantizeLinear" for u in users):
            continue
        counts[n.op_type] = counts.get(n.op_type, 0) + 1
    return dict(sorted(counts.items()))


@contextmanager
def _quiet_quantizer() -> Iterator[None]:
    """The quantizer logs a warning per bias it cannot type and advises pre-processing (done): keep errors only."""
    root = logging.getLogger()
    level = root.level
    root.setLevel(max(level, logging.ERROR))
    try:
        yield
    finally:
        root.setLevel(level)
