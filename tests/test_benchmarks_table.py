"""measure_rows on one tiny row: the row's measurements take turns, slow rows go one after the other, --quick's
PyTorch skip (no assertions on speed)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest

from streamdet.benchmarks.modules import build_rows
from streamdet.benchmarks.table import TableConfig, _timing_groups, measure_rows
from streamdet.benchmarks.timing import TimingConfig
from streamdet.models.presets import get_preset

FAST = TimingConfig(repeat=2, warmup=1, budget_s=5.0, min_repeat=2, settle_s=0.01)


@pytest.fixture(scope="module")
def encoder_row():
    rows = build_rows(get_preset("tiny"), [(128, 72)])
    return next(r for r in rows if r.module == "image encoding 128x72")


def _measure(row, tmp_path, **kwargs):
    messages: list[str] = []
    [result] = measure_rows([row], tmp_path, TableConfig(threads=1, int8=False, **kwargs), messages.append)
    return result, messages


def test_a_row_takes_turns(encoder_row, tmp_path):
    result, messages = _measure(encoder_row, tmp_path, timing=FAST)
    assert any("fp32, fp16, PyTorch taking turns in 4 rounds" in m for m in messages)
    assert result.fp32.count == result.fp16.count == result.torch.count == 2
    assert not any("one after the other" in n for n in result.notes)


def test_a_slow_row_goes_one_after_the_other(encoder_row, tmp_path):
    slow = dataclasses.replace(FAST, slow_warmup_s=1e-6)  # every run counts as slow
    result, messages = _measure(encoder_row, tmp_path, timing=slow)
    assert any("one after the other" in m for m in messages)
    assert any(n.startswith("measured one after the other, not taking turns") for n in result.notes)
    assert result.fp32.count == result.fp16.count == result.torch.count == 2


def test_quick_skips_pytorch_on_a_slow_row(encoder_row, tmp_path):
    result, _ = _measure(encoder_row, tmp_path, timing=FAST, torch_skip_ms=1e-6)
    assert result.torch is None and result.torch_over_ort is None
    assert any(n.startswith("PyTorch skipped (first, cold fp32 run") for n in result.notes)
    assert result.fp32.count == result.fp16.count == 2


def test_timing_groups_pair_the_cropped_rows():
    keys = ["slice_multi_head", "slice_single_head", "slice_single_head_cropped", "conv3d", "image_a", "conv3d_cropped"]
    rows = [SimpleNamespace(key=k) for k in keys]
    assert _timing_groups(rows) == [[0], [1, 2], [3, 5], [4]]
    assert _timing_groups(rows[:2]) == [[0], [1]]  # a row without its partner stands alone
    assert _timing_groups([]) == []


def test_a_cropping_pair_takes_turns_together(tmp_path):
    rows = [r for r in build_rows(get_preset("tiny"), [(128, 72)]) if r.key in ("slice_single_head", "slice_single_head_cropped")]
    messages: list[str] = []
    results = measure_rows(rows, tmp_path, TableConfig(threads=1, int8=False, timing=FAST), messages.append)
    assert [r.key for r in results] == ["slice_single_head", "slice_single_head_cropped"]
    assert any("of 2 rows (a cropping pair) taking turns in 4 rounds" in m for m in messages)
    for r in results:
        assert r.fp32.count == r.fp16.count == r.torch.count == r.torch_export.count == 2
