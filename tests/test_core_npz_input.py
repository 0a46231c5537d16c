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


def _stored(name: str, data: bytes) -> zipfile.ZipFile:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(name, data)
    return zipfile.ZipFile(io.BytesIO(buf.getvalue()))


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a)
    return buf.getvalue()


@pytest.mark.parametrize("damage", [
    lambda b: b.replace(b"(3, 4)", b"(3, 4 "),  # the header dict unterminated: Python's tokenizer raises TokenError
    lambda b: b.replace(b"'descr'", b"'de\x00r'"),  # a NUL in the header literal
    lambda b: b[:12],  # cut inside the header
    lambda b: b"\x93NUMPY\x09\x00" + b[8:],  # another format version: its 4-byte header length reads as huge
    lambda b: b"PK" + b[2:],  # no .npy magic at all
], ids=["unterminated_shape", "nul_byte", "cut_header", "odd_version", "no_magic"])  # fmt: skip
def test_any_unreadable_header_is_a_value_error_naming_the_member(damage):
    good = _npy(np.zeros((3, 4), np.int32))
    zf = _stored("x.npy", damage(good))
    with pytest.raises(ValueError, match=r"^x\.npy: cannot read its \.npy header: \w+"):
        npy_header(zf, zf.getinfo("x.npy"))


def test_zip_flags_zipfile_refuses_are_a_value_error_naming_the_member():
    zf = _stored("x.npy", _npy(np.zeros(3, np.float32)))
    for flag, cause in ((0x20, "NotImplementedError: compressed patched data"), (0x01, "RuntimeError: File .* is encrypted")):
        info = zf.getinfo("x.npy")
        info.flag_bits |= flag  # what a damaged central directory declares
        with pytest.raises(ValueError, match=rf"^x\.npy: cannot read its \.npy header: {cause}"):
            npy_header(zf, info)
        info.flag_bits &= ~flag
    assert npy_header(zf, zf.getinfo("x.npy")).shape == (3,)  # the naive case still reads
