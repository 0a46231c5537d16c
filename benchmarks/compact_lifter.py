"""Would the compacted LUT pay inside the lifter graph? The export's lifter in both gather forms, per quadrant.

``python -m streamdet.benchmarks.compact_lifter --export-dir DIR [--checkpoint F] [--rounds 30] [--threads 1]``
exports the detector's lifter (``to_export_form``: the folded lifter of the shipped presets) twice, fp32 (and with
``--int8`` quantized as the export quantizes its lifter), with the export's opset and names: as exported today (K-slot LUT with sentinels) and as ``CompactLifter``
(models/compact_lifter.py: the valid (voxel, camera) pairs, ``calibration/compact_lut.py``), and times both on
every quadrant of the export's LUT (each quadrant's own rows and the feature maps of the cameras that see it, what
the phase-locked lane lifts), taking turns within every round. With ``--compact-export`` (an export of the same
weights in the default ``--lut-layout compact``, ``--export-dir`` one made with ``--lut-layout slots``) it times the two exports' own lifter graphs, fp32 and int8, instead. The outputs are compared first. The features come
from the export's encoder on the bundled sample's images. Results: docs/replay.md ("Less work per lift").
"""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np
import torch

from streamdet.benchmarks.image_half import _lift_feeds, _stats
from streamdet.benchmarks.timing import ort_session
from streamdet.calibration.compact_lut import lifter_feeds
from streamdet.core.lut_layout import LUT_COMPACT, LUT_SLOTS
from streamdet.core.sectors import NUM_QUADRANTS
from streamdet.export.onnx_export import GRAPH_IO, GraphIO, export_module
from streamdet.export.weights import bundled_checkpoint, load_detector
from streamdet.models.compact_lifter import CompactLifter
from streamdet.models.export_form import to_export_form
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.manifest import graph_file_name, read_manifest

COMPACT_IO = GraphIO(
    name="volumetric_lifter",
    inputs=("features", "multi_index", "multi_weight", "final_index", "final_weight"),
    outputs=("image_bev",),
    dynamic_axes={"features": {0: "J", 2: "Hf", 3: "Wf"}, "multi_index": {0: "K", 1: "M"}, "multi_weight": {0: "K", 1: "M"},
                  "final_index": {0: "Q"}, "final_weight": {0: "Q"}, "image_bev": {0: "Q"}},
)  # fmt: skip


def _compact_feeds(feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The K-slot lifter ``feeds`` with their LUT compacted (the runtime's own conversion)."""
    return lifter_feeds(feeds["features"], feeds["lut_index"], feeds["lut_weight"], LUT_COMPACT)


def run(export_dir: Path, checkpoint: Path | None, rounds: int, threads: int, int8: bool = False,
        compact_export: Path | None = None) -> list[str]:  # fmt: skip
    manifest = read_manifest(export_dir)
    if compact_export is not None:  # the pair timed: a K-slot export against a compact one
        layouts = (manifest.lut_layout, read_manifest(compact_export).lut_layout)
        if layouts != (LUT_SLOTS, LUT_COMPACT):
            raise ValueError(f"--export-dir must hold a {LUT_SLOTS!r} export (streamdet-export --lut-layout slots) and "
                             f"--compact-export a {LUT_COMPACT!r} one, got lut_layout {layouts[0]!r} and {layouts[1]!r}")
    slots = _lift_feeds(export_dir, threads, compact=False)
    compact = [_compact_feeds(f) for f in slots]
    if compact_export is not None:  # the two exports' own graphs (the int8 ones calibrated by the export)
        precisions = [p for p in ("fp32", "int8") if p in manifest.precisions and p in read_manifest(compact_export).precisions]
        sessions, feeds = {}, {}
        for p in precisions:
            suffix = "" if p == "fp32" else f"_{p}"
            sessions["slots" + suffix] = ort_session(export_dir / graph_file_name("volumetric_lifter", p), threads)
            sessions["compact" + suffix] = ort_session(compact_export / graph_file_name("volumetric_lifter", p), threads)
            feeds.update({"slots" + suffix: slots, "compact" + suffix: compact})
        return _timed(sessions, feeds, slots, compact, rounds, threads)
    preset = get_preset(manifest.preset_name)
    det, _ = load_detector(preset, checkpoint or bundled_checkpoint(preset.name))
    lifter = to_export_form(det).volumetric_lifter
    with torch.no_grad():
        t = lambda a: torch.from_numpy(a)  # noqa: E731
        slots_model = export_module(lifter, tuple(t(slots[0][n]) for n in GRAPH_IO["volumetric_lifter"].inputs), GRAPH_IO["volumetric_lifter"])
        compact_model = export_module(CompactLifter(lifter).eval(), tuple(t(compact[0][n]) for n in COMPACT_IO.inputs), COMPACT_IO)
    sessions = {"slots": _session_of(slots_model, threads), "compact": _session_of(compact_model, threads)}
    feeds = {"slots": slots, "compact": compact}
    if int8:  # both quantized as the export quantizes its lifter (float gather), calibrated on the four quadrants
        sessions["slots_int8"] = _session_of(slots_model, threads, slots)
        sessions["compact_int8"] = _session_of(compact_model, threads, compact)
        feeds.update(slots_int8=slots, compact_int8=compact)
    return _timed(sessions, feeds, slots, compact, rounds, threads)


def _timed(sessions: dict, feeds: dict, slots: list, compact: list, rounds: int, threads: int) -> list[str]:
    """Parity of the fp32 pair, then every session on every quadrant, taking turns within every round."""
    worst = max(float(np.abs(sessions["slots"].run(None, a)[0] - sessions["compact"].run(None, b)[0]).max()) for a, b in zip(slots, compact))
    multi = [c["multi_index"].shape[1] for c in compact]
    lines = [f"parity: {NUM_QUADRANTS} quadrants, max |diff| {worst:.3g}; voxels seen by 2+ cameras per quadrant {multi}"]
    times: dict[str, list[float]] = {k: [] for k in sessions}
    names = list(sessions)
    for r in range(rounds):
        for key in names if r % 2 == 0 else names[::-1]:
            for f in feeds[key]:
                t0 = time.perf_counter()
                sessions[key].run(None, f)
                times[key].append((time.perf_counter() - t0) * 1e3)
    lines.append(f"{'lifter':<18} {'median':>8} {'p95':>8} {'min':>8} {'p95/med':>6}  ms per quadrant lift ({rounds} rounds, {threads} thread(s))")
    for key in sessions:
        lines.append(f"{key:<18} {_stats(times[key])}")
    return lines


def _session_of(model, threads: int, calibration: list | None = None):
    """A session of ``model``, or of its int8 version calibrated on ``calibration`` feeds (export/int8_quantize.py)."""
    import tempfile

    import onnx

    from streamdet.export.int8_quantize import quantize_graph

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lifter.onnx"
        onnx.save_model(model, str(path))
        if calibration is not None:
            quantize_graph("volumetric_lifter", path, Path(tmp) / "lifter.int8.onnx", calibration)
            path = Path(tmp) / "lifter.int8.onnx"
        return ort_session(path, threads)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--export-dir", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True,
              help="A fused export (its manifest names the preset; its LUT and encoder give the inputs); with "
                   "--compact-export, one made with --lut-layout slots.")
@click.option("--checkpoint", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Weights of the lifter exported here (default: the preset's bundled checkpoint, else seeded weights).")
@click.option("--rounds", type=click.IntRange(min=3), default=30, show_default=True, help="Timed rounds (every quadrant).")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True, help="Intra-op threads per session.")
@click.option("--int8", is_flag=True, help="Also both graphs quantized as the export quantizes its lifter (calibrated on the quadrants timed).")
@click.option("--compact-export", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="An export of the same weights with --lut-layout compact: time the two exports' own lifter graphs "
                   "(every precision both hold) instead of exporting them here.")
def main(export_dir: Path, checkpoint: Path | None, rounds: int, threads: int, int8: bool, compact_export: Path | None) -> None:
    """Time the lifter graph on the K-slot LUT and on the compacted LUT, per quadrant, taking turns."""
    try:
        lines = run(export_dir, checkpoint, rounds, threads, int8, compact_export)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    for line in lines:
        click.echo(line)


if __name__ == "__main__":
    main()
