"""The projection LUT compacted to its valid (voxel, camera) pairs: a gather without sentinel slots.

The lifter's LUT (``lut.py``) gives every voxel K slots, each a row of the feature table (``j * Hf * Wf + cell``)
or the sentinel (an all-zero row); the gather reads all K rows of every voxel, weights them and sums over K. Most
voxels are seen by one camera, so most of those reads fetch the sentinel and most of the multiplications are by
zero. The compact form reads each valid pair once:

- the **multi** voxels (two or more valid slots) are combined first: ``multi[m] = sum_k weight * table[index]``
  over their K slots (the only place where K is kept);
- those rows are appended to the table (``ext = [table; multi]``), so every voxel is one row of ``ext``: its only
  valid row (single voxels), its combined row (multi voxels, weight 1), or the sentinel (no camera sees it);
- ``out = ext[final_index] * final_weight``.

Per voxel that is the K-slot gather's own sum, in the same order (a single voxel's ``w * row + 0`` is ``w * row``
exactly), so the two agree bit for bit (``tests/test_compact_lut.py``). Whether it pays is measured in
``benchmarks/lut_gather.py`` (results: benchmarks/RESULTS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.core.lut_layout import LUT_COMPACT, check_lut_layout


@dataclass(frozen=True, eq=False)
class CompactLut:
    """The valid pairs of a (Q, K, Z, Yq, Xq) LUT, for a table of ``sentinel + 1`` rows (sentinel last)."""

    sentinel: int  # the table's all-zero row (= rows of the feature maps)
    multi_index: np.ndarray  # (K, M) int32 table rows of the M voxels with two or more valid slots (sentinel-padded)
    multi_weight: np.ndarray  # (K, M) float32
    final_index: np.ndarray  # (V,) int32 rows of ext = [table; multi]: V = Q * Z * Yq * Xq in the LUT's voxel order
    final_weight: np.ndarray  # (V,) float32
    voxel_shape: tuple[int, ...]  # (Q, Z, Yq, Xq)

    @property
    def num_pairs(self) -> int:
        """Rows read: the multi voxels' valid slots plus one per voxel."""
        return int((self.multi_index != self.sentinel).sum()) + int(self.final_index.size)


def compact_lut(index: np.ndarray, weight: np.ndarray, sentinel: int) -> CompactLut:
    """The compact form of a K-slot LUT ``index``, ``weight`` (Q, K, Z, Yq, Xq) whose empty slots hold ``sentinel``."""
    index = np.asarray(index)
    weight = np.asarray(weight)
    if index.ndim != 5 or index.shape != weight.shape:
        raise ValueError(f"index and weight must both be (Q, K, Z, Yq, Xq), got {index.shape} and {weight.shape}")
    if not np.issubdtype(index.dtype, np.integer) or index.size and (index.min() < 0 or index.max() > sentinel):
        raise ValueError(f"index must hold integer rows in [0, {sentinel}] (the sentinel last), got {index.dtype}")
    q, k = index.shape[:2]
    rows = index.transpose(1, 0, 2, 3, 4).reshape(k, -1)  # (K, V) voxel order Q, Z, Yq, Xq
    w = weight.transpose(1, 0, 2, 3, 4).reshape(k, -1).astype(np.float32)  # (K, V)
    valid = rows != sentinel  # (K, V)
    count = valid.sum(axis=0)  # (V,)
    multi = np.flatnonzero(count >= 2)  # (M,)
    first = np.argmax(valid, axis=0)  # (V,) the single voxels' valid slot (0 for empty ones, which are sentinel)
    v = np.arange(rows.shape[1])
    final_index = np.where(count == 1, rows[first, v], sentinel).astype(np.int64)
    final_weight = np.where(count == 1, w[first, v], 0.0).astype(np.float32)
    final_index[multi] = sentinel + 1 + np.arange(multi.size)  # their combined rows follow the table
    final_weight[multi] = 1.0
    return CompactLut(
        sentinel=int(sentinel),
        multi_index=np.ascontiguousarray(np.where(valid[:, multi], rows[:, multi], sentinel).astype(np.int32)),
        multi_weight=np.ascontiguousarray(np.where(valid[:, multi], w[:, multi], 0.0).astype(np.float32)),
        final_index=final_index.astype(np.int32),
        final_weight=final_weight,
        voxel_shape=(q, *index.shape[2:]),
    )


def lifter_lut_feeds(index: np.ndarray, weight: np.ndarray, sentinel: int, compact: bool) -> dict[str, np.ndarray]:
    """The lifter graph's LUT feeds of a K-slot ``index``, ``weight`` (Q, K, Z, Yq, Xq): as they are (``lut_index``,
    ``lut_weight``), or compacted (``multi_index``, ``multi_weight`` (K, M), ``final_index``, ``final_weight``
    (Q, Z, Yq, Xq); core/lut_layout.py names both)."""
    if not compact:
        return {"lut_index": index, "lut_weight": weight}
    lut = compact_lut(index, weight, sentinel)
    voxels = lut.voxel_shape  # (Q, Z, Yq, Xq)
    return {"multi_index": lut.multi_index, "multi_weight": lut.multi_weight,
            "final_index": lut.final_index.reshape(voxels), "final_weight": lut.final_weight.reshape(voxels)}  # fmt: skip


def lifter_feeds(features: np.ndarray, index: np.ndarray, weight: np.ndarray, layout: str) -> dict[str, np.ndarray]:
    """The lifter graph's whole feeds: the (J, C, Hf, Wf) ``features`` and the K-slot ``index``, ``weight``
    (Q, K, Z, Yq, Xq) in ``layout`` (a manifest's ``lut_layout``, core/lut_layout.py), the sentinel being the maps'
    J * Hf * Wf rows. What code feeding an export's lifter by hand calls, so it reads either layout."""
    if features.ndim != 4:
        raise ValueError(f"features must be (J, C, Hf, Wf), got shape {features.shape}")
    j, _, hf, wf = features.shape
    compact = check_lut_layout(layout) == LUT_COMPACT
    return {"features": features, **lifter_lut_feeds(index, weight, j * hf * wf, compact)}


def gather_compact(table: np.ndarray, lut: CompactLut) -> np.ndarray:
    """(Q, Z, Yq, Xq, C) = the K-slot gather ``sum_k weight * table[index]`` read through the compact form.
    ``table`` (sentinel + 1, C) float32 with its last row zero."""
    if table.ndim != 2 or table.shape[0] != lut.sentinel + 1:
        raise ValueError(f"table must be ({lut.sentinel + 1}, C), got {table.shape}")
    multi = (table[lut.multi_index] * lut.multi_weight[..., None]).sum(axis=0)  # (M, C)
    ext = np.concatenate([table, multi])  # (sentinel + 1 + M, C)
    out = ext[lut.final_index] * lut.final_weight[:, None]  # (V, C)
    return out.reshape(*lut.voxel_shape, table.shape[1])
