"""The LUT compacted to its valid (voxel, camera) pairs gathers exactly what the K-slot LUT gathers."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.calibration.compact_lut import compact_lut, gather_compact
from streamdet.calibration.quadrant_lut import quadrant_lut


def naive_slots(table: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The lifter's K-slot gather, voxel by voxel: (Q, K, Z, Y, X) -> (Q, Z, Y, X, C)."""
    q, k, z, y, x = index.shape
    out = np.zeros((q, z, y, x, table.shape[1]), np.float32)
    for qi, zi, yi, xi in np.ndindex(q, z, y, x):
        acc = np.zeros(table.shape[1], np.float32)
        for ki in range(k):
            acc = acc + table[index[qi, ki, zi, yi, xi]] * weight[qi, ki, zi, yi, xi]
        out[qi, zi, yi, xi] = acc
    return out


def random_lut(seed: int, rows: int, k: int, shape=(2, 2, 3, 4)):
    rng = np.random.default_rng(seed)
    q, z, y, x = shape
    count = rng.integers(0, k + 1, (q, z, y, x))  # valid slots per voxel, valid ones first
    index = np.full((q, k, z, y, x), rows, np.int32)
    weight = np.zeros((q, k, z, y, x), np.float32)
    for s in range(k):
        here = count > s
        index[:, s][here] = rng.integers(0, rows, int(here.sum()))
        weight[:, s][here] = rng.uniform(0.1, 1.0, int(here.sum())).astype(np.float32)
    return index, weight


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("k", [1, 2, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_compact_gather_equals_the_k_slot_gather(seed, k, dtype):
    rows, c = 17, 5
    index, weight = random_lut(seed, rows, k)
    rng = np.random.default_rng(seed + 10)
    table = np.concatenate([rng.standard_normal((rows, c)), np.zeros((1, c))]).astype(dtype).astype(np.float32)
    lut = compact_lut(index, weight, rows)
    np.testing.assert_array_equal(gather_compact(table, lut), naive_slots(table, index, weight))
    count = (index != rows).sum(axis=1)  # (Q, Z, Y, X) valid slots per voxel
    assert lut.num_pairs == int(count[count >= 2].sum()) + count.size  # multi voxels' slots, then one row per voxel


def test_compact_gather_of_a_real_quadrant_lut(tiny_export):
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    lut = det.lut
    for q in range(4):
        qlut = quadrant_lut(lut, q)
        cells = lut.feature_height * lut.feature_width
        sentinel = qlut.num_feature_maps * cells
        rng = np.random.default_rng(q)
        table = np.concatenate([rng.standard_normal((sentinel, 3)), np.zeros((1, 3))]).astype(np.float32)
        want = (table[qlut.index] * qlut.weight[..., None]).sum(axis=1)  # (1, Z, Y, X, C) the lifter's order
        np.testing.assert_array_equal(gather_compact(table, compact_lut(qlut.index, qlut.weight, sentinel)), want)


def test_edge_cases_and_malformed_input():
    index = np.full((1, 2, 1, 1, 3), 4, np.int32)  # no camera sees anything
    lut = compact_lut(index, np.zeros(index.shape, np.float32), 4)
    assert lut.multi_index.shape == (2, 0)
    np.testing.assert_array_equal(gather_compact(np.zeros((5, 2), np.float32), lut), np.zeros((1, 1, 1, 3, 2)))
    with pytest.raises(ValueError, match="Q, K, Z"):
        compact_lut(np.zeros((2, 3), np.int32), np.zeros((2, 3), np.float32), 4)
    with pytest.raises(ValueError, match=r"\[0, 4\]"):
        compact_lut(np.full((1, 1, 1, 1, 1), 9, np.int32), np.zeros((1, 1, 1, 1, 1), np.float32), 4)
    with pytest.raises(ValueError, match="table must be"):
        gather_compact(np.zeros((3, 2), np.float32), lut)
