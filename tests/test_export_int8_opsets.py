"""int8 export at the newest opsets: onnxruntime's symbolic shape inference raised a TypeError on the slice graph at
opsets 18-20 inside ``quant_pre_process`` (a traceback from ``streamdet-export --int8 --opset 18``); the pre-processing
now goes on without it there (export/int8_quantize.py ``_pre_process``)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from streamdet.export.cli import main as export_main
from streamdet.runtime_ort.manifest import read_manifest


@pytest.mark.parametrize("opset", [20])
def test_int8_export_at_the_newest_opset(tmp_path, opset):
    out = tmp_path / "e"
    # the bundled sample calibrates (one sample: --calibration-samples without --calibration-data is refused, review 41 F4)
    args = ["--preset", "tiny", "--slices", "8", "--opset", str(opset), "--int8", "--out", str(out)]
    result = CliRunner().invoke(export_main, args)
    assert result.exit_code == 0, result.output
    m = read_manifest(out)
    assert {g.opset for g in m.graphs} == {opset} and {g.precision for g in m.graphs} == {"fp32", "int8"}
    assert m.int8 is not None and m.int8.boxes.matched > 0
