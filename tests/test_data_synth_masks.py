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



def _stored_mask(path, damage=lambda b: b):
    """A 2 x 3 mask written uncompressed (any zip is read), its class_id member's bytes passed through ``damage``
    before they are stored (the zip's CRC then matches them: only the .npy header is wrong)."""
    import io
    import zipfile

    arrays = {"class_id": np.full((2, 3), MASK_NONE, np.uint8), "instance": np.zeros((2, 3), np.uint16),
              "ids": np.zeros(0, np.uint16), "tokens": np.zeros(0, np.str_)}  # fmt: skip
    with zipfile.ZipFile(path, "w") as zf:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, a)
            zf.writestr(f"{name}.npy", damage(buf.getvalue()) if name == "class_id" else buf.getvalue())
    return path


def _unterminated_shape(b: bytes) -> bytes:
    at = b.index(b")", b.index(b"'shape': ("))
    return b[:at] + b" " + b[at + 1:]


def test_a_damaged_header_or_zip_flag_is_a_value_error_naming_the_file(tmp_path):
    # the two damages of a lut.npz that escaped as tokenize.TokenError / NotImplementedError (core/npz_input.py)
    good = _stored_mask(tmp_path / "good.npz").read_bytes()
    assert read_mask(tmp_path / "good.npz", 2, 3)[0].shape == (2, 3)
    tok = _stored_mask(tmp_path / "tok.npz", _unterminated_shape)
    flag = bytearray(good)
    flag[good.index(b"PK\x01\x02") + 8] |= 0x20  # "compressed patched data" on the first member
    (tmp_path / "flag.npz").write_bytes(bytes(flag))
    for path, cause in ((tok, "TokenError"), (tmp_path / "flag.npz", "NotImplementedError: compressed patched data")):
        with pytest.raises(ValueError, match=rf"^mask .*{path.name}: not a readable \.npz: class_id\.npy: cannot read its \.npy header: {cause}"):
            read_mask(path, 2, 3)
