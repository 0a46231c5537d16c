"""core.sectors.check_quadrants, the one check of a quadrant list (slice maps, LUT slicing, uncrop, image updates),
against a naive reference over every subset of 0..3 and over arbitrary lists."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from streamdet.calibration.slice_maps import slice_maps
from streamdet.core.sectors import NUM_QUADRANTS, check_quadrants
from streamdet.runtime_ort.image_cache import ALL_QUADRANTS, update_quadrants


def naive_ok(qs: list) -> bool:
    """A non-empty list of distinct ints of 0..3 in increasing order."""
    if not qs:
        return False
    for q in qs:
        if type(q) is bool or not isinstance(q, (int, np.integer)) or not 0 <= q <= 3:
            return False
    return list(qs) == sorted(set(int(q) for q in qs))


@pytest.mark.parametrize("n", range(1, NUM_QUADRANTS + 1))
def test_every_increasing_subset_passes_unchanged(n):
    for qs in itertools.combinations(range(NUM_QUADRANTS), n):
        assert check_quadrants(qs) == qs
        assert check_quadrants(list(qs)) == qs
        assert check_quadrants(np.array(qs, dtype=np.int64)) == qs
        out = check_quadrants(np.array(qs, dtype=np.int32))
        assert out == qs and all(type(q) is int for q in out)


@pytest.mark.parametrize("bad", [(), [], (1, 0), (0, 0), (0, 4), (-1,), (True,), (0, True), (0.0,), ("0",), "01", b"\x00", 2, None, (0, None)])
def test_bad_lists_are_refused_quoting_the_value(bad):
    with pytest.raises(ValueError, match=r"quadrants must be a non-empty strictly increasing list of 0\.\.3, got "):
        check_quadrants(bad)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.integers(-2, 5), st.booleans(), st.floats(0, 3)), max_size=6))
def test_matches_the_naive_reference(qs):
    if naive_ok(qs):
        assert check_quadrants(qs) == tuple(int(q) for q in qs)
    else:
        with pytest.raises(ValueError):
            check_quadrants(qs)


def test_image_update_none_means_every_quadrant():
    assert update_quadrants(None) == ALL_QUADRANTS == (0, 1, 2, 3)
    assert update_quadrants([2]) == (2,)
    with pytest.raises(ValueError, match="got \\[3, 1\\]"):
        update_quadrants([3, 1])


def test_users_share_the_check():
    from streamdet.calibration.grid import GridSpec

    grid = GridSpec()
    with pytest.raises(ValueError, match="strictly increasing list of 0..3, got \\(2, 1\\)"):
        slice_maps(grid, (2, 1))
    assert slice_maps(grid, (np.int64(1),)).count == 1
