"""GMAC counting: known layer counts, the paper's Table 3 within 5 %, and the streamdet-bench --flops-only CLI."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from streamdet.benchmarks.cli import main
from streamdet.benchmarks.flops_report import gmac_rows
from streamdet.models.flops import count_gmac, count_macs
from streamdet.models.presets import get_preset

PAPER_TABLE3 = [180.2, 161.6, 40.43, 715.7, 178.9, 126.5, 71.6, 32.1]


@pytest.mark.parametrize("device", ["cpu", "meta"])
def test_count_macs_of_known_layers(device):
    with torch.device(device):
        conv = torch.nn.Conv2d(8, 16, 3, padding=1)
        x = torch.empty(2, 8, 10, 12)
        lin = torch.nn.Linear(11, 64)
        pts = torch.empty(30, 20, 11)
        conv3d = torch.nn.Conv3d(4, 4, 3, stride=(2, 1, 1), padding=1)
        vol = torch.empty(1, 4, 8, 5, 6)
    assert count_macs(conv, x) == 2 * 10 * 12 * 16 * 8 * 9
    assert count_macs(lin, pts) == 30 * 20 * 11 * 64
    assert count_macs(conv3d, vol) == 4 * 5 * 6 * 4 * 4 * 27  # z halved by the stride
    assert count_gmac(conv, x) == pytest.approx(count_macs(conv, x) / 1e9)


@pytest.fixture(scope="module")
def paper_rows():
    return gmac_rows(get_preset("paper"))


def test_paper_rows_within_five_percent(paper_rows):
    assert [r.paper_gmac for r in paper_rows] == PAPER_TABLE3
    for r in paper_rows:
        assert abs(r.gmac / r.paper_gmac - 1.0) < 0.05, f"{r.module}: {r.gmac:.2f} GMAC vs paper {r.paper_gmac}"


def test_row_structure(paper_rows):
    gm = [r.gmac for r in paper_rows]
    assert gm[0] > gm[1]  # the multi-head costs more
    assert gm[2] == pytest.approx(gm[1] / 4, rel=0.05)  # cropping: a quarter
    assert gm[4] == pytest.approx(gm[3] / 4, rel=1e-6)
    assert gm[5] > gm[6] > gm[7]
    assert paper_rows[3].module == "3D convolutions (512x512x16 volume)"


def test_small_preset_slice_budget():
    rows = gmac_rows(get_preset("small"), [(800, 450)])
    assert all(r.paper_gmac is None for r in rows)
    cropped = rows[2]
    assert cropped.module.endswith("cropped (1 quadrant)")
    assert cropped.gmac <= 0.5, f"small slice graph costs {cropped.gmac:.3f} GMAC per quadrant"


def test_gmac_rows_bad_resolution():
    with pytest.raises(ValueError, match="at least one image resolution"):
        gmac_rows(get_preset("tiny"), [])
    with pytest.raises(ValueError, match="must be positive, got 0x450"):
        gmac_rows(get_preset("tiny"), [(0, 450)])


def test_cli_flops_only_json(tmp_path):
    out = tmp_path / "gmac.json"
    result = CliRunner().invoke(main, ["--flops-only", "--preset", "tiny", "--resolution", "1200x675", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "GMAC" in result.output and "image encoding 1200x675" in result.output
    doc = json.loads(out.read_text())
    assert [set(r) for r in doc["rows"]] == [{"module", "gmac", "paper_gmac"}] * 6
    assert all(r["paper_gmac"] is None for r in doc["rows"])


def test_cli_paper_figures_for_paper_resolution(tmp_path):
    out = tmp_path / "gmac.json"
    result = CliRunner().invoke(main, ["--flops-only", "--resolution", "800x450", "--json", str(out)])
    assert result.exit_code == 0, result.output
    rows = json.loads(out.read_text())["rows"]
    assert rows[-1]["module"] == "image encoding 800x450" and rows[-1]["paper_gmac"] == 32.1


@pytest.mark.parametrize(
    "args, message",
    [
        (["--resolution", "800x450x3"], "expected WIDTHxHEIGHT"),
        (["--flops-only", "--resolution", "800by450"], "expected WIDTHxHEIGHT"),
        (["--flops-only", "--resolution", "0x450"], "must be positive"),
        (["--flops-only", "--preset", "huge"], "'huge' is not one of"),
    ],
)
def test_cli_bad_input_is_one_line_error(args, message):
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0
    assert message in result.output
    assert "Traceback" not in result.output


def test_cli_unwritable_json(tmp_path):
    result = CliRunner().invoke(main, ["--flops-only", "--preset", "tiny", "--json", str(tmp_path / "no" / "x.json")])
    assert result.exit_code != 0 and "cannot write --json" in result.output
