"""The synthetic world's mask format (data/synth_masks.py): what write_mask writes, read_mask reads back, and a
mask of another size is refused naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.core.classes import NUM_CLASSES
from streamdet.data.synth_masks import MASK_NONE, MASK_SUFFIX, mask_path, read_mask, write_mask


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_write_then_read_round_trips(tmp_path, seed):
    rng = np.random.default_rng(seed)
    h, w = 9, 16
    class_id = rng.choice([*range(NUM_CLASSES), MASK_NONE], size=(h, w)).astype(np.uint8)
    instance = np.where(class_id == MASK_NONE, 0, rng.integers(1, 5, size=(h, w))).astype(np.uint16)
    ids = np.unique(instance[instance > 0])
    tokens = np.array([f"tok{i}" for i in ids])
    path = write_mask(mask_path(tmp_path / "cam.jpg"), class_id, instance, ids, tokens)
    assert path.name == "cam.jpg" + MASK_SUFFIX
    got = read_mask(path, h, w)
    for a, b in zip(got, (class_id, instance, ids, tokens)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r"mask .*cam\.jpg\.mask\.npz: class_id must be an integer map of the image's shape \(10, 16\)"):
        read_mask(path, 10, w)


def test_empty_mask(tmp_path):
    path = write_mask(tmp_path / "m.npz", np.full((2, 2), MASK_NONE, np.uint8), np.zeros((2, 2), np.uint16),
                      np.zeros(0, np.uint16), np.zeros(0, np.str_))  # fmt: skip
    class_id, instance, ids, tokens = read_mask(path, 2, 2)
    assert (class_id == MASK_NONE).all() and not instance.any() and ids.size == 0 and tokens.size == 0
