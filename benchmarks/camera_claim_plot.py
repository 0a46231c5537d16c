"""The picture of issue 19's decision: fused minus LiDAR-only per figure, with its 95 % interval, at 8 and 32 slices.

A forest plot (one row per figure, the difference as a dot, the paired-bootstrap interval as a bar, zero as a line,
the decision's bars as ticks) drawn from the two ``streamdet-eval --compare --json`` files that
``camera_claim`` decides on. matplotlib (Agg) is imported only when a plot is asked for.
"""

from __future__ import annotations

from pathlib import Path

from streamdet.core.classes import CLASS_NAMES

# (subset, key, label) of the rows, top to bottom; a row a comparison lacks is left out (e.g. --no-subsets)
ROWS: tuple[tuple[str, str, str], ...] = (
    ("all", "mAP", "mAP"),
    ("all", "NDS", "NDS"),
    *(("all", f"AP/{c}", f"AP {c.replace('_', ' ')}") for c in CLASS_NAMES),
    ("cut_by_slice_border", "mAP", "mAP, boxes cut by a slice border"),
    ("gt<=5pts", "mAP", "mAP, boxes with <= 5 points"),
)


def _rows(compare: dict) -> list[tuple[str, float, float, float]]:
    """(label, B - A, lo, hi) in points for each row of ROWS the comparison holds."""
    out = []
    subsets = compare.get("subsets", {})
    for subset, key, label in ROWS:
        d = subsets.get(subset, {}).get(key)
        if d is not None:
            out.append((label, 100 * d["B_minus_A"], 100 * d["ci_lo"], 100 * d["ci_hi"]))
    return out


def plot_claim(compare8: dict, compare32: dict, path: Path, verdict: str = "",
               needs: dict[tuple[str, int], float] | None = None) -> None:  # fmt: skip
    """Write the forest plot to ``path`` (PNG). ``needs``: (row label, slices) -> the decision's bar in points,
    e.g. ``{("mAP", 8): 3, ("mAP", 32): 5, ("AP bicycle", 8): 10}``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = [(8, _rows(compare8), "o", "tab:blue", -0.15), (32, _rows(compare32), "s", "tab:orange", 0.15)]
    labels = [label for _, key, label in ROWS if any(r[0] == label for _, rows, *_ in series for r in rows)]
    if not labels:
        raise ValueError("the comparison files hold none of the plotted figures: are they streamdet-eval --compare --json output?")
    y_of = {label: len(labels) - 1 - i for i, label in enumerate(labels)}  # first row on top
    fig, ax = plt.subplots(figsize=(7.5, 0.42 * len(labels) + 1.4))
    offset = {}
    for slices, rows, marker, color, dy in series:
        offset[slices] = dy
        ys = [y_of[r[0]] + dy for r in rows]
        diffs = [r[1] for r in rows]
        errs = [[r[1] - r[2] for r in rows], [r[3] - r[1] for r in rows]]  # asymmetric: below, above
        ax.errorbar(diffs, ys, xerr=errs, fmt=marker, color=color, capsize=3, label=f"{slices} slices (95 % interval)")
    drawn = False
    for (label, slices), need in (needs or {}).items():
        if label in y_of and slices in offset:
            y = y_of[label] + offset[slices]
            ax.plot([need, need], [y - 0.14, y + 0.14], color="tab:red", lw=2.5, label=None if drawn else "the issue's bar")
            drawn = True
    ax.axvline(0.0, color="black", lw=1)
    ax.set_yticks(list(y_of.values()), list(y_of.keys()))
    ax.set_xlabel("fused - LiDAR-only (points)")
    title = "Do the cameras earn their cost? (paired bootstrap over scenes)"
    ax.set_title(title + (f"\nverdict: {verdict}" if verdict else ""), fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
