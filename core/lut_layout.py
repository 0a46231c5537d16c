"""How the lifter graph reads the LUT: the K-slot arrays or the compacted valid pairs (calibration/compact_lut.py).

Torch-free, for the exporter, the manifest and the runtime alike. ``slots``: ``lut_index`` / ``lut_weight``
(Q, K, Z, Yq, Xq), the empty slots holding the sentinel row. ``compact``: ``multi_index`` / ``multi_weight`` (K, M)
(the voxels seen by two or more cameras) and ``final_index`` / ``final_weight`` (Q, Z, Yq, Xq) (one row of the table
extended by the combined rows per voxel); the same sum per voxel (models/compact_lifter.py). A manifest without the
field is ``slots`` (every export before the field existed).
"""

from __future__ import annotations

LUT_SLOTS = "slots"
LUT_COMPACT = "compact"
LUT_LAYOUTS: tuple[str, ...] = (LUT_SLOTS, LUT_COMPACT)
SLOTS_INPUTS: tuple[str, ...] = ("lut_index", "lut_weight")
COMPACT_INPUTS: tuple[str, ...] = ("multi_index", "multi_weight", "final_index", "final_weight")


def check_lut_layout(layout: str) -> str:
    """``layout`` if it is one of LUT_LAYOUTS, else a ValueError naming it."""
    if layout not in LUT_LAYOUTS:
        raise ValueError(f"LUT layout must be one of {LUT_LAYOUTS}, got {layout!r}")
    return layout


def lut_inputs(layout: str) -> tuple[str, ...]:
    """The lifter graph's LUT inputs (after ``features``) in ``layout``."""
    return COMPACT_INPUTS if check_lut_layout(layout) == LUT_COMPACT else SLOTS_INPUTS
