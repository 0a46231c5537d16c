"""The export's one list of steps: the fused and LiDAR-only exports share it, and its length is the [k/N] total."""

from __future__ import annotations

import dataclasses
import warnings

import pytest

from streamdet.export import int8 as q8
from streamdet.export.options import ExportOptions
from streamdet.export.steps import export_steps
from streamdet.models.presets import get_preset

TINY = get_preset("tiny")


@pytest.mark.parametrize("use_image,base,fp16,int8", [(True, 10, 4, 5), (False, 6, 2, 3)])
def test_step_count_follows_the_graphs_and_options(use_image, base, fp16, int8):
    preset = dataclasses.replace(TINY, use_image=use_image)
    for with16, with8 in [(False, False), (True, False), (False, True), (True, True)]:
        steps = export_steps(preset, ExportOptions(fp16=with16, int8=with8), (128, 72))
        assert len(steps) == base + fp16 * with16 + int8 * with8
        labels = [s.label for s in steps]
        assert len(set(labels)) == len(labels)
        assert labels[0].startswith("loading weights") and labels[-1] == "moving the export into place"
        assert ("building the LUT for 128x72" in labels) == use_image


def test_int8_calibration_error_keeps_its_old_name_with_a_warning():
    with pytest.warns(DeprecationWarning, match="Int8CalibrationDataError"):
        old = q8.CalibrationError
    assert old is q8.Int8CalibrationDataError
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert issubclass(q8.Int8CalibrationDataError, ValueError)
    with pytest.raises(AttributeError):
        q8.NoSuchThing  # noqa: B018
