"""Does a per-camera lift pay? One camera's share of a quadrant lift, against the whole quadrant lift.

``python -m streamdet.benchmarks.partial_lift --export-dir DIR [--rounds 25] [--threads 1] [--json FILE]``

The phase-locked image lane (issue 22) lifts a quadrant again whenever one of its cameras sends a new frame, and each
lift gathers every camera's slots (K per voxel, most of them sentinels). The flat lifter's gather and its first
layer (a 1x1 convolution) are linear, so the quadrant's pre-activation map is a sum of one term per camera
(``calibration/camera_lut.py``): a new frame of one camera needs only that camera's term again. This benchmark
runs the runtime's pieces (``runtime_ort/camera_terms.py``, cut from the export's fp32 lifter by
``runtime_ort/lifter_split.py``; nothing of the export is changed):

- ``partial``: the camera's (C, Hf, Wf) feature map times the first convolution's weight blocks (its projected
  table), then its share of the quadrant's LUT gathered from it and summed over the slots (no bias): (N, C),
  ``lifter_split.term_graph``;
- ``combine`` (numpy): the quadrant's cameras' terms and cells concatenated (the tail's feeds);
- ``tail``: the terms scattered into the quadrant's cells and added to the bias, then the rest of the export's own
  lifter graph, cut after its first convolution;

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

from streamdet.benchmarks.timing import ort_session
from streamdet.calibration.compact_lut import lifter_feeds
from streamdet.calibration.lut import Lut
from streamdet.calibration.quadrant_lut import quadrant_luts
from streamdet.runtime_ort.camera_terms import CameraTerms
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.sessions import SessionConfig


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
    """One quadrant's per-camera lift: its camera shares and their newest terms (``CameraTerms`` runs the pieces)."""

    def __init__(self, terms: CameraTerms, qlut) -> None:
        self.pieces, self.qlut = terms, qlut
        self.shares = terms.shares(qlut)
        self.terms: dict[str, np.ndarray] = {}

    def partial(self, name: str, features: dict[str, np.ndarray]) -> None:
        share = next(s for s in self.shares if s.share.camera_name == name)
        self.terms[name] = self.pieces.term(features[name], share)

    def combine(self) -> dict[str, np.ndarray]:
        return self.pieces.tail_feeds(self.shares, self.terms)

    def lift(self, feeds: dict[str, np.ndarray]) -> np.ndarray:
        return self.pieces.tail(feeds)


def run(export_dir: Path, rounds: int, threads: int) -> dict:
    manifest = read_manifest(export_dir)
    if manifest.preset.get("use_image", True) is False or not (export_dir / "volumetric_lifter.onnx").is_file():
        raise ValueError(f"{export_dir} is a LiDAR-only export: there is no lifter to split")
    lifter = onnx.load(str(export_dir / "volumetric_lifter.onnx"))
    lut = Lut.load(export_dir / "lut.npz")
    channels = int(manifest.preset["channels"])
    hw = (lut.feature_height, lut.feature_width)
    features = _features(export_dir)
    yq, xq = lut.index.shape[3:]
    cfg = SessionConfig(("CPUExecutionProvider",), threads)
    pieces = CameraTerms(lifter, lifter, channels, hw, (yq, xq), int(lut.index.shape[2]), cfg)  # SplitError (a ValueError) if it cannot split
    lift32 = ort_session(export_dir / "volumetric_lifter.onnx", threads)
    int8_path = export_dir / "volumetric_lifter.int8.onnx"
    lift8 = ort_session(int8_path, threads) if int8_path.is_file() else None
    quadrants, feeds, parity = [], [], []
    for qlut in quadrant_luts(lut):
        if not qlut.camera_names:  # a quadrant no camera sees has nothing to lift (the runtime clears it)
            parity.append({"quadrant": qlut.quadrant, "max_abs_diff": None, "output_range": None})
            continue
        quad = _Quadrant(pieces, qlut)
        maps = np.stack([features[n] for n in qlut.camera_names])  # (J', C, Hf, Wf)
        feed = lifter_feeds(maps, qlut.index, qlut.weight, manifest.lut_layout)
        (ref,) = lift32.run(None, feed)
        for s in quad.shares:
            quad.partial(s.share.camera_name, features)
        got = quad.lift(quad.combine())
        parity.append({"quadrant": qlut.quadrant, "max_abs_diff": float(np.abs(got - ref).max()),
                       "output_range": float(np.ptp(ref))})  # fmt: skip
        quadrants.append(quad)
        feeds.append(feed)
    jobs = []  # (label, callable), interleaved every round
    for quad, feed in zip(quadrants, feeds):
        q = quad.qlut.quadrant
        jobs.append((f"q{q} lift fp32", lambda f=feed: lift32.run(None, f)))
        if lift8 is not None:
            jobs.append((f"q{q} lift int8", lambda f=feed: lift8.run(None, f)))
        for s in quad.shares:
            jobs.append((f"q{q} {s.share.camera_name} partial", lambda qd=quad, n=s.share.camera_name: qd.partial(n, features)))
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
    for quad in quadrants:
        q = quad.qlut.quadrant
        rest = stats[f"q{q} combine"]["median"] + stats[f"q{q} tail"]["median"]
        for s in quad.shares:
            share = s.share
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
        if p["max_abs_diff"] is None:
            lines.append(f"quadrant {p['quadrant']}: no camera sees it, nothing to lift")
            continue
        lines.append(f"quadrant {p['quadrant']}: per-camera sum vs the export's lifter max |diff| {p['max_abs_diff']:.2e} "
                     f"(output range {p['output_range']:.2f})")  # fmt: skip
    lines.append("| quadrant | camera | cells | one camera's update (partial + combine + tail) | quadrant lift fp32 | int8 |")
    lines.append("|---|---|---|---|---|---|")
    for r in result["per_camera_update"]:
        int8 = "-" if r["lift_int8_ms"] is None else f"{r['lift_int8_ms']:.2f}"
        lines.append(f"| {r['quadrant']} | {r['camera']} | {r['cells']} | {r['update_ms']:.2f} | {r['lift_fp32_ms']:.2f} | {int8} |")
    t = result["times_ms"]
    for q in (p["quadrant"] for p in result["parity"] if p["max_abs_diff"] is not None):
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
