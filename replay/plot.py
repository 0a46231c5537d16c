"""The replay's picture: a timeline of a few hundred ms of the first scene per mode, and latency CDFs per mode.

Timeline rows, top to bottom: slices released (their last point scanned; a red x where the lane dropped one), the
slice lane's jobs, the image lane's jobs (in sequential mode both are the one queue's jobs), emissions (a grey line
joins each slice's release to its emission, so a growing backlog shows as lines leaning ever further), camera
triggers (an x where the image set was superseded). matplotlib is imported here only (the dev / export extras).
"""

from __future__ import annotations

import math

from pathlib import Path

import numpy as np

from streamdet.replay.record import Recording
from streamdet.replay.run import ReplayResult

ROWS = ("released", "slice jobs", "image jobs", "emitted", "camera")
COLORS = {"streaming": "tab:blue", "full-sweep": "tab:orange", "sequential": "tab:red"}


def timeline_window(result: ReplayResult, width_s: float = 0.4) -> tuple[float, float]:
    """A window of ``width_s`` a second into the first scene (or at its start for a shorter drive)."""
    drive = result.drives[0]
    start = 1.0 if drive.duration_s >= 1.0 + width_s else 0.0
    return start, start + width_s


def plot_replay(result: ReplayResult, path: str | Path, window_s: tuple[float, float] | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    lo, hi = window_s or timeline_window(result)
    modes = list(result.modes)
    fig = plt.figure(figsize=(15, 2.3 * len(modes) + 1.0))
    grid = fig.add_gridspec(len(modes), 3, wspace=0.35, hspace=0.45)
    for i, mode in enumerate(modes):
        ax = fig.add_subplot(grid[i, :2])
        _timeline(ax, result.modes[mode].recordings[0], lo, hi, COLORS.get(mode, "tab:gray"))
        ax.set_title(f"{mode}: {result.scenes[0]}, drive time {lo:.2f}-{hi:.2f} s", fontsize=9, loc="left")
    ax.set_xlabel("drive time (ms)")
    cdf = fig.add_subplot(grid[:, 2])
    period_ms = 1000.0 / result.config.lidar_hz / result.num_slices
    for mode in modes:
        lat = np.sort(np.concatenate([r.latencies_ms() for r in result.modes[mode].recordings]))
        if lat.size:
            cdf.step(lat, np.arange(1, lat.size + 1) / lat.size, where="post", color=COLORS.get(mode), label=mode)
    cdf.axvline(2 * period_ms, color="k", ls="--", lw=0.8, label=f"two slice periods ({2 * period_ms:.1f} ms)")
    cdf.set_xscale("log")
    # plain numbers at 1, 2 and 5 of each decade: matplotlib labels every minor tick of a log axis that spans a decade
    # or two, and in this narrow panel "2x10^1 3x10^1 4x10^1 ..." ran into each other (the other ticks stay unlabelled)
    cdf.xaxis.set_major_formatter(FuncFormatter(_one_two_five))
    cdf.xaxis.set_minor_formatter(FuncFormatter(_one_two_five))
    cdf.set_xlabel("latency: last point scanned to detections (ms, drive time)")
    cdf.set_ylabel("fraction of emitted slices")
    cdf.set_title(f"latency CDF, {len(result.scenes)} scene(s), time scale {result.config.time_scale:g}", fontsize=9)
    cdf.grid(True, which="both", alpha=0.3)
    cdf.legend(fontsize=8, loc="lower right")
    fig.suptitle(f"streamdet-replay: {result.precision_label}, LiDAR {result.config.lidar_hz:g} Hz x {result.num_slices} "
                 f"slices, cameras {result.config.camera_hz:g} Hz", fontsize=10)  # fmt: skip
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _one_two_five(value: float, _pos=None) -> str:
    """A log axis tick's label: the value where it is 1, 2 or 5 times a power of ten, else none."""
    if not value > 0:
        return ""
    mantissa = value / 10 ** math.floor(math.log10(value))
    return f"{value:g}" if any(abs(mantissa - m) < 1e-6 for m in (1, 2, 5)) else ""


def _timeline(ax, rec: Recording, lo: float, hi: float, color: str) -> None:
    y = {name: len(ROWS) - 1 - i for i, name in enumerate(ROWS)}
    ms = lambda t: (np.asarray(t, dtype=np.float64) - lo) * 1e3  # noqa: E731

    def visible(t: float) -> bool:
        return lo <= t <= hi

    for s in rec.slices:
        if visible(s.scan_end_s):
            ax.plot(ms(s.scan_end_s), y["released"], "x" if s.dropped else "|", color="red" if s.dropped else "k", ms=7)
        if s.emitted and (visible(s.emit_s) or visible(s.scan_end_s)):
            ax.plot([ms(s.scan_end_s), ms(s.emit_s)], [y["released"] - 0.1, y["emitted"] + 0.1], color="0.6", lw=0.6)
            ax.plot(ms(s.emit_s), y["emitted"], "|", color=color, ms=7)
        if np.isfinite(s.start_s) and s.start_s < hi and s.end_s > lo:
            ax.barh(y["slice jobs"], ms(s.end_s) - ms(s.start_s), left=ms(s.start_s), height=0.6, color=color, alpha=0.55,
                    edgecolor="k", lw=0.3)  # fmt: skip
    for im in rec.images:
        if visible(im.capture_s):
            ax.plot(ms(im.capture_s), y["camera"], "x" if im.superseded else "o", color="0.3", ms=5, mfc="none")
        if np.isfinite(im.start_s) and im.start_s < hi and im.end_s > lo:
            ax.barh(y["image jobs"], ms(im.end_s) - ms(im.start_s), left=ms(im.start_s), height=0.6, color="tab:green",
                    alpha=0.55, edgecolor="k", lw=0.3)  # fmt: skip
    ax.set_xlim(0, (hi - lo) * 1e3)
    ax.set_ylim(-0.6, len(ROWS) - 0.4)
    ax.set_yticks([y[name] for name in ROWS], ROWS, fontsize=8)
    ax.grid(True, axis="x", alpha=0.3)
