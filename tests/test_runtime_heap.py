"""runtime_ort/heap.py: freezing the start-up heap out of full collections, and measuring the collector's pauses."""

from __future__ import annotations

import gc

import pytest

from streamdet.runtime_ort.heap import GcPauses, frozen_heap


class Node:
    def __init__(self) -> None:
        self.other = self  # a reference cycle: only the cyclic collector frees it


def test_the_heap_is_frozen_inside_and_thawed_after():
    assert gc.get_freeze_count() == 0
    keep = [Node() for _ in range(100)]
    with frozen_heap():
        assert gc.get_freeze_count() >= len(keep)
    assert gc.get_freeze_count() == 0


def test_a_disabled_freeze_leaves_the_heap_alone_and_an_error_still_thaws():
    with frozen_heap(enabled=False):
        assert gc.get_freeze_count() == 0
    with pytest.raises(RuntimeError, match="boom"):
        with frozen_heap():
            raise RuntimeError("boom")
    assert gc.get_freeze_count() == 0


def test_cycles_made_while_frozen_are_still_collected():
    with frozen_heap():
        Node()
        assert gc.collect() >= 1  # the new cycle is not in the frozen generation


@pytest.mark.parametrize("generation", [0, 1, 2])
def test_pauses_count_each_collection_of_its_generation(generation):
    with GcPauses() as pauses:
        for _ in range(3):
            gc.collect(generation)
    got = pauses.to_dict()[f"gen{generation}"]
    assert got["collections"] >= 3 and got["max_ms"] > 0 and got["total_ms"] >= got["max_ms"]
    assert pauses.max_ms >= got["max_ms"]
    assert pauses._callback not in gc.callbacks  # removed on exit


def test_no_collection_means_zero_pauses_and_exit_twice_is_harmless():
    pauses = GcPauses()
    assert pauses.max_ms == 0.0 and all(g["collections"] == 0 for g in pauses.to_dict().values())
    with pauses:
        pass
    pauses.__exit__(None, None, None)
    assert set(pauses.to_dict()) == {"gen0", "gen1", "gen2"}
