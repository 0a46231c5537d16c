"""The slice graphs of two or more exports side by side: per-slice time, taking turns, parity first.

``python -m streamdet.benchmarks.slice_graphs DIR DIR [...] [--rounds 30] [--threads 1] [--slices 8]`` times the
slice graph of each export (every precision all of them hold: fp32, fp16, int8) on every slice of the bundled
nuScenes sweep that has pillars, each fed its quadrants' image BEV from the first export's fp32 lifter (the same
maps for all; the exports must share the image layout and the map size). Meant for exports of the same weights
that differ in an export-time rewrite (e.g. before and after one, ``models/export_form.py``) or in the runtime
version that wrote them.

Before timing, every export's detections are compared with the first's on every slice (boxes paired by label and
centre, as the export's int8 check pairs them), so a speed-up that changed the function shows. The graphs
take turns within every round (the order alternates), so a machine's fast and slow states slow them alike; per
graph the median, p95, min and p95/median spread of the per-slice times, and the median over rounds of each
round's median ratio to the first export. Results: benchmarks/RESULTS.md.
"""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from streamdet.benchmarks.image_half import _lift_feeds, _slice_feeds, _stats
from streamdet.benchmarks.timing import ort_session
from streamdet.export.int8_parity import box_agreement
from streamdet.models.presets import Preset
from streamdet.runtime_ort.manifest import graph_file_name, read_manifest

def _check_alike(dirs: list[Path]) -> list[str]:
    """The precisions every export holds; refuses exports whose slice graphs take different inputs."""
    manifests = [read_manifest(d) for d in dirs]
    first = manifests[0]
    for d, m in zip(dirs[1:], manifests[1:]):
        if m.image_layout != first.image_layout or m.grid != first.grid or m.image is None or first.image is None:
            raise click.ClickException(
                f"{d}: its slice graph takes other inputs than {dirs[0]}'s (image layout {m.image_layout} vs "
                f"{first.image_layout}, or another grid, or a LiDAR-only export)"
            )
    precisions = [p for p in ("fp32", "fp16", "int8") if all(p in m.precisions for m in manifests)]
    if not precisions:
        raise click.ClickException("the exports share no precision of the slice graph")
    return precisions


def parity(reference, other, feeds: list[dict[str, np.ndarray]], cell_m: float) -> str:
    """The boxes of ``other`` against ``reference`` on every feed, paired as the export's int8 check pairs them
    (same label, centres within two head cells, score >= 0.1: export/int8_parity.py), so graphs whose scores differ
    by a rounding (int8 graphs calibrated apart) compare by what they detect, not by their top-K order."""
    got = box_agreement([reference.run(None, f) for f in feeds], [other.run(None, f) for f in feeds], cell_m)
    return (f"{got.count_fp32} / {got.count_int8} boxes, {got.matched} paired, centre diff mean {got.mean_centre_diff_m:.3g} "
            f"max {got.max_centre_diff_m:.3g} m, max score diff {got.max_score_diff:.3g}")


def run(dirs: list[Path], rounds: int, threads: int, num_slices: int) -> list[str]:
    precisions = _check_alike(dirs)
    lifter = ort_session(dirs[0] / graph_file_name("volumetric_lifter", "fp32"), threads)
    maps = [lifter.run(None, f)[0] for f in _lift_feeds(dirs[0], threads)]  # each (1, C, Yq, Xq)
    feeds = _slice_feeds(dirs[0], read_manifest(dirs[0]).image_layout, maps, num_slices)
    if not feeds:
        raise click.ClickException("no slice of the bundled sweep has pillars")
    sessions = {(p, i): ort_session(d / graph_file_name("slice_head", p), threads) for p in precisions for i, d in enumerate(dirs)}
    lines = []
    cell_m = Preset.from_dict(read_manifest(dirs[0]).preset).head_cell_m
    for p in precisions:
        for i in range(1, len(dirs)):
            agreement = parity(sessions[(p, 0)], sessions[(p, i)], feeds, cell_m)
            lines.append(f"parity {p}, {dirs[i].name} against {dirs[0].name}, {len(feeds)} slices: {agreement}")
    keys = list(sessions)
    times: dict[tuple[str, int], list[float]] = {k: [] for k in keys}
    round_medians: dict[tuple[str, int], list[float]] = {k: [] for k in keys}
    for r in range(rounds):
        for key in keys if r % 2 == 0 else keys[::-1]:
            this_round = []
            for f in feeds:  # every slice, one after the other
                t = time.perf_counter()
                sessions[key].run(None, f)
                this_round.append((time.perf_counter() - t) * 1e3)
            times[key] += this_round
            round_medians[key].append(float(np.median(this_round)))
    lines.append(f"{'export':<32} {'prec':<5} {'median':>8} {'p95':>8} {'min':>8} {'p95/med':>6}  ms per slice  ratio to the first [min, max over rounds]")
    for p, i in keys:
        ratio = np.asarray(round_medians[(p, i)]) / np.asarray(round_medians[(p, 0)])
        lines.append(
            f"{dirs[i].name:<32} {p:<5} {_stats(times[(p, i)])}  {np.median(ratio):.3f} [{ratio.min():.3f}, {ratio.max():.3f}]"
        )
    lines.append(f"({rounds} rounds of {len(feeds)} slices, {threads} intra-op thread(s), taking turns)")
    return lines


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("export_dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--rounds", type=click.IntRange(min=3), default=30, show_default=True, help="Timed rounds (every graph, every slice).")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True, help="Intra-op threads per session.")
@click.option("--slices", "num_slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices of the bundled sweep.")
def main(export_dirs: tuple[Path, ...], rounds: int, threads: int, num_slices: int) -> None:
    """Time the slice graphs of EXPORT_DIRS (two or more fused exports) per slice, taking turns; the first is the reference."""
    if len(export_dirs) < 2:
        raise click.UsageError("give two or more export directories")
    for line in run(list(export_dirs), rounds, threads, num_slices):
        click.echo(line)


if __name__ == "__main__":
    main()
