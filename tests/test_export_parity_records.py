"""What an fp16 export records of its parity: the records' output names (the lifter's is the layout's, image_half or
image_bev, at both precisions: review 38, L2), the det_boxes groups, and the counts and warnings the CLI prints."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from streamdet.export.cli import main as export_main
from streamdet.export.parity import BOX_COLUMN_GROUPS, FEW_COMPARED
from streamdet.runtime_ort.manifest import read_manifest


@pytest.fixture(scope="module", params=["image_bev", "image_half"])
def fp16_export(request, tmp_path_factory) -> tuple[str, Path, str]:
    out = tmp_path_factory.mktemp("parity_records") / request.param
    result = CliRunner().invoke(export_main, ["--preset", "tiny", "--fp16", "--image-layout", request.param, "--out", str(out)])
    assert result.exit_code == 0, result.output
    return request.param, out, result.output


def test_each_dense_record_is_named_after_the_graph_output_at_both_precisions(fp16_export):
    layout, out, _ = fp16_export
    outputs = {(p.graph, p.precision): p.output for p in read_manifest(out).parity if p.graph != "slice_head"}
    assert outputs == {("image_encoder", "fp32"): "features", ("image_encoder", "fp16"): "features",
                       ("volumetric_lifter", "fp32"): layout, ("volumetric_lifter", "fp16"): layout}  # fmt: skip


def test_the_slice_graph_records_each_box_group(fp16_export):
    _, out, output = fp16_export
    m = read_manifest(out)
    want = [f"det_boxes.{name}" for name, _ in BOX_COLUMN_GROUPS] + ["det_scores", "det_labels"]
    for precision in ("fp32", "fp16"):
        records = [p for p in m.parity if p.graph == "slice_head" and p.precision == precision]
        assert [p.output for p in records] == want and all(p.passed for p in records)
        assert " detections compared as sets" in records[0].note
        if records[0].note.startswith(FEW_COMPARED):  # the untrained tiny head: mostly near-ties; said aloud
            assert f"slice_head {precision}: {records[0].note}" in output
    assert m.pipeline_parity.passed and "max diff of the pairs above: z " in m.pipeline_parity.note
    assert f"pipeline: {m.pipeline_parity.note}" in output
