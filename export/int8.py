"""int8 siblings of exported graphs: static QDQ quantization calibrated on real inputs (numpy + onnxruntime).

Format. ``onnxruntime.quantization.quantize_static`` in QDQ form: weights int8, symmetric, one scale per output
channel; activations **uint8**, asymmetric, one scale per tensor. onnxruntime's x86 CPU provider fuses
``DequantizeLinear -> Conv -> QuantizeLinear`` into its int8 convolution (QLinearConv, u8s8 GEMM) only with uint8
activations. The fusion needs the session at ORT_ENABLE_ALL (what the runtime uses): the int8 NHWC kernels come
with it, and the small int8 encoder measured 1.4x slower at ENABLE_EXTENDED. ``quantize_dynamic`` is not a path: it makes ConvInteger, slower than fp32.

Weights are 7-bit (``reduce_range``) by default. x86 CPUs without VNNI (AVX2 only, like the AMD EPYC this was
measured on) multiply u8 x s8 with ``vpmaddubsw``, which adds two products into a saturating int16: 255 * 127 * 2
overflows it, 255 * 63 * 2 does not. Measured on the small image encoder (bundled images, untrained weights):
relative L2 error of the features 0.354 with 8-bit weights, 0.070 with 7-bit. With 7-bit weights the graph computes the same thing on every
x86 CPU, VNNI or not.

Pre-processing. The TorchScript exporter shares equal initializers (e.g. zero biases) through ``Identity`` nodes,
and the quantizer does not make a QDQ unit of a Conv whose bias is not an initializer (measured: 16 of the 25
convolutions of the small image encoder stay float). ``quant_pre_process`` (shape inference and onnxruntime's basic optimisations, which
fold those Identities) runs first.

What stays float, and why (``float_nodes``; timings with onnxruntime 1.32, one thread, small preset):

- slice graph, the decode and the heatmap convolution: peak picking keeps a cell that equals the max of its 3x3
  neighbourhood. A uint8 heatmap has 256 levels over the logit range, so neighbouring cells of one object round
  to the same level, each of them is a "peak", and one object yields several boxes. The heatmap logits are
  computed in float (their last conv excluded) and the sigmoid / max-pool / equality / top-k / box arithmetic run
  in float on them. The other head outputs (centre offset, z, log size, yaw, velocity) come from float convs too:
  the decode turns them into box values directly, and these 1-layer convs are a few percent of the graph.
- slice graph, the pillar net and scatter: ``pillar_features`` holds x and y (up to +-51 m) beside offsets of a
  few centimetres and reflectance in 0..1; one uint8 scale per tensor (0.4 m steps) would erase all but x and y.
  The PointNet is a single 11-input linear layer, which int8 would not speed up.
- image encoder, the input normalisation (cast, scale, shift of the full image), rewritten as one float
  BatchNormalization (``normalisation_as_batchnorm``, bit-identical in fp32). onnxruntime runs the int8 convolutions
  in NHWC and moves the graph's NHWC -> NCHW transpose of the image past the Mul and Add, which then broadcast
  their per-channel constants over the innermost axis of size 3. Measured at 384x216: that float Mul + Add 6.6 ms,
  quantized (QLinearMul + QLinearAdd) 11.5 ms, the BatchNormalization (which the transpose is not moved past)
  0.2 ms, the whole int8 encoder 33 ms in float Mul + Add, 26 ms with the BatchNormalization.
- lifter, z pooling and the max over z: QLinearAveragePool measured 23 ms where the float AveragePool takes 6 and
  the DequantizeLinear before it 5 (small preset, Q = 4).
- lifter, the LUT gather and weighted sum (``Int8Config.quantize_lifter_gather``, off): quantized, the feature
  table is quantized once, gathered and weighted as uint8 (QLinearMul), and the gathered (Q, K, Z, Yq, Xq, C)
  rows, K = 2 times the volume, are dequantized before the sum. Measured at the runtime's Q = 4 (small preset, one
  thread, per-op profiles): gather + weighting + that DequantizeLinear + sum + BN took 150-160 ms against 145-150 ms
  for the float gather, weighting and sum followed by one QuantizeLinear of the volume; the whole int8 lifter ran
  1.51x and 1.52x faster than fp32. It saves nothing, and quantizing the features before the camera average adds
  error (relative L2 of the image BEV 0.0187 against 0.0178), so the gather stays float and the volume is
  quantized once, before the first 3D convolution.
- ConvTranspose (the BEV encoder's upsampling): onnxruntime has no QDQ ConvTranspose; it runs in float between a
  DequantizeLinear and a QuantizeLinear.

Calibration. Ranges come from real graph inputs (``graph_inputs``): camera images for the encoder, the fp32
encoder's features of those images with each sample's own LUT for the lifter, and pillarised LiDAR slices with the
fp32 lifter's image BEV for the slice graph (a LiDAR-only export: the pillarised slices alone, no image is read). Never random tensors: a ReLU network's activation ranges on noise have
nothing to do with its ranges on images. MinMax calibration: Percentile and Entropy keep a histogram of every
activation of every input in memory. ``CalibMaxIntermediateOutputs`` is not used: onnxruntime 1.32 clears the data
it collected without merging it and then fails with "No data is collected".
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import numpy_helper
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from streamdet.calibration.lut import Lut, build_lut
from streamdet.data.sample import Sample, load_bundled_sample, load_image
from streamdet.data.slicing import slice_sample
from streamdet.runtime_ort.manifest import BoxAgreement, Int8Calibration, Int8OutputParity
from streamdet.export.onnx_export import heatmap_producers, is_decode_node
from streamdet.runtime_ort.boxes import YAW
from streamdet.runtime_ort.pillarize import pillarize

ACTIVATION_TYPE = QuantType.QUInt8  # the only activation type x86 onnxruntime runs as fused int8 convolutions
WEIGHT_TYPE = QuantType.QInt8
BUNDLED_SOURCE = "bundled:nuscenes_sample"
DEFAULT_CALIBRATION_SAMPLES = 8  # samples of a --calibration-data dataset (6 images and n slices each)
BOX_SCORE_THRESHOLD = 0.1  # boxes compared by box_agreement (the pipeline parity's threshold)
INPUT_NORM_NOTE = "input normalisation: quantized it costs 50x a float BatchNormalization on the NCHW image"
LIFTER_POOL_NOTE = "z pooling: QLinearAveragePool costs 2x the float AveragePool with its DequantizeLinear"
LIFTER_GATHER_NOTE = "LUT gather and weighted sum: dequantizing K x the volume costs what the uint8 gather saves"
HEAD_OUTPUT_NOTE = "head outputs: the decode reads them as box values; uint8 steps would show in the boxes"
PILLAR_NOTE = "pillar net and scatter: metres and centimetre offsets in one tensor do not share a uint8 scale"

Feeds = dict[str, np.ndarray]


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


def _first(model: onnx.ModelProto, op_type: str) -> onnx.NodeProto:
    nodes = [n for n in model.graph.node if n.op_type == op_type]
    if not nodes:
        raise ValueError(f"the graph has no {op_type} node")
    return nodes[0]  # graphs are topologically sorted


def _head_outputs(model: onnx.ModelProto) -> set[str]:
    """The last layers of the head: nodes from the decode's inputs upstream to (and including) the first Conv."""
    producer = {o: n for n in model.graph.node for o in n.output}
    found: set[str] = set()
    stack = [i for n in model.graph.node if is_decode_node(n) for i in n.input]
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in found or is_decode_node(node):
            continue
        found.add(node.name)
        if node.op_type != "Conv":
            stack.extend(node.input)
    return found


def _constant(model: onnx.ModelProto, name: str) -> np.ndarray | None:
    for t in model.graph.initializer:
        if t.name == name:
            return numpy_helper.to_array(t)
    for n in model.graph.node:
        if n.op_type == "Constant" and n.output[0] == name:
            return numpy_helper.to_array(n.attribute[0].t)
    return None


def normalisation_as_batchnorm(model: onnx.ModelProto) -> bool:
    """Rewrite the encoder's input normalisation ``Add(Mul(x, scale), shift)`` with (1, C, 1, 1) constants before
    the first Conv into one BatchNormalization (mean 0, variance 1, epsilon 0: the same arithmetic). In place;
    False when there is no such pair. See the module doc for why."""
    first = _first(model, "Conv")
    producer = {o: n for n in model.graph.node for o in n.output}
    add = producer.get(first.input[0])
    mul = producer.get(add.input[0]) if add is not None and add.op_type == "Add" else None
    if mul is None or mul.op_type != "Mul":
        return False
    scale, shift = _constant(model, mul.input[1]), _constant(model, add.input[1])
    per_channel = lambda a: a is not None and a.ndim == 4 and a.shape[0] == a.shape[2] == a.shape[3] == 1  # noqa: E731
    if not (per_channel(scale) and per_channel(shift) and scale.shape == shift.shape):
        return False
    users = [n for n in model.graph.node if mul.output[0] in n.input]
    if users != [add]:
        return False
    c = scale.shape[1]  # (1, C, 1, 1)
    names = [f"{first.name}/input_norm_{k}" for k in ("scale", "shift", "mean", "var")]
    values = [scale.reshape(c), shift.reshape(c), np.zeros(c), np.ones(c)]
    model.graph.initializer.extend(numpy_helper.from_array(v.astype(np.float32), n) for n, v in zip(names, values))
    bn = onnx.helper.make_node("BatchNormalization", [mul.input[0], *names], [add.output[0]], epsilon=0.0,
                               name=f"{first.name}/input_norm")  # fmt: skip
    nodes = [bn if n is mul else n for n in model.graph.node if n is not add]
    used = {i for n in nodes for i in n.input}
    nodes = [n for n in nodes if not (n.op_type == "Constant" and n.output[0] not in used)]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    inits = [t for t in model.graph.initializer if t.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(inits)
    return True


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
            quant_pre_process(str(src), str(pre))
            model = onnx.load(str(pre))
            if graph == "image_encoder" and normalisation_as_batchnorm(model):
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
    reasons: dict[str, int] = {}
    for why in keep.values():
        reasons[why] = reasons.get(why, 0) + 1
    return QuantizedGraph(Path(dst), len(feeds), quantized_ops(onnx.load(str(dst))), reasons, time.perf_counter() - t0)


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


# ---- calibration data ---------------------------------------------------------------------------------------


class CalibrationError(ValueError):
    """Calibration data that cannot be used, stated in one line."""


@dataclass(frozen=True, eq=False)
class CalibrationSamples:
    samples: tuple[Sample, ...]
    source: str  # BUNDLED_SOURCE or the dataset directory
    version: str
    split: str  # "train" or "all"


def dataset_version(root: str | Path) -> str:
    """The nuScenes table folder under ``root`` (``v1.0-*`` holding sample.json); a test split is never used."""
    root = Path(root)
    if not root.is_dir():
        raise CalibrationError(f"calibration data {str(root)!r} is not a directory")
    found = sorted(p.name for p in root.glob("v1.0-*") if (p / "sample.json").is_file())
    usable = [v for v in found if not v.endswith("-test")]
    if not usable:
        raise CalibrationError(
            f"calibration data {str(root)!r} holds no nuScenes table folder (v1.0-*/sample.json)"
            + (f"; only the test split {found}" if found else "")
        )
    return usable[0]


def load_calibration_samples(data_dir: str | Path | None, num_samples: int, camera_names: Sequence[str]) -> CalibrationSamples:
    """Samples to calibrate on: ``num_samples`` spread evenly over the train split of a nuScenes-format dataset
    (all of it without a ``splits.json``), or the bundled nuScenes sample when ``data_dir`` is None.

    Every sample must have an image of each of ``camera_names`` (the export's rig).
    """
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
        raise CalibrationError(f"calibration samples must be a positive integer, got {num_samples!r}")
    if data_dir is None:
        samples: tuple[Sample, ...] = (load_bundled_sample(),)
        source, version, split = BUNDLED_SOURCE, "v1.0-mini", "all"
    else:
        from streamdet.data.nuscenes import NuScenesReader
        from streamdet.evaluation.dataset_eval import split_tokens

        version = dataset_version(data_dir)
        try:
            reader = NuScenesReader(data_dir, version)
            has_train = _has_split(Path(data_dir), "train")
            tokens = split_tokens(reader, data_dir, "train" if has_train else None)
        except (OSError, KeyError, ValueError) as e:
            raise CalibrationError(f"calibration data {str(data_dir)!r}: {e}") from None
        if not tokens:
            raise CalibrationError(f"calibration data {str(data_dir)!r} holds no samples")
        pick = np.unique(np.linspace(0, len(tokens) - 1, min(num_samples, len(tokens))).round().astype(int))
        try:
            samples = tuple(reader.get(tokens[i]) for i in pick)
        except (OSError, KeyError, ValueError) as e:
            raise CalibrationError(f"calibration data {str(data_dir)!r}: {e}") from None
        source, split = str(data_dir), "train" if has_train else "all"
    for s in samples:
        missing = [n for n in camera_names if n not in s.image_paths]
        if missing:
            raise CalibrationError(
                f"calibration sample {s.token} of {source} has no image of cameras {missing} (the export's rig needs "
                f"{list(camera_names)}); calibrate on data from this rig with --calibration-data"
            )
    return CalibrationSamples(samples, source, version, split)


def _has_split(root: Path, split: str) -> bool:
    path = root / "splits.json"
    if not path.is_file():
        return False
    try:
        return isinstance(json.loads(path.read_text()).get(split), list)
    except (OSError, ValueError, AttributeError):
        return False


@dataclass(frozen=True)
class GraphInputs:
    """Real inputs of the three graphs (fp32 graphs upstream), one list of feed dicts per graph."""

    image_encoder: list[Feeds]
    volumetric_lifter: list[Feeds]
    slice_head: list[Feeds]
    slice_sources: list[tuple[int, tuple[int, ...]]] = field(default_factory=list)  # per slice feed: (position of its
    # sample in the volumetric_lifter feeds, the quadrants its image_bev was cut from)

    def for_graph(self, name: str) -> list[Feeds]:
        return getattr(self, name)


def sample_lut(sample: Sample, camera_names: Sequence[str], grid, feature_stride: int, size: tuple[int, int]) -> Lut:
    """The sample's own projection LUT (its rig, resized to the export's images), cameras in export order."""
    if tuple(sample.rig.names) != tuple(camera_names):
        raise CalibrationError(
            f"sample {sample.token} has cameras {list(sample.rig.names)}; the export's rig orders them "
            f"{list(camera_names)}: the LUT rows would not match the encoded images"
        )
    return build_lut(sample.rig, grid, feature_stride, size)


def graph_inputs(
    samples: Sequence[Sample],
    sessions32: Mapping[str, Any],
    camera_names: Sequence[str],
    size: tuple[int, int],
    preset: Any,
    num_slices: int,
    luts: Sequence[Lut] | None = None,
) -> GraphInputs:
    """Run the fp32 encoder and lifter over the samples to get each graph's real inputs.

    ``sessions32``: onnxruntime sessions of the fp32 graphs by name; ``size`` (W, H) of the export's images;
    ``preset`` the exported ``Preset`` (grid, feature stride, pillar limits); ``luts`` one per sample, default
    each sample's own (``sample_lut``). Slices without a pillar are left out (the runtime does not run them).

    A LiDAR-only preset (``use_image`` False) has only the slice graph: its feeds are the pillar tensors and the
    slice's quadrant ids, no image is read (``camera_names`` may be empty, ``sessions32`` need only hold slice_head),
    and the encoder and lifter lists stay empty.
    """
    if not preset.use_image:
        return _lidar_graph_inputs(samples, preset, num_slices)
    enc, lift, sl = [], [], []
    sources = []
    pil = preset.pillars
    for i, sample in enumerate(samples):
        images = np.stack([load_image(sample.image_paths[n], size) for n in camera_names])  # (J, H, W, 3)
        lut = luts[i] if luts is not None else sample_lut(sample, camera_names, preset.grid, preset.image.feature_stride, size)
        (features,) = sessions32["image_encoder"].run(None, {"images": images})  # (J, C, Hf, Wf)
        lifter_feeds = {"features": features, "lut_index": lut.index, "lut_weight": lut.weight}
        (bev,) = sessions32["volumetric_lifter"].run(None, lifter_feeds)  # (4, C, Yq, Xq)
        enc.append({"images": images})
        lift.append(lifter_feeds)
        for s in slice_sample(sample, num_slices):
            pl = pillarize(s.points, preset.grid, s.quadrants, pil.max_points_per_pillar, pil.max_pillars)
            if pl.num_pillars == 0:
                continue
            sl.append({**pl.as_feeds(), "image_bev": np.ascontiguousarray(bev[list(s.quadrants)])})  # (Q, C, Yq, Xq)
            sources.append((i, tuple(s.quadrants)))
    return GraphInputs(enc, lift, sl, sources)


def _lidar_graph_inputs(samples: Sequence[Sample], preset: Any, num_slices: int) -> GraphInputs:
    """The LiDAR-only slice graph's real inputs: every non-empty slice of every sample, pillarised."""
    sl, sources = [], []
    pil = preset.pillars
    for i, sample in enumerate(samples):
        for s in slice_sample(sample, num_slices):
            pl = pillarize(s.points, preset.grid, s.quadrants, pil.max_points_per_pillar, pil.max_pillars)
            if pl.num_pillars:
                sl.append(pl.as_feeds(tuple(s.quadrants)))
                sources.append((i, tuple(s.quadrants)))
    return GraphInputs([], [], sl, sources)


# ---- parity ---------------------------------------------------------------------------------------------------


def relative_l2(got: np.ndarray, ref: np.ndarray) -> float:
    """||got - ref|| / ||ref|| in float64; 0 when both are zero, inf when only ref is."""
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if got.shape != ref.shape:
        raise ValueError(f"shapes differ: {got.shape} vs the reference's {ref.shape}")
    diff = float(np.linalg.norm(got - ref))
    norm = float(np.linalg.norm(ref))
    if norm == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / norm


def dense_parity(graph: str, output: str, inputs: str, got: Sequence[np.ndarray], ref: Sequence[np.ndarray], note: str = "") -> Int8OutputParity:
    """Relative L2 error over all parity inputs together (outputs flattened and concatenated)."""
    g = np.concatenate([np.ravel(a) for a in got]) if got else np.zeros(0)
    r = np.concatenate([np.ravel(a) for a in ref]) if ref else np.zeros(0)
    max_abs = float(np.abs(g.astype(np.float64) - r).max()) if r.size else 0.0
    return Int8OutputParity(graph, output, inputs, relative_l2(g, r), max_abs, len(ref), note)


def pair_boxes(
    boxes_a: np.ndarray, labels_a: np.ndarray, boxes_b: np.ndarray, labels_b: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedy nearest-centre pairing of two box sets (same label, centres within ``radius_m``).

    Returns (index into a, index into b, centre distance) of each pair, nearest pairs first.
    """
    d = np.linalg.norm(boxes_a[:, None, :2].astype(np.float64) - boxes_b[None, :, :2], axis=-1)  # (Na, Nb)
    d[labels_a[:, None] != labels_b[None, :]] = np.inf
    used_a = np.zeros(len(boxes_a), dtype=bool)
    used_b = np.zeros(len(boxes_b), dtype=bool)
    ia, ib, dist = [], [], []
    for flat in np.argsort(d, axis=None, kind="stable"):
        i, j = divmod(int(flat), len(boxes_b))
        if not d[i, j] <= radius_m:
            break
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            ia.append(i)
            ib.append(j)
            dist.append(d[i, j])
    return np.asarray(ia, dtype=np.int64), np.asarray(ib, dtype=np.int64), np.asarray(dist, dtype=np.float64)


def box_agreement(
    dets32: Sequence[Sequence[np.ndarray]],
    dets8: Sequence[Sequence[np.ndarray]],
    cell_m: float,
    score_threshold: float = BOX_SCORE_THRESHOLD,
) -> BoxAgreement:
    """Boxes with score >= threshold of the fp32 and int8 pipelines, slice by slice and quadrant by quadrant.

    ``dets32`` / ``dets8``: per slice (det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K)).
    Pairs: same label, centres within two head cells (``pair_boxes``).
    """
    if len(dets32) != len(dets8):
        raise ValueError(f"{len(dets32)} fp32 slices but {len(dets8)} int8 slices")
    radius = 2.0 * cell_m
    n32 = n8 = 0
    dists, score_diffs, box_pairs = [], [], []
    for (b32, s32, l32), (b8, s8, l8) in zip(dets32, dets8):
        for q in range(s32.shape[0]):
            k32 = s32[q] >= score_threshold
            k8 = s8[q] >= score_threshold
            n32 += int(k32.sum())
            n8 += int(k8.sum())
            ia, ib, d = pair_boxes(b32[q][k32], l32[q][k32], b8[q][k8], l8[q][k8], radius)
            dists.append(d)
            score_diffs.append(np.abs(s32[q][k32][ia].astype(np.float64) - s8[q][k8][ib]))
            box_pairs.append((b32[q][k32][ia], b8[q][k8][ib]))
    dist = np.concatenate(dists) if dists else np.zeros(0)
    sd = np.concatenate(score_diffs) if score_diffs else np.zeros(0)
    matched = int(dist.size)
    return BoxAgreement(
        num_slices=len(dets32),
        score_threshold=score_threshold,
        pair_radius_m=radius,
        count_fp32=n32,
        count_int8=n8,
        matched=matched,
        max_centre_diff_m=float(dist.max()) if matched else math.nan,
        mean_centre_diff_m=float(dist.mean()) if matched else math.nan,
        max_score_diff=float(sd.max()) if matched else math.nan,
        note=f"{n32 - matched} fp32 and {n8 - matched} int8 boxes without a partner",
    )


def _slice_parity(
    inputs: str, dets8: Sequence[Sequence[np.ndarray]], dets32: Sequence[Sequence[np.ndarray]], cell_m: float
) -> list[Int8OutputParity]:
    """det_scores: the top-K scores sorted per quadrant (rank swaps between near-equal peaks do not count);
    det_boxes: the boxes above the threshold paired as in ``box_agreement``."""
    s8 = [np.sort(d[1], axis=1)[:, ::-1] for d in dets8]
    s32 = [np.sort(d[1], axis=1)[:, ::-1] for d in dets32]
    scores = dense_parity("slice_head", "det_scores", inputs, s8, s32, "top-K scores sorted per quadrant")
    got, ref = [], []
    for (b32, sc32, l32), (b8, sc8, l8) in zip(dets32, dets8):
        for q in range(sc32.shape[0]):
            k32, k8 = sc32[q] >= BOX_SCORE_THRESHOLD, sc8[q] >= BOX_SCORE_THRESHOLD
            ia, ib, _ = pair_boxes(b32[q][k32], l32[q][k32], b8[q][k8], l8[q][k8], 2.0 * cell_m)
            r, g = b32[q][k32][ia].astype(np.float64), b8[q][k8][ib].astype(np.float64)
            g[:, YAW] = r[:, YAW] + _wrap(g[:, YAW] - r[:, YAW])  # yaw pi and -pi are one heading
            ref.append(r)
            got.append(g)
    boxes = dense_parity("slice_head", "det_boxes", inputs, got, ref,
                         f"boxes with score >= {BOX_SCORE_THRESHOLD} paired by label and centre (all 9 columns, yaw "
                         "difference wrapped to [-pi, pi))")  # fmt: skip
    return [scores, boxes]


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class Int8Parity:
    outputs: tuple[Int8OutputParity, ...]
    boxes: BoxAgreement


def int8_parity(
    sessions32: Mapping[str, Any], sessions8: Mapping[str, Any], inputs: GraphInputs, cell_m: float
) -> Int8Parity:
    """int8 graphs against fp32 graphs on ``inputs`` (fp32 upstream): each graph alone on the same inputs, then the
    whole int8 pipeline (int8 encoder -> int8 lifter -> int8 slice graph) against the fp32 pipeline.

    Inputs without encoder feeds are a LiDAR-only export's: the slice graph is the whole pipeline, compared once."""
    out: list[Int8OutputParity] = []
    run = lambda s, feeds: s.run(None, feeds)  # noqa: E731
    if not inputs.image_encoder:
        dets32 = [run(sessions32["slice_head"], f) for f in inputs.slice_head]
        dets8 = [run(sessions8["slice_head"], f) for f in inputs.slice_head]
        out.extend(_slice_parity("same", dets8, dets32, cell_m))
        return Int8Parity(tuple(out), box_agreement(dets32, dets8, cell_m))
    f32 = [run(sessions32["image_encoder"], f)[0] for f in inputs.image_encoder]
    f8 = [run(sessions8["image_encoder"], f)[0] for f in inputs.image_encoder]
    out.append(dense_parity("image_encoder", "features", "same", f8, f32))
    bev32 = [run(sessions32["volumetric_lifter"], f)[0] for f in inputs.volumetric_lifter]
    bev8 = [run(sessions8["volumetric_lifter"], f)[0] for f in inputs.volumetric_lifter]
    out.append(dense_parity("volumetric_lifter", "image_bev", "same", bev8, bev32))
    dets32 = [run(sessions32["slice_head"], f) for f in inputs.slice_head]
    dets8 = [run(sessions8["slice_head"], f) for f in inputs.slice_head]
    out.extend(_slice_parity("same", dets8, dets32, cell_m))
    # the int8 pipeline: each int8 graph fed by the int8 graph before it
    bev8p = [run(sessions8["volumetric_lifter"], {**lf, "features": f})[0] for lf, f in zip(inputs.volumetric_lifter, f8)]
    out.append(dense_parity("volumetric_lifter", "image_bev", "pipeline", bev8p, bev32))
    dets8p = []
    for feeds, (i, quadrants) in zip(inputs.slice_head, inputs.slice_sources):
        bev = np.ascontiguousarray(bev8p[i][list(quadrants)])  # (Q, C, Yq, Xq)
        dets8p.append(run(sessions8["slice_head"], {**feeds, "image_bev": bev}))
    out.extend(_slice_parity("pipeline", dets8p, dets32, cell_m))
    return Int8Parity(tuple(out), box_agreement(dets32, dets8p, cell_m))
