"""Does a per-camera lift pay? One camera's share of a quadrant lift, against the whole quadrant lift.

``python -m streamdet.benchmarks.partial_lift --export-dir DIR [--rounds 25] [--threads 1] [--json FILE]``

The phase-locked image lane (issue 22) lifts a quadrant again whenever one of its cameras sends a new frame, and each
lift gathers every camera's slots (K per voxel, most of them sentinels). The flat lifter's gather and its first
layer (a 1x1 convolution) are linear, so the quadrant's pre-activation map is a sum of one term per camera
(``calibration/camera_lut.py``): a new frame of one camera needs only that camera's term again. This benchmark
builds, from an export with the flat lifter (fp32 graphs; nothing of the export is changed):

- ``partial`` (one graph per camera and quadrant, its share of the LUT as constants): the camera's (C, Hf, Wf)
  feature map -> its rows -> weighted sum over its slots -> the first convolution's weights (no bias): (N, C);
- ``combine`` (numpy): the quadrant's cameras' terms scattered into (Yq * Xq, C) and the bias added;
- ``tail``: the rest of the export's own lifter graph, cut after its first convolution (``onnx.utils.Extractor``),
  fed the sum (a Transpose in front takes it cells-major);

checks that ``tail(combine(partials))`` is the export's lifter output on every quadrant (max |diff|, real feature
maps of the bundled nuScenes images), and times, in interleaved rounds, the export's quadrant lift (fp32, and the
int8 graph where the export has one) against one camera's update (``partial`` of that camera + ``combine`` +
``tail``), for every (quadrant, camera). Results: docs/replay.md, "Per-camera partial lifts".
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from streamdet.calibration.camera_lut import CameraLut, camera_luts
from streamdet.calibration.quadrant_lut import quadrant_luts
from streamdet.calibration.lut import Lut
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.benchmarks.timing import ort_session

OPSET = 17


def first_conv(model: onnx.ModelProto) -> tuple[onnx.NodeProto, np.ndarray, np.ndarray]:
    """The lifter graph's first Conv (the flat lifter's 1x1 over the z-stacked channels) and its weight, bias."""
    inits = {t.name: t for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Conv":
            if len(node.input) < 3 or node.input[1] not in inits or node.input[2] not in inits:
                raise ValueError(f"the lifter's first Conv {node.name!r} has no constant weight and bias")
            weight = numpy_helper.to_array(inits[node.input[1]])
            if weight.shape[2:] != (1, 1):
                raise ValueError(f"the lifter's first Conv is {weight.shape[2]}x{weight.shape[3]}, not 1x1: "
                                 "a per-camera lift needs the flat lifter (LifterConfig.form='flat')")  # fmt: skip
            return node, weight[:, :, 0, 0], numpy_helper.to_array(inits[node.input[2]])
    raise ValueError("the lifter graph has no Conv")


def partial_graph(share: CameraLut, weight: np.ndarray, channels: int, feature_hw: tuple[int, int]) -> onnx.ModelProto:
    """features (1, C, Hf, Wf) -> (N, C_out): ``gather_share`` then ``@ weight.T`` (weight (C_out, Z * C))."""
    hf, wf = feature_hw
    n, z, s = share.index.shape
    c = lambda name, value: numpy_helper.from_array(np.ascontiguousarray(value), name)  # noqa: E731
    inits = [
        c("flat", np.array([channels, hf * wf], np.int64)), c("zero_row", np.zeros((1, channels), np.float32)),
        c("idx", share.index.reshape(-1)), c("w", share.weight[..., None]), c("nzs", np.array([n, z, s, channels], np.int64)),
        c("axis2", np.array([2], np.int64)), c("nzc", np.array([n, z * channels], np.int64)), c("wt", weight.T.astype(np.float32)),
    ]  # fmt: skip
    nodes = [
        helper.make_node("Reshape", ["features", "flat"], ["cf"]),  # (C, Hf*Wf)
        helper.make_node("Transpose", ["cf"], ["rows"], perm=[1, 0]),  # (Hf*Wf, C)
        helper.make_node("Concat", ["rows", "zero_row"], ["table"], axis=0),  # (Hf*Wf + 1, C)
        helper.make_node("Gather", ["table", "idx"], ["g"], axis=0),  # (N*Z*S, C)
        helper.make_node("Reshape", ["g", "nzs"], ["g4"]),  # (N, Z, S, C)
        helper.make_node("Mul", ["g4", "w"], ["wg"]),
        helper.make_node("ReduceSum", ["wg", "axis2"], ["zc"], keepdims=0),  # (N, Z, C)
        helper.make_node("Reshape", ["zc", "nzc"], ["v"]),  # (N, Z*C): channel z * C + c
        helper.make_node("MatMul", ["v", "wt"], ["partial"]),  # (N, C_out)
    ]
    graph = helper.make_graph(
        nodes, "partial_lift", [helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, channels, hf, wf])],
        [helper.make_tensor_value_info("partial", TensorProto.FLOAT, [n, weight.shape[0]])], inits,
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    onnx.checker.check_model(model)
    return model


def tail_graph(lifter: onnx.ModelProto, cut: str, shape: tuple[int, int, int]) -> onnx.ModelProto:
    """The lifter graph from tensor ``cut`` (the first Conv's output) on, fed cells-major (1, Yq * Xq, C)."""
    from onnx.utils import Extractor

    outputs = [o.name for o in lifter.graph.output]
    lifter = onnx.shape_inference.infer_shapes(lifter)
    if cut not in {v.name for v in lifter.graph.value_info}:  # the Extractor needs the cut tensor's type
        lifter.graph.value_info.append(helper.make_tensor_value_info(cut, TensorProto.FLOAT, None))
    tail = Extractor(lifter).extract_model([cut], outputs)
    c, yq, xq = shape
    inits = [numpy_helper.from_array(np.array([1, yq, xq, c], np.int64), "tail_shape")]
    head = [
        helper.make_node("Reshape", ["summed", "tail_shape"], ["summed4"]),  # (1, Yq, Xq, C)
        helper.make_node("Transpose", ["summed4"], [cut], perm=[0, 3, 1, 2]),  # (1, C, Yq, Xq)
    ]
    graph = helper.make_graph(
        head + list(tail.graph.node), "lifter_tail",
        [helper.make_tensor_value_info("summed", TensorProto.FLOAT, [1, yq * xq, c])], list(tail.graph.output),
        inits + list(tail.graph.initializer),
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=list(lifter.opset_import))
    onnx.checker.check_model(model)
    return model




def _features(export_dir: Path) -> dict[str, np.ndarray]:
    """(C, Hf, Wf) feature maps of the bundled nuScenes images, by camera, from the export's fp32 encoder."""
    from streamdet.data.sample import load_bundled_sample
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(export_dir)
    sample = load_bundled_sample()
    img = det.image
    images = sample.load_images((img.width, img.height))  # (J, H, W, 3) in rig order
    return det.encode_images({n: images[j] for j, n in enumerate(sample.rig.names) if n in det.camera_names})


class _Quadrant:
    """One quadrant's per-camera lift: its partial sessions, bias, tail session and the cells of each camera."""

    def __init__(self, shares, partials, bias: np.ndarray, tail, cells: int) -> None:
        self.shares, self.partials, self.bias, self.tail, self.cells = shares, partials, bias, tail, cells
        self.terms: dict[str, np.ndarray] = {}

    def partial(self, name: str, features: dict[str, np.ndarray]) -> None:
        (self.terms[name],) = self.partials[name].run(None, {"features": features[name][None]})

    def combine(self) -> np.ndarray:
        summed = np.broadcast_to(self.bias, (self.cells, self.bias.size)).copy()  # (Yq*Xq, C)
        for share in self.shares:
            summed[share.cells] += self.terms[share.camera_name]
        return summed[None]  # (1, Yq*Xq, C)

    def lift(self, summed: np.ndarray) -> np.ndarray:
        (out,) = self.tail.run(None, {"summed": summed})
        return out


def run(export_dir: Path, rounds: int, threads: int) -> dict:
    manifest = read_manifest(export_dir)
    if manifest.preset.get("use_image", True) is False or not (export_dir / "volumetric_lifter.onnx").is_file():
        raise ValueError(f"{export_dir} is a LiDAR-only export: there is no lifter to split")
    lifter = onnx.load(str(export_dir / "volumetric_lifter.onnx"))
    conv, weight, bias = first_conv(lifter)
    lut = Lut.load(export_dir / "lut.npz")
    channels = int(manifest.preset["channels"])
    hw = (lut.feature_height, lut.feature_width)
    cells_per_map = hw[0] * hw[1]
    features = _features(export_dir)
    yq, xq = lut.index.shape[3:]
    shape = (weight.shape[0], yq, xq)
    tail = ort_session(tail_graph(lifter, conv.output[0], shape), threads)
    lift32 = ort_session(export_dir / "volumetric_lifter.onnx", threads)
    int8_path = export_dir / "volumetric_lifter.int8.onnx"
    lift8 = ort_session(int8_path, threads) if int8_path.is_file() else None
    quadrants, feeds, parity = [], [], []
    for qlut in quadrant_luts(lut):
        shares = camera_luts(qlut, cells_per_map)
        partials = {s.camera_name: ort_session(partial_graph(s, weight, channels, hw), threads) for s in shares}
        quad = _Quadrant(shares, partials, bias.astype(np.float32), tail, yq * xq)
        maps = np.stack([features[n] for n in qlut.camera_names])  # (J', C, Hf, Wf)
        feed = {"features": maps, "lut_index": qlut.index, "lut_weight": qlut.weight}
        (ref,) = lift32.run(None, feed)
        for name in partials:
            quad.partial(name, features)
        got = quad.lift(quad.combine())
        parity.append({"quadrant": qlut.quadrant, "max_abs_diff": float(np.abs(got - ref).max()),
                       "output_range": float(np.ptp(ref))})  # fmt: skip
        quadrants.append(quad)
        feeds.append(feed)
    jobs = []  # (label, callable), interleaved every round
    for q, (quad, feed) in enumerate(zip(quadrants, feeds)):
        jobs.append((f"q{q} lift fp32", lambda f=feed: lift32.run(None, f)))
        if lift8 is not None:
            jobs.append((f"q{q} lift int8", lambda f=feed: lift8.run(None, f)))
        for share in quad.shares:
            jobs.append((f"q{q} {share.camera_name} partial", lambda qd=quad, n=share.camera_name: qd.partial(n, features)))
        jobs.append((f"q{q} combine", quad.combine))
        summed = quad.combine()
        jobs.append((f"q{q} tail", lambda qd=quad, s=summed: qd.lift(s)))
    for _, job in jobs:  # warm-up
        job()
    times: dict[str, list[float]] = {label: [] for label, _ in jobs}
    for _ in range(rounds):
        for label, job in jobs:
            t0 = time.perf_counter()
            job()
            times[label].append((time.perf_counter() - t0) * 1e3)
    stats = {k: {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "min": float(np.min(v))} for k, v in times.items()}
    per_camera = []
    for q, quad in enumerate(quadrants):
        rest = stats[f"q{q} combine"]["median"] + stats[f"q{q} tail"]["median"]
        for share in quad.shares:
            update = stats[f"q{q} {share.camera_name} partial"]["median"] + rest
            per_camera.append({"quadrant": q, "camera": share.camera_name, "cells": share.num_cells,
                               "slots_per_voxel": int(share.index.shape[2]), "update_ms": update,
                               "lift_fp32_ms": stats[f"q{q} lift fp32"]["median"],
                               "lift_int8_ms": stats[f"q{q} lift int8"]["median"] if lift8 is not None else None})  # fmt: skip
    return {"export_dir": str(export_dir), "rounds": rounds, "threads": threads, "parity": parity, "times_ms": stats,
            "per_camera_update": per_camera, "lut_slots": int(lut.index.shape[1]), "cells_per_quadrant": yq * xq}  # fmt: skip


def report(result: dict) -> list[str]:
    lines = [f"{result['rounds']} interleaved rounds, {result['threads']} intra-op thread(s); LUT K = {result['lut_slots']} "
             f"slots, {result['cells_per_quadrant']} cells per quadrant; ms medians"]  # fmt: skip
    for p in result["parity"]:
        lines.append(f"quadrant {p['quadrant']}: per-camera sum vs the export's lifter max |diff| {p['max_abs_diff']:.2e} "
                     f"(output range {p['output_range']:.2f})")  # fmt: skip
    lines.append("| quadrant | camera | cells | one camera's update (partial + combine + tail) | quadrant lift fp32 | int8 |")
    lines.append("|---|---|---|---|---|---|")
    for r in result["per_camera_update"]:
        int8 = "-" if r["lift_int8_ms"] is None else f"{r['lift_int8_ms']:.2f}"
        lines.append(f"| {r['quadrant']} | {r['camera']} | {r['cells']} | {r['update_ms']:.2f} | {r['lift_fp32_ms']:.2f} | {int8} |")
    t = result["times_ms"]
    for q in range(len(result["parity"])):
        lines.append(f"q{q}: combine {t[f'q{q} combine']['median']:.2f}, tail {t[f'q{q} tail']['median']:.2f} ms")
    return lines


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False, exists=True), required=True,
              help="Export directory of a fused model with the flat lifter (volumetric_lifter.onnx, lut.npz).")
@click.option("--rounds", type=click.IntRange(min=3), default=25, show_default=True, help="Timed runs of every step.")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True, help="Intra-op threads per session.")
@click.option("--json", "json_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Also write every figure here.")
def main(export_dir: Path, rounds: int, threads: int, json_path: Path | None) -> None:
    """Time one camera's share of a quadrant lift against the whole quadrant lift, and check they agree."""
    for name in ("lut.npz", "volumetric_lifter.onnx"):
        if not (export_dir / name).is_file():
            raise click.ClickException(f"{export_dir} holds no {name}: pass the export of a fused model (streamdet-export --out)")
    try:
        result = run(export_dir, rounds, threads)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    for line in report(result):
        click.echo(line)
    if json_path is not None:
        json_path.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
