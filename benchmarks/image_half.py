"""Does the image_half layout pay? Per-quadrant lift and per-slice time of two exports of the same weights.

``python -m streamdet.benchmarks.image_half --old DIR --new DIR [--rounds 40] [--threads 1]`` takes an export in
the ``image_bev`` layout and one in the ``image_half`` layout (models/image_half.py; ``streamdet-export
--image-layout``) and times, with onnxruntime sessions of ``--threads`` intra-op threads:

- the lifter graph on one quadrant (its own LUT rows and the feature maps of the cameras that see it, as the
  phase-locked image lane lifts), every quadrant in turn, in each precision both exports hold (fp32, int8);
- the slice graph on every slice of the bundled sample's sweep (``--slices``), fed the lifter's map of its
  quadrants.

The graphs of both layouts take turns within every round (the order alternates), so a busy machine slows them
alike; medians, p95, min and the p95/median spread are printed per graph, with the lift + slices per rotation at
nuScenes rates. The features are the old export's encoder run on the bundled sample's images (the lift's time
does not depend on them much, its parity does): before timing, the detections of every slice are compared between
the layouts. Results: docs/replay.md ("Less work per lift").
"""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from streamdet.calibration.compact_lut import lifter_lut_feeds
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut
from streamdet.calibration.quadrant_lut import quadrant_lut
from streamdet.core.image_layout import IMAGE_BEV, IMAGE_HALF
from streamdet.core.lut_layout import LUT_COMPACT
from streamdet.core.sectors import NUM_QUADRANTS, quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.manifest import graph_file_name, read_manifest
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.benchmarks.timing import ort_session



def _stats(ms: list[float]) -> str:
    a = np.asarray(ms)
    med = float(np.median(a))
    return f"{med:8.2f} {np.percentile(a, 95):8.2f} {a.min():8.2f} {np.percentile(a, 95) / med:6.2f}"


def _lift_feeds(export_dir: Path, threads: int, compact: bool | None = None) -> list[dict[str, np.ndarray]]:
    """Per quadrant: the lifter feeds of the cameras that see it (features from the export's fp32 encoder), the
    LUT compacted or not (None: as the export's lut_layout says)."""
    manifest = read_manifest(export_dir)
    img = manifest.image
    sample = load_bundled_sample()
    images = sample.load_images((img.width, img.height))  # (J, H, W, 3)
    order = [sample.rig.names.index(n) for n in img.camera_names]
    enc = ort_session(export_dir / graph_file_name("image_encoder", "fp32"), threads)
    (features,) = enc.run(None, {"images": images[order]})  # (J, C, Hf, Wf)
    lut = Lut.load(export_dir / "lut.npz")
    feeds = []
    for q in range(NUM_QUADRANTS):
        qlut = quadrant_lut(lut, q)
        maps = features[list(qlut.camera_indices)] if qlut.camera_indices else features[:1] * 0
        if compact is None:
            compact = manifest.lut_layout == LUT_COMPACT
        j, _, hf, wf = maps.shape
        feeds.append({"features": np.ascontiguousarray(maps), **lifter_lut_feeds(qlut.index, qlut.weight, j * hf * wf, compact)})
    return feeds


def _slice_feeds(export_dir: Path, name: str, maps: list[np.ndarray], num_slices: int) -> list[dict[str, np.ndarray]]:
    """Per slice of the bundled sweep with pillars: the slice graph's feeds, ``name`` the lifter's map of its quadrants."""
    manifest = read_manifest(export_dir)
    grid = GridSpec.from_dict(manifest.grid)
    m = int(manifest.preset["pillars"]["max_points_per_pillar"])
    p = int(manifest.preset["pillars"]["max_pillars"])
    sweep = load_bundled_sample().points
    feeds = []
    for k, pts in enumerate(split_sweep(sweep, num_slices)):
        quads = quadrants_of_sector(k, num_slices, 0.0)
        pl = pillarize(pts.astype(np.float32), grid, quads, m, p)
        if pl.num_pillars:
            feeds.append({**pl.as_feeds(), name: np.concatenate([maps[q] for q in quads])})
    return feeds


def _score_error(session, feeds32: list, feeds8: list) -> str:
    """Relative L2 error of the slice graph's scores fed the int8 lifter's maps against fed the fp32 lifter's."""
    s32 = np.concatenate([session.run(None, f)[1].ravel() for f in feeds32])
    s8 = np.concatenate([session.run(None, f)[1].ravel() for f in feeds8])
    rel = np.linalg.norm(s8 - s32) / max(np.linalg.norm(s32), 1e-12)
    return f"scores relative L2 error {rel:.4f}, max |diff| {np.abs(s8 - s32).max():.3g}"


def run(old_dir: Path, new_dir: Path, rounds: int, threads: int, num_slices: int) -> list[str]:
    old_m, new_m = read_manifest(old_dir), read_manifest(new_dir)
    if (old_m.image_layout, new_m.image_layout) != (IMAGE_BEV, IMAGE_HALF):
        raise click.ClickException(
            f"--old must be an image_bev export and --new an image_half one, got {old_m.image_layout} and {new_m.image_layout}"
        )
    lift_feeds = _lift_feeds(old_dir, threads)
    precisions = [p for p in ("fp32", "int8") if p in old_m.precisions and p in new_m.precisions]
    sessions, feeds = {}, {}
    lines = []
    for layout, d in (("old", old_dir), ("new", new_dir)):
        for prec in precisions:
            sessions[f"lift_{prec}_{layout}"] = ort_session(d / graph_file_name("volumetric_lifter", prec), threads)
            feeds[f"lift_{prec}_{layout}"] = lift_feeds
        lifter = ort_session(d / graph_file_name("volumetric_lifter", "fp32"), threads)
        maps = [lifter.run(None, f)[0] for f in lift_feeds]  # each (1, C, H, W)
        name = IMAGE_BEV if layout == "old" else IMAGE_HALF
        sessions[f"slice_fp32_{layout}"] = ort_session(d / graph_file_name("slice_head", "fp32"), threads)
        feeds[f"slice_fp32_{layout}"] = _slice_feeds(d, name, maps, num_slices)
        if "int8" in precisions:  # the mixed lanes (int8 image lane, fp32 slices): what int8 lifts cost the scores
            maps8 = [sessions[f"lift_int8_{layout}"].run(None, f)[0] for f in lift_feeds]
            lines.append(f"{layout} layout, fp32 slices on int8 lifts: {_score_error(sessions[f'slice_fp32_{layout}'], feeds[f'slice_fp32_{layout}'], _slice_feeds(d, name, maps8, num_slices))}")
    # parity first: the same detections from both layouts on every slice
    worst = 0.0
    for fo, fn in zip(feeds["slice_fp32_old"], feeds["slice_fp32_new"]):
        bo, so, lo = sessions["slice_fp32_old"].run(None, fo)
        bn, sn, ln = sessions["slice_fp32_new"].run(None, fn)
        keep = so > 0.1
        worst = max(worst, float(np.abs(sn - so).max()), float(np.abs(bn[keep] - bo[keep]).max(initial=0.0)))
        if not np.array_equal(lo[keep], ln[keep]):
            lines.append("WARNING: a slice's labels above score 0.1 differ between the layouts")
    lines.append(f"parity: {len(feeds['slice_fp32_old'])} slices, max |diff| of scores and boxes (score > 0.1) {worst:.3g}")
    times: dict[str, list[float]] = {k: [] for k in sessions}
    names = list(sessions)
    for r in range(rounds):
        for key in names if r % 2 == 0 else names[::-1]:
            for f in feeds[key]:  # every quadrant / every slice, one after the other
                t = time.perf_counter()
                sessions[key].run(None, f)
                times[key].append((time.perf_counter() - t) * 1e3)
    lines.append(f"{'graph':<18} {'median':>8} {'p95':>8} {'min':>8} {'p95/med':>6}  ms ({rounds} rounds, {threads} thread(s))")
    for key in names:
        what = "per quadrant lift" if key.startswith("lift") else "per slice"
        lines.append(f"{key:<18} {_stats(times[key])}  {what}")
    return lines


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--old", "old_dir", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True,
              help="Export in the image_bev layout (streamdet-export --image-layout image_bev).")
@click.option("--new", "new_dir", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True,
              help="Export of the same weights in the image_half layout.")
@click.option("--rounds", type=click.IntRange(min=3), default=40, show_default=True, help="Timed rounds (every graph, every input).")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True, help="Intra-op threads per session.")
@click.option("--slices", "num_slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices of the bundled sweep.")
def main(old_dir: Path, new_dir: Path, rounds: int, threads: int, num_slices: int) -> None:
    """Time the lifter per quadrant and the slice graph per slice in both image layouts, taking turns."""
    for line in run(old_dir, new_dir, rounds, threads, num_slices):
        click.echo(line)


if __name__ == "__main__":
    main()
