"""The modules behind the rows of the paper's Table 3, their benchmark inputs, and their ONNX exports.

The rows are not the three deployment graphs: each row isolates one module the way the paper times it (one image,
30,000 points, ``benchmarks/flops_report.py``):

- slice rows: SliceNet + in-graph decode (``slice_head.onnx``'s module) with the multi head / single head on one
  map the size of the whole grid (Q = 1, "uncropped"), and the single head on one quadrant ("cropped");
- 3D-convolution rows: the lifter after its gather (BN, 1x1x1 conv, residual k3 conv, z-strided conv, pooling)
  on the whole volume and on one quadrant volume, as the export writes it (z folded into channels where that pays,
  ``models/lifter_fold.py``; the GMAC stays the 3D convolutions' own);
- image rows: the image encoder at each resolution (one export, dynamic H and W as the deployed graph).

Weights are a seeded random init in eval mode: the time of a dense convolution does not depend on the values.
Each graph is exported with the export library (``streamdet.export.onnx_export``) and given an fp16 sibling with
``convert_model_to_fp16``, keeping in fp32 what the deployed fp16 slice graph keeps (decode and heatmap convs), and
an int8 sibling with ``streamdet.export.int8.quantize_graph`` (what ``streamdet-export --int8`` writes, with the same
nodes kept float). The int8 rows are calibrated on the row's own benchmark input: their weights are random too, and
the time of the int8 kernels does not depend on the values; int8 accuracy is the export's parity record and
``streamdet-eval --precision int8``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import Tensor, nn

from streamdet.benchmarks.flops_report import BENCH_NUM_IMAGES, gmac_rows, slice_row_pillars
from streamdet.core.errors import first_line
from streamdet.export.fp16 import check_model, convert_model_to_fp16
from streamdet.export.int8 import quantize_graph
from streamdet.export.onnx_export import (
    IMAGE_ENCODER_IO,
    SLICE_HEAD_IO,
    GraphIO,
    export_module,
    export_slice_head,
    heatmap_producers,
    is_decode_node,
    save_model,
    slice_decoder,
)
from streamdet.models.detector import StreamDetector
from streamdet.models.decode import SliceDecoder
from streamdet.models.flat_lifter import FlatLifterConvs
from streamdet.models.lifter_fold import FoldedLifterConvs, LifterConvs, export_lifter_convs, folded_mac_ratio
from streamdet.models.presets import Preset
from streamdet.models.peak_head import peak_head_mac_ratio
from streamdet.models.slice_split import grouped_head_mac_ratio

# The deployed graph each kind of row is cut from: its int8 sibling keeps the same nodes float.
INT8_GRAPH_OF_KIND = {"slice": "slice_head", "conv3d": "volumetric_lifter", "image": "image_encoder"}

# The lifter's convolutions alone: the volume in, the image BEV out. Q dynamic like the deployed lifter.
LIFTER_CONVS_IO = GraphIO(
    name="lifter_convs",
    inputs=("volume",),
    outputs=("image_bev",),
    dynamic_axes={"volume": {0: "Q"}, "image_bev": {0: "Q"}},
)


@dataclass(frozen=True, eq=False)
class Row:
    """One Table 3 row: a torch module, its inputs, how to export it, and its MACs by the torch counter."""

    module: str  # the row's label, as benchmarks/flops_report.py names it
    key: str  # file stem of its graphs
    kind: str  # slice | conv3d | image
    net: nn.Module  # eval mode
    inputs: tuple[Tensor, ...]
    io: GraphIO
    gmac: float  # models/flops.py's counter, through flops_report.gmac_rows
    graph_key: str = ""  # rows that share one exported graph (the image rows) name it here; "" = own graph
    detector: StreamDetector | None = None  # slice rows: the detector export_slice_head takes
    notes: tuple[str, ...] = ()  # printed under the table with the row's measurement notes
    # what the graph is exported from when the export rewrites ``net`` (same function; PyTorch is timed on both)
    export_net: nn.Module | None = None

    @property
    def graph_net(self) -> nn.Module:
        return self.net if self.export_net is None else self.export_net

    @property
    def graph_stem(self) -> str:
        return self.graph_key or self.key

    def feeds(self) -> dict[str, np.ndarray]:
        return {name: t.numpy() for name, t in zip(self.io.inputs, self.inputs)}

    def input_shapes(self) -> dict[str, tuple[int, ...]]:
        return {name: tuple(t.shape) for name, t in zip(self.io.inputs, self.inputs)}


def pillar_inputs(preset: Preset, cropped: bool, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The slice graph's inputs: the pillars ``flops_report`` counts (30,000 points of the bundled sweep, on the whole
    grid or in the busiest quadrant, ``benchmarks/sweep_pillars.py``) and a seeded random image BEV on that map."""
    pillars = slice_row_pillars(preset, cropped)
    gen = torch.Generator().manual_seed(seed)
    image_bev = torch.randn(1, preset.channels, pillars.map_ny, pillars.map_nx, generator=gen)  # (Q=1, C, Y, X)
    return (
        torch.from_numpy(pillars.features),  # (P, M, 11)
        torch.from_numpy(pillars.mask),  # (P, M)
        torch.from_numpy(pillars.index),  # (P,) increasing
        image_bev,
    )


def build_rows(preset: Preset, resolutions: list[tuple[int, int]], seed: int = 0) -> list[Row]:
    """The Table 3 rows of ``preset``: five slice / 3D-conv rows, then one image row per (width, height)."""
    g = preset.grid
    gmacs = gmac_rows(preset, resolutions)
    torch.manual_seed(seed)
    head = lambda multi: dataclasses.replace(preset, head=dataclasses.replace(preset.head, multi_head=multi))  # noqa: E731
    multi, single = head(True), head(False)
    det_multi = StreamDetector(multi).eval()  # its image lane goes unused; building it costs a second
    det = StreamDetector(single).eval()
    if det.image_encoder is None or det.lifter is None:
        raise ValueError(f"preset {preset.name!r} has use_image=False: it has no image rows to benchmark")
    # PyTorch runs each module as trained (``net``); the graphs come from the export's rewrites of some of them
    # (``export_net``: models/slice_split.py, models/lifter_fold.py), which PyTorch is timed on as well
    slice_multi, slice_single = SliceDecoder(det_multi.slice_net, multi).eval(), SliceDecoder(det.slice_net, single).eval()
    split_multi, split_single = slice_decoder(det_multi), slice_decoder(det)
    convs = LifterConvs(det.lifter).eval()
    folded: nn.Module | None = export_lifter_convs(det.lifter, preset.lifter, g.nz).eval()
    conv_notes: tuple[str, ...] = ()
    if isinstance(folded, FlatLifterConvs):
        conv_notes = ("the flat lifter (models/flat_lifter.py): 2D convolutions over z stacked into channels, "
                      "exported with its BatchNorms folded",)  # fmt: skip
    elif not isinstance(folded, FoldedLifterConvs):
        folded = None  # exported as it is: nothing else to time
    else:
        conv_notes = (
            f"exported as 2D convolutions over z folded into channels (models/lifter_fold.py): the graph computes "
            f"{folded_mac_ratio(preset.lifter, g.nz):.2f}x the 3D convolutions' MACs in banded zero taps and runs "
            "faster; GMAC, GFLOP/s and % peak count the 3D convolutions' own MACs",
        )
    encoder = det.image_encoder
    multi_head = det_multi.slice_net.head
    multi_notes = (
        f"exported with each output's branches grouped across the {len(multi_head.tasks)} tasks (models/slice_split.py, "
        f"GroupedTaskHead): the graph computes {grouped_head_mac_ratio(multi_head):.2f}x the head branches' MACs in zero "
        "blocks and runs faster; GMAC, GFLOP/s and % peak count the model's own MACs",
    )

    single_head = det.slice_net.head

    def single_notes(cropped: bool) -> tuple[str, ...]:
        cells = (g.quadrant_ny * g.quadrant_nx if cropped else g.ny * g.nx) // preset.head.out_stride**2
        ratio = peak_head_mac_ratio(single_head, cells, preset.top_k)
        return (
            f"exported with the head's regression computed at the decode's {preset.top_k} peaks only "
            f"(models/peak_head.py): the graph computes {ratio:.2f}x the head branches' MACs; GMAC, GFLOP/s and % "
            "peak count the model's own MACs",
        )

    def volume(ny: int, nx: int) -> Tensor:
        gen = torch.Generator().manual_seed(seed)
        return torch.randn(1, preset.channels, g.nz, ny, nx, generator=gen)  # (Q=1, C, Z, Y, X)

    rows = [
        Row(
            gmacs[0].module, "slice_multi_head", "slice", slice_multi, pillar_inputs(multi, False, seed),
            SLICE_HEAD_IO, gmacs[0].gmac, detector=det_multi, export_net=split_multi, notes=multi_notes,
        ),
        Row(
            gmacs[1].module, "slice_single_head", "slice", slice_single, pillar_inputs(single, False, seed),
            SLICE_HEAD_IO, gmacs[1].gmac, detector=det, export_net=split_single, notes=single_notes(False),
        ),
        Row(
            gmacs[2].module, "slice_single_head_cropped", "slice", slice_single,
            pillar_inputs(single, True, seed), SLICE_HEAD_IO, gmacs[2].gmac, detector=det, export_net=split_single,
            notes=single_notes(True),
        ),
        Row(
            gmacs[3].module, "conv3d", "conv3d", convs, (volume(g.ny, g.nx),), LIFTER_CONVS_IO, gmacs[3].gmac,
            notes=conv_notes, export_net=folded,
        ),
        Row(
            gmacs[4].module, "conv3d_cropped", "conv3d", convs, (volume(g.quadrant_ny, g.quadrant_nx),),
            LIFTER_CONVS_IO, gmacs[4].gmac, notes=conv_notes, export_net=folded,
        ),
    ]
    for (w, h), gm in zip(resolutions, gmacs[5:]):
        gen = torch.Generator().manual_seed(seed)
        images = torch.randint(0, 256, (BENCH_NUM_IMAGES, h, w, 3), dtype=torch.uint8, generator=gen)  # (J, H, W, 3)
        rows.append(Row(gm.module, f"image_{w}x{h}", "image", encoder, (images,), IMAGE_ENCODER_IO, gm.gmac, graph_key="image_encoder"))
    return rows


def _slice_keep(model: onnx.ModelProto) -> Callable[[onnx.NodeProto], bool]:
    """The deployed fp16 slice graph keeps the decode and the heatmap-logit convs in fp32 (export/fp16.py explains
    the peak-picking ties fp16 would create); so does the row's."""
    producers = set(heatmap_producers(model))
    return lambda node: is_decode_node(node) or node.name in producers


@dataclass(frozen=True)
class RowGraphs:
    fp32: Path
    fp16: Path | None  # None when not asked for or when the conversion failed (fp16_error says why)
    fp16_error: str | None
    model: onnx.ModelProto  # the fp32 graph, for the MAC cross-check
    int8: Path | None = None  # None when not asked for or when the quantization failed (int8_error says why)
    int8_error: str | None = None


def _int8_row(row: Row, fp32: Path, out_dir: Path) -> tuple[Path | None, str | None]:
    path = out_dir / f"{row.graph_stem}.int8.onnx"
    try:
        quantize_graph(INT8_GRAPH_OF_KIND[row.kind], fp32, path, [row.feeds()])
        check_model(path)
    except Exception as e:  # noqa: BLE001 - a failed quantization is a result to report, not a crash of the run
        return None, f"{type(e).__name__}: {first_line(e)}"
    return path, None


def export_row(row: Row, out_dir: Path, fp16: bool = True, int8: bool = False) -> RowGraphs:
    """Export ``row.graph_net`` (slice rows: the detector's slice graph) to ``out_dir/<graph_stem>.onnx`` and its
    siblings ``<graph_stem>.fp16.onnx`` (``fp16``)
    and ``<graph_stem>.int8.onnx`` (``int8``)."""
    if row.kind == "slice":
        model = export_slice_head(row.detector, row.inputs)
        keep: Callable[[onnx.NodeProto], bool] | tuple[()] = _slice_keep(model)
    else:
        model = export_module(row.graph_net, row.inputs, row.io)
        keep = ()
    fp32 = out_dir / f"{row.graph_stem}.onnx"
    save_model(model, fp32)
    int8_path, int8_error = _int8_row(row, fp32, out_dir) if int8 else (None, None)
    if not fp16:
        return RowGraphs(fp32, None, None, model, int8_path, int8_error)
    fp16_path: Path | None = out_dir / f"{row.graph_stem}.fp16.onnx"
    error = None
    try:
        converted, _ = convert_model_to_fp16(model, keep)
        check_model(converted)  # the converter's output is no guarantee of a valid graph
        save_model(converted, fp16_path)
    except Exception as e:  # noqa: BLE001 - a failed conversion is a result to report, not a crash of the run
        fp16_path, error = None, f"{type(e).__name__}: {first_line(e)}"
    return RowGraphs(fp32, fp16_path, error, model, int8_path, int8_error)
