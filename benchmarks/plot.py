"""PNG bar chart of the Table 3 rows: ms per row for onnxruntime fp32, fp16, int8 and PyTorch eager, on the module as
trained and, where the export rewrites it, on the rewrite (log scale); beside it, given the probe's peak, each row's
fp32 throughput as a fraction of it, against the benchmark's 60 % target."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from streamdet.benchmarks.report import PEAK_FRACTION_MIN
from streamdet.benchmarks.table import RowResult


def plot_rows(rows: Sequence[RowResult], path: str | Path, title: str, peak_gflops_per_s: float | None = None) -> Path:
    """Horizontal grouped bars, one group per row; missing measurements (skipped, failed) leave a gap. With
    ``peak_gflops_per_s``, a second panel: % of that peak per row (fp32, the row's own MACs)."""
    import matplotlib

    matplotlib.use("Agg")  # no display on the benchmark machine
    import matplotlib.pyplot as plt

    if not rows:
        raise ValueError("plot_rows needs at least one row")
    path = Path(path)
    series = (
        ("onnxruntime fp32", [r.fp32.median_ms for r in rows]),
        ("onnxruntime fp16", [np.nan if r.fp16 is None else r.fp16.median_ms for r in rows]),
        ("onnxruntime int8", [np.nan if r.int8 is None else r.int8.median_ms for r in rows]),
        ("PyTorch eager", [np.nan if r.torch is None else r.torch.median_ms for r in rows]),
        ("PyTorch eager, the export's rewrite", [np.nan if r.torch_export is None else r.torch_export.median_ms for r in rows]),
    )
    colors = ("tab:blue", "tab:orange", "tab:green", "tab:red", "lightcoral")
    y = np.arange(len(rows))
    height = 0.8 / len(series)
    if peak_gflops_per_s is not None and not peak_gflops_per_s > 0:
        raise ValueError(f"peak_gflops_per_s must be a positive number, got {peak_gflops_per_s!r}")
    size = (10, 0.75 * len(rows) + 1.5)
    if peak_gflops_per_s is None:
        fig, ax = plt.subplots(figsize=size)
    else:
        fig, (ax, eff) = plt.subplots(1, 2, figsize=(size[0] + 3, size[1]), sharey=True, width_ratios=(3, 1))
    for i, ((label, values), color) in enumerate(zip(series, colors)):
        ax.barh(y + (i - (len(series) - 1) / 2) * height, values, height, label=label, color=color)
    ax.set_yticks(y, [r.module for r in rows], fontsize=8)
    ax.invert_yaxis()  # first row on top, as in the table
    ax.set_xscale("log")  # rows span milliseconds to seconds
    ax.set_xlabel("ms per run (median)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower right")  # the bottom rows (image encoder) leave that corner free
    ax.grid(axis="x", which="both", alpha=0.3)
    if peak_gflops_per_s is not None:
        percent = [100.0 * r.gflops_per_s / peak_gflops_per_s for r in rows]
        eff.barh(y, percent, 0.6, color="tab:blue")
        eff.axvline(100.0 * PEAK_FRACTION_MIN, color="black", linestyle="--", linewidth=1, label=f"{100 * PEAK_FRACTION_MIN:.0f} % target")
        for yi, pct in zip(y, percent):
            eff.text(pct + 2, yi, f"{pct:.0f} %", va="center", fontsize=8)
        eff.set_xlim(0, max(120.0, max(percent) + 20))
        eff.set_xlabel(f"fp32 % of the {peak_gflops_per_s:.0f} GFLOP/s probe")
        eff.legend(fontsize=8, loc="lower right")
        eff.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
