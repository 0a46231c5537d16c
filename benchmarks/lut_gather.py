"""Does a cheaper LUT gather pay? The lifter's gather in four forms, timed with onnxruntime on an export's LUT.

``python -m streamdet.benchmarks.lut_gather --export-dir DIR [--rounds 30] [--threads 1]`` builds, for one
quadrant's LUT (``quadrant_lut``: the rows of the cameras that see it, what the phase-locked image lane lifts) and
for the whole LUT (the full update), small ONNX graphs of the gather alone (table in, (V, C) volume out):

- ``slots``: today's lifter: ``Gather`` of all K slots of every voxel, ``Mul`` by the weights, ``ReduceSum`` over K;
- ``compact``: the valid (voxel, camera) pairs (``calibration/compact_lut.py``): the voxels seen by two or more
  cameras combined first, then one row per voxel;
- ``slots_int8`` / ``compact_int8``: the same reading an int8 copy of the feature table (``QuantizeLinear`` of the
  table in the graph, then ``DequantizeLinear`` of the gathered rows), as an int8 image lane could.

and times the export's own lifter on the same quadrant (fp32 and int8, the gather plus its 3D convolutions) for
scale, fed the LUT in the layout its manifest names (``lut_layout``), and, for a K-slot export, fed the compacted LUT
without changing the graph (the combined rows made in numpy and appended to the table, a K = 1 LUT: what the runtime
alone could do). Rounds interleave the graphs so a busy machine slows them alike; medians, p95 and min are printed. The
transpose of the feature maps into the table, common to all forms, is left out. Results: benchmarks/RESULTS.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from streamdet.calibration.compact_lut import CompactLut, compact_lut, lifter_feeds
from streamdet.calibration.lut import Lut
from streamdet.calibration.quadrant_lut import quadrant_lut
from streamdet.core.lut_layout import LUT_SLOTS
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.onnx_build import make_model
from streamdet.benchmarks.timing import ort_session

OPSET = 17
INT8_SCALE = 0.05  # per-tensor scale of the int8 table (the timing does not depend on it)


def _const(name: str, value: np.ndarray) -> onnx.TensorProto:
    return numpy_helper.from_array(np.ascontiguousarray(value), name)


def _quantized_table(nodes: list, inits: list, table: str = "table") -> str:
    inits += [_const("q_scale", np.array(INT8_SCALE, np.float32)), _const("q_zero", np.array(0, np.int8))]
    nodes.append(helper.make_node("QuantizeLinear", [table, "q_scale", "q_zero"], [table + "_q"]))
    return table + "_q"


def _weighted_sum(nodes: list, inits: list, table: str, index: np.ndarray, weight: np.ndarray, out: str, int8: bool) -> None:
    """out (N, C) = sum over the K rows of index, weight (K, N) of weight * table[index]."""
    k, n = index.shape
    inits += [_const(out + "_idx", index.reshape(-1).astype(np.int64)), _const(out + "_w", weight[..., None].astype(np.float32)),
              _const(out + "_shape", np.array([k, n, -1], np.int64))]  # fmt: skip
    nodes.append(helper.make_node("Gather", [table, out + "_idx"], [out + "_rows"], axis=0))  # (K*N, C)
    rows = out + "_rows"
    if int8:
        nodes.append(helper.make_node("DequantizeLinear", [rows, "q_scale", "q_zero"], [rows + "_f"]))
        rows += "_f"
    nodes.append(helper.make_node("Reshape", [rows, out + "_shape"], [out + "_kn"]))  # (K, N, C)
    nodes.append(helper.make_node("Mul", [out + "_kn", out + "_w"], [out + "_wkn"]))
    inits.append(_const(out + "_axes", np.array([0], np.int64)))
    nodes.append(helper.make_node("ReduceSum", [out + "_wkn", out + "_axes"], [out], keepdims=0))  # (N, C)


def slots_graph(index: np.ndarray, weight: np.ndarray, channels: int, int8: bool = False) -> onnx.ModelProto:
    """Today's gather: index, weight (K, V)."""
    nodes: list = []
    inits: list = []
    table = _quantized_table(nodes, inits) if int8 else "table"
    _weighted_sum(nodes, inits, table, index, weight, "volume", int8)
    return _model(nodes, inits, channels)


def compact_graph(lut: CompactLut, channels: int, int8: bool = False) -> onnx.ModelProto:
    nodes: list = []
    inits: list = []
    table = _quantized_table(nodes, inits) if int8 else "table"
    _weighted_sum(nodes, inits, table, lut.multi_index, lut.multi_weight, "multi", int8)  # (M, C) float
    multi = "multi"
    if int8:  # the combined rows join the int8 table
        nodes.append(helper.make_node("QuantizeLinear", ["multi", "q_scale", "q_zero"], ["multi_q"]))
        multi = "multi_q"
    nodes.append(helper.make_node("Concat", [table, multi], ["ext"], axis=0))  # (R + 1 + M, C)
    inits += [_const("final_idx", lut.final_index.astype(np.int64)), _const("final_w", lut.final_weight[:, None])]
    nodes.append(helper.make_node("Gather", ["ext", "final_idx"], ["rows"], axis=0))  # (V, C)
    rows = "rows"
    if int8:
        nodes.append(helper.make_node("DequantizeLinear", ["rows", "q_scale", "q_zero"], ["rows_f"]))
        rows = "rows_f"
    nodes.append(helper.make_node("Mul", [rows, "final_w"], ["volume"]))
    return _model(nodes, inits, channels)


def _model(nodes: list, inits: list, channels: int) -> onnx.ModelProto:
    graph = helper.make_graph(
        nodes, "lut_gather", [helper.make_tensor_value_info("table", TensorProto.FLOAT, ["R", channels])],
        [helper.make_tensor_value_info("volume", TensorProto.FLOAT, ["V", channels])], inits,
    )  # fmt: skip
    model = make_model(graph, [helper.make_opsetid("", OPSET)])
    onnx.checker.check_model(model)
    return model




class _CompactedLifter:
    """The export's lifter graph fed a compacted LUT without changing the graph: the multi-camera voxels combined in
    numpy, appended to the feature table, and the table passed as one (1, C, 1, rows) feature map with a K = 1 LUT
    (the same BEV bit for bit: ``tests/test_compact_lut.py`` checks the gather)."""

    def __init__(self, session, lut: CompactLut, voxels: tuple[int, ...]) -> None:
        self.session = session
        self.lut = lut
        self.index = lut.final_index.reshape(1, 1, *voxels)  # (1, 1, Z, Yq, Xq)
        self.weight = lut.final_weight.reshape(1, 1, *voxels)

    def run(self, _outputs, features: np.ndarray):
        c = features.shape[1]
        table = features.transpose(0, 2, 3, 1).reshape(-1, c)  # (J*Hf*Wf, C)
        table = np.concatenate([table, np.zeros((1, c), np.float32)])  # + the sentinel row
        multi = (table[self.lut.multi_index] * self.lut.multi_weight[..., None]).sum(axis=0)  # (M, C)
        ext = np.ascontiguousarray(np.concatenate([table, multi]).T)[None, :, None, :]  # (1, C, 1, rows)
        return self.session.run(None, {"features": ext, "lut_index": self.index, "lut_weight": self.weight})


def _stats(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"{np.median(a):7.2f} {np.percentile(a, 95):7.2f} {a.min():7.2f}"


def run(export_dir: Path, rounds: int, threads: int, quadrant: int) -> list[str]:
    lut = Lut.load(export_dir / "lut.npz")
    channels = int(json.loads((export_dir / "manifest.json").read_text())["preset"]["channels"])
    cells = lut.feature_height * lut.feature_width
    rng = np.random.default_rng(0)
    cases = []
    qlut = quadrant_lut(lut, quadrant)
    for name, index, weight, maps in [
        (f"quadrant {quadrant} ({len(qlut.camera_names)} cameras)", qlut.index, qlut.weight, qlut.num_feature_maps),
        ("all 4 quadrants (6 cameras)", lut.index, lut.weight, lut.num_cameras),
    ]:
        sentinel = maps * cells
        k = index.shape[1]
        flat_i = index.transpose(1, 0, 2, 3, 4).reshape(k, -1)  # (K, V)
        flat_w = weight.transpose(1, 0, 2, 3, 4).reshape(k, -1)  # (K, V)
        comp = compact_lut(index, weight, sentinel)
        table = np.concatenate([rng.standard_normal((sentinel, channels)), np.zeros((1, channels))]).astype(np.float32)
        graphs = {
            "slots": slots_graph(flat_i, flat_w, channels), "compact": compact_graph(comp, channels),
            "slots_int8": slots_graph(flat_i, flat_w, channels, int8=True), "compact_int8": compact_graph(comp, channels, int8=True),
        }  # fmt: skip
        sessions = {g: ort_session(m, threads) for g, m in graphs.items()}
        ref = sessions["slots"].run(None, {"table": table})[0]
        assert np.allclose(sessions["compact"].run(None, {"table": table})[0], ref, atol=1e-6), "compact != slots"
        feeds = {g: {"table": table} for g in graphs}
        valid = int((index != sentinel).sum())
        cases.append((name, sessions, feeds, f"V {flat_i.shape[1]} voxels x K {k} slots, {valid} valid "
                      f"({100 * valid / flat_i.size:.0f} %), compact reads {comp.num_pairs} rows"))  # fmt: skip
    lifter = {}
    feats = rng.standard_normal((qlut.num_feature_maps, channels, lut.feature_height, lut.feature_width)).astype(np.float32)
    qcomp = compact_lut(qlut.index, qlut.weight, qlut.num_feature_maps * cells)
    layout = read_manifest(export_dir).lut_layout  # the lifter's LUT inputs (core/lut_layout.py)
    for precision, fname in (("fp32", "volumetric_lifter.onnx"), ("int8", "volumetric_lifter.int8.onnx")):
        if (export_dir / fname).is_file():
            session = ort_session(export_dir / fname, threads)
            lifter[f"export lifter {precision} ({layout} LUT), quadrant {quadrant}"] = (
                session, lifter_feeds(feats, qlut.index, qlut.weight, layout))
            if layout == LUT_SLOTS:  # a compact export's graph already reads the compacted LUT
                lifter[f"export lifter {precision}, quadrant {quadrant}, compacted in numpy, K = 1"] = (
                    _CompactedLifter(session, qcomp, qlut.index.shape[2:]), feats)
    times: dict[tuple[str, str], list[float]] = {}
    everything = [(case, g, s, f[g]) for case, sessions, f, _ in cases for g, s in sessions.items()]
    everything += [("lifter", g, s, f) for g, (s, f) in lifter.items()]
    for _, _, s, f in everything:  # warm-up: first runs allocate
        s.run(None, f)
    for _ in range(rounds):
        for case, g, s, f in everything:
            t0 = time.perf_counter()
            s.run(None, f)
            times.setdefault((case, g), []).append((time.perf_counter() - t0) * 1e3)
    lines = [f"{rounds} interleaved rounds, {threads} intra-op thread(s); ms: median p95 min"]
    for case, _, _, note in cases:
        lines.append(f"{case}: {note}")
        base = np.median(times[(case, "slots")])
        for g in ("slots", "compact", "slots_int8", "compact_int8"):
            t = times[(case, g)]
            lines.append(f"  {g:<14}{_stats(t)}   x{base / np.median(t):.2f} vs slots")
    for g in lifter:
        lines.append(f"{g}: {_stats(times[('lifter', g)])}")
    return lines


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Export directory (lut.npz, manifest.json, and the lifter graphs for scale).")
@click.option("--rounds", type=click.IntRange(min=3), default=30, show_default=True, help="Timed runs of every graph.")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True, help="Intra-op threads per session.")
@click.option("--quadrant", type=click.IntRange(0, 3), default=0, show_default=True, help="The quadrant timed alone.")
def main(export_dir: Path, rounds: int, threads: int, quadrant: int) -> None:
    """Time the lifter's gather as K slots, as valid pairs, and both over an int8 table."""
    if not (export_dir / "lut.npz").is_file():
        raise click.ClickException(f"{export_dir} holds no lut.npz: pass an export directory (streamdet-export --out)")
    for line in run(export_dir, rounds, threads, quadrant):
        click.echo(line)


if __name__ == "__main__":
    main()
