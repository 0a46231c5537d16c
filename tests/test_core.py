"""streamdet.core: the shared vocabulary is defined once and every user reads the same values; box pairing against a
naive reference with multi-column keys; the sweep layout check."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest

from streamdet.core import constants, points
from streamdet.core.boxes import pair_boxes

SEEDS = [0, 1, 2, 3]


def test_old_homes_give_the_core_values():
    import streamdet.calibration.grid as grid
    import streamdet.data.slicing as slicing
    import streamdet.runtime_ort.boxes as boxes
    import streamdet.runtime_ort.detector as detector
    import streamdet.runtime_ort.manifest as manifest
    import streamdet.runtime_ort.pillarize as pillarize
    from streamdet.cli_utils import PRECISION_CHOICES
    from streamdet.core import boxes as core_boxes
    from streamdet.core import classes, sectors, slicing as core_slicing

    assert boxes.CLASS_NAMES is classes.CLASS_NAMES and boxes.box_corners_bev is core_boxes.box_corners_bev
    assert slicing.split_sweep is core_slicing.split_sweep and slicing.SWEEP_DURATION_S == points.SWEEP_DURATION_S
    assert grid.check_num_slices is sectors.check_num_slices and grid.NUM_QUADRANTS == sectors.NUM_QUADRANTS
    assert detector.PRECISIONS == manifest.PRECISIONS == PRECISION_CHOICES == constants.PRECISIONS
    assert pillarize.POINT_DIM == points.SLICE_COLUMNS
    assert constants.BUNDLED_CALIBRATION_SOURCE == "bundled:nuscenes_sample/calibration.json"  # written in manifests


def test_bundled_sources_name_shipped_files():
    import importlib.resources

    root = importlib.resources.files("streamdet.data")
    for source in (constants.BUNDLED_SAMPLE_SOURCE, constants.BUNDLED_CALIBRATION_SOURCE):
        assert source.startswith(constants.BUNDLED_PREFIX)
        assert (root / source[len(constants.BUNDLED_PREFIX):]).is_file() or (root / source[len(constants.BUNDLED_PREFIX):]).is_dir()


@pytest.mark.parametrize("shape", [(0, 5), (7, 5)])
def test_check_sweep_accepts_the_sweep_layout(shape):
    assert points.check_sweep(np.zeros(shape, np.float32)).shape == shape


@pytest.mark.parametrize("shape", [(7,), (7, 4), (7, 6), (2, 5, 1)])
def test_check_sweep_names_the_bad_shape(shape):
    with pytest.raises(ValueError, match=r"my sweep must be \(N, 5\) x, y, z, intensity, ring; got shape " + re.escape(str(shape))):
        points.check_sweep(np.zeros(shape), "my sweep")


def test_check_sweep_extra_columns_only_when_asked():
    assert points.check_sweep(np.zeros((3, 6)), exact=False).shape == (3, 6)
    with pytest.raises(ValueError):
        points.check_sweep(np.zeros((3, 4)), exact=False)


# ---- pair_boxes ------------------------------------------------------------------------------------------------


def _boxes(rng: np.random.Generator, n: int, dtype) -> np.ndarray:
    b = np.zeros((n, 9), dtype=dtype)
    b[:, :2] = rng.uniform(0, 8, size=(n, 2))
    b[:, 3:6] = 1.0
    return b


def _naive_pairs(ba, ka, bb, kb, radius):
    """Every candidate pair by distance (ties in row-major order), taken while both boxes are free."""
    cands = []
    for i, j in itertools.product(range(len(ba)), range(len(bb))):
        if np.array_equal(ka[i], kb[j]):
            d = float(np.hypot(*(ba[i, :2].astype(np.float64) - bb[j, :2])))
            if d <= radius:
                cands.append((d, i, j))
    used_a, used_b, pairs = set(), set(), []
    for d, i, j in sorted(cands):
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j, d))
    return pairs


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("key_columns", [1, 2])
def test_pair_boxes_matches_naive(seed, dtype, key_columns):
    rng = np.random.default_rng(seed)
    ba, bb = _boxes(rng, 14, dtype), _boxes(rng, 10, dtype)
    shape_a = (14,) if key_columns == 1 else (14, 2)
    shape_b = (10,) if key_columns == 1 else (10, 2)
    ka, kb = rng.integers(0, 2, size=shape_a), rng.integers(0, 2, size=shape_b)
    ia, ib, d = pair_boxes(ba, ka, bb, kb, radius_m=2.5)
    want = _naive_pairs(ba, ka, bb, kb, 2.5)
    assert sorted(zip(ia.tolist(), ib.tolist())) == sorted((i, j) for i, j, _ in want)
    assert np.all(np.diff(d) >= 0)  # nearest pairs first
    assert np.allclose(d, np.linalg.norm(ba[ia, :2].astype(np.float64) - bb[ib, :2], axis=1))
    assert all(np.array_equal(ka[i], kb[j]) for i, j in zip(ia, ib))


def test_pair_boxes_empty_and_out_of_radius():
    ia, ib, d = pair_boxes(np.zeros((0, 9)), np.zeros((0, 2), int), np.zeros((4, 9)), np.zeros((4, 2), int), 1.0)
    assert ia.size == ib.size == d.size == 0
    far = np.zeros((1, 9))
    far[0, 0] = 5.0
    assert pair_boxes(np.zeros((1, 9)), [0], far, [0], 1.0)[0].size == 0


def test_pair_boxes_refuses_keys_that_do_not_fit():
    with pytest.raises(ValueError, match=r"keys_b must be \(2,\) or \(2, k\)"):
        pair_boxes(np.zeros((3, 9)), np.zeros(3), np.zeros((2, 9)), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match=r"boxes_a must be \(N, 9\)"):
        pair_boxes(np.zeros((3, 7)), np.zeros(3), np.zeros((2, 9)), np.zeros(2), 1.0)
