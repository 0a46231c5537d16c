"""benchmarks/slice_graphs.py: the slice graphs of several exports timed in turns, parity first."""

from __future__ import annotations

import shutil

import click
import pytest
from click.testing import CliRunner

from streamdet.benchmarks.slice_graphs import main, run


def test_two_exports_of_the_same_weights_are_timed_with_their_parity(tiny_export, tiny_int8_export):
    # the fp32 + fp16 export against the fp32 + int8 one of the same (seeded) tiny weights: fp32 is what both hold
    lines = run([tiny_export, tiny_int8_export.path], rounds=3, threads=1, num_slices=8)
    text = "\n".join(lines)
    assert "parity fp32, tiny against tiny" in text and "parity fp16" not in text and "parity int8" not in text
    rows = [line for line in lines if line.split()[1:2] == ["fp32"]]
    assert len(rows) == 2
    assert rows[0].split()[-3] == "1.000"  # the first export's ratio to itself
    assert "3 rounds" in lines[-1]


def test_the_same_export_twice_has_exact_parity(tiny_export):
    lines = run([tiny_export, tiny_export], rounds=3, threads=1, num_slices=4)
    parity = [line for line in lines if line.startswith("parity")]
    assert [p.split()[1] for p in parity] == ["fp32,", "fp16,"]
    for p in parity:  # every box paired, at the same place and score
        counts = p.split(": ")[1].split(" boxes")[0]
        n = counts.split(" / ")[0]
        assert counts == f"{n} / {n}" and f"{n} paired" in p and "mean 0 max 0 m, max score diff 0" in p, p


def test_a_lidar_only_export_is_refused(tiny_export, tiny_lidar_export):
    with pytest.raises(click.ClickException, match="other inputs"):
        run([tiny_export, tiny_lidar_export], rounds=3, threads=1, num_slices=8)


def test_another_image_layout_is_refused(tiny_export, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(tiny_export, other)
    manifest = other / "manifest.json"
    manifest.write_text(manifest.read_text().replace('"image_layout": "image_bev"', '"image_layout": "image_half"'))
    with pytest.raises(Exception, match="image_half|image layout|other inputs"):
        run([tiny_export, other], rounds=3, threads=1, num_slices=8)


def test_the_cli_needs_two_exports(tiny_export):
    result = CliRunner().invoke(main, [str(tiny_export)])
    assert result.exit_code == 2 and "two or more" in result.output
