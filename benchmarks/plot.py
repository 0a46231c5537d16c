"""PNG bar chart of the Table 3 rows: ms per row for onnxruntime fp32, fp16, int8 and PyTorch eager, on the module as
trained and, where the export rewrites it, on the rewrite (log scale)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from streamdet.benchmarks.table import RowResult


def plot_rows(rows: Sequence[RowResult], path: str | Path, title: str) -> Path:
    """Horizontal grouped bars, one group per row; missing measurements (skipped, failed) leave a gap."""
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
    fig, ax = plt.subplots(figsize=(10, 0.75 * len(rows) + 1.5))
    for i, ((label, values), color) in enumerate(zip(series, colors)):
        ax.barh(y + (i - (len(series) - 1) / 2) * height, values, height, label=label, color=color)
    ax.set_yticks(y, [r.module for r in rows], fontsize=8)
    ax.invert_yaxis()  # first row on top, as in the table
    ax.set_xscale("log")  # rows span milliseconds to seconds
    ax.set_xlabel("ms per run (median)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower right")  # the bottom rows (image encoder) leave that corner free
    ax.grid(axis="x", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
