"""core.npz_input: .npy member headers read before anything inflates; object dtypes and mis-sized members refused."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from streamdet.core.npz_input import check_member_size, npy_header


def _npz(**arrays) -> zipfile.ZipFile:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return zipfile.ZipFile(io.BytesIO(buf.getvalue()))


@pytest.mark.parametrize("a", [np.zeros((3, 4), np.int32), np.ones(7, np.float64), np.array("json"), np.zeros((0, 2), np.uint8)])
def test_headers_of_real_members(a):
    zf = _npz(x=a)
    info = zf.getinfo("x.npy")
    h = npy_header(zf, info)
    assert (h.shape, h.dtype, h.fortran_order) == (a.shape, a.dtype, False) and h.data_bytes == a.nbytes
    check_member_size(info, h)


def test_object_dtype_is_refused_unread():
    zf = _npz(x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match=r"x\.npy holds Python objects \(dtype object\): a pickle, never loaded"):
        npy_header(zf, zf.getinfo("x.npy"))


def test_a_member_of_another_size_than_its_header_is_refused():
    zf = _npz(x=np.zeros(10, np.float32))
    info = zf.getinfo("x.npy")
    h = npy_header(zf, info)
    info.file_size += 4  # padded
    with pytest.raises(ValueError, match=r"x\.npy declares \d+ bytes, but its header implies \d+ \(<f4 \(10,\)\): truncated or padded"):
        check_member_size(info, h)
