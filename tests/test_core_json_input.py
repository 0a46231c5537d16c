"""core/json_input.py: the one reader of input JSON, the safe number test and the cut repr, against plain references."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from streamdet.core.json_input import FLOAT_MAX, is_finite_number, read_json, short_repr


@pytest.mark.parametrize(
    "value, expected",
    [(0, True), (-3, True), (1.5, True), (FLOAT_MAX, True), (-FLOAT_MAX, True), (10**308, True), (10**309, False),
     (-(10**400), False), (math.nan, False), (math.inf, False), (True, False), (np.bool_(True), False),
     (np.float32(2.5), True), (np.float64(np.nan), False), (np.int64(7), True), ("1", False), (None, False), ([1], False)],
)  # fmt: skip
def test_is_finite_number_matches_the_float64_reference(value, expected):
    assert is_finite_number(value) is expected


def test_short_repr_cuts_and_names_huge_integers():
    assert short_repr(10**400) == "an integer of 401 digits"
    assert short_repr("x" * 500, limit=20) == repr("x" * 500)[:17] + "..."
    assert short_repr([10**5000]) == "a list holding an integer too long to print"
    assert short_repr({"a": 1}) == "{'a': 1}"


@pytest.mark.parametrize(
    "content, match",
    [
        (b"{not json", "splits file .* is not valid JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "nests too deeply to be a splits file"),
        (b"[1" + b"0" * 5000 + b"]", "is not valid JSON: Exceeds the limit"),
        (b"\xff\xfe{}", r"is not UTF-8 text \(a binary file\?\)"),
        (b" " * 65, "is larger than 64 bytes: not a splits file"),
    ],
)
def test_read_json_names_the_file_and_what_went_wrong(tmp_path, content, match):
    path = tmp_path / "splits.json"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=match) as e:
        read_json(path, "splits file", 64 if len(content) < 1000 else 1 << 30)
    assert str(path) in str(e.value)


def test_read_json_refuses_a_large_file_unread_and_bounds_a_device(tmp_path):
    big = tmp_path / "big.json"
    with open(big, "wb") as f:  # sparse: 3 GiB on paper, nothing on disk
        f.truncate(3 << 30)
    with pytest.raises(ValueError, match=r"is larger than 2048 MiB"):
        read_json(big, "results file", 2 << 30)
    if os.path.exists("/dev/zero"):
        with pytest.raises(ValueError, match="/dev/zero is larger than 1024 bytes"):
            read_json("/dev/zero", "results file", 1024)
    with pytest.raises(ValueError, match="cannot read"):
        read_json(tmp_path / "missing.json", "results file", 1024)
    assert read_json(_write(tmp_path / "ok.json", b'{"a": [1, 2.5]}'), "x", 100) == {"a": [1, 2.5]}


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


def test_read_json_never_allocates_its_cap(tmp_path):
    """A 16 GiB cap (the tables') must not mean a 16 GiB buffer: under an address-space limit the read still works."""
    import subprocess
    import sys

    path = _write(tmp_path / "t.json", b'[{"token": "a"}]')
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30)); "
            "from streamdet.core.json_input import read_json; import sys; "
            f"print(read_json({str(path)!r}, 'table', 16 << 30)); "
            "print(len(read_json('/dev/stdin', 'table', 16 << 30)))")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], input=b"[1, 2, 3]", capture_output=True, timeout=60)
    assert done.returncode == 0, done.stderr.decode()[-500:]
    assert done.stdout.decode().split() == ["[{'token':", "'a'}]", "3"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
def test_a_fifo_without_a_writer_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "results.json"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"results file .*results\.json is a pipe or device that gave no data"):
        read_json(fifo, "results file", 1 << 20)  # an open() that blocks would hang this test


@pytest.mark.skipif(not os.path.isdir("/dev/fd"), reason="/dev/fd names a process's pipes (Linux, macOS)")
def test_a_pipe_with_a_writer_is_read():
    """A shell's ``--gt <(zcat gt.json.gz)`` names a pipe whose writer is there: it reads as a file would."""
    read_end, write_end = os.pipe()
    try:
        os.write(write_end, b'{"results": {}}')
        os.close(write_end)
        write_end = None
        assert read_json(f"/dev/fd/{read_end}", "gt file", 1 << 20) == {"results": {}}
    finally:
        os.close(read_end)
        if write_end is not None:
            os.close(write_end)
