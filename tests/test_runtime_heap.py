"""runtime_ort/heap.py: freezing the start-up heap out of full collections, and measuring the collector's pauses."""

from __future__ import annotations

import contextlib
import gc
import weakref

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


def test_release_free_memory_hands_the_c_heap_back_where_glibc_has_malloc_trim():
    import ctypes.util
    import platform

    from streamdet.runtime_ort import heap

    released = heap.release_free_memory()
    assert isinstance(released, bool)
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc" and ctypes.util.find_library("c"):
        assert released  # the detector's calibration swaps and close() rely on it here


def test_release_free_memory_is_a_no_op_without_malloc_trim(monkeypatch):
    from streamdet.runtime_ort import heap

    monkeypatch.setattr(heap, "_TRIM", None)
    assert heap.release_free_memory() is False


def test_a_calibration_swap_and_close_release_the_c_heap(tiny_export, monkeypatch):
    import dataclasses

    from streamdet.runtime_ort import detector as detector_module
    from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
    from streamdet.runtime_ort.export_settings import export_rig

    calls = []
    monkeypatch.setattr(detector_module, "release_free_memory", lambda: calls.append(1) or True)
    det = StreamingDetector(tiny_export, DetectorConfig())
    rig = export_rig(det.manifest, det.export_dir)
    det.set_calibration(rig)  # built from the rig (the export's lut.npz is a file): released
    det.set_calibration(rig)  # the rig in use: nothing built, nothing to release
    assert calls == [1]
    focal = rig.cameras[0].K.copy()
    focal[:2, :2] *= 1.001
    det.set_calibration(dataclasses.replace(rig, cameras=(dataclasses.replace(rig.cameras[0], K=focal), *rig.cameras[1:])))
    assert calls == [1, 1]
    det.close()
    assert calls == [1, 1, 1]


# ---- a closed detector is freed by reference counting alone ----------------------------------------------------------
@contextlib.contextmanager
def _no_collector():
    """The cyclic collector off, after one full collection: what is freed meanwhile was freed by reference counts."""
    gc.collect()
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def test_schema_anyof_failures_leave_no_reference_cycles():
    """A failed anyOf option's exception was kept with its traceback, which holds the validating frame that holds it:
    a cycle that kept the callers' frames (StreamingDetector.__init__'s, with its sessions) alive until a full
    collection, hundreds of MB per detector closed and dropped (benchmarks/RESULTS.md, "Memory after calibration swaps")."""
    from streamdet.runtime_ort.schema import validate

    with _no_collector():
        validate({"a": 1}, {"properties": {"a": {"anyOf": [{"type": "string"}, {"type": "integer"}]}}})
        assert gc.collect() == 0


@pytest.mark.parametrize("runner", [False, True])
def test_a_closed_detector_and_its_sessions_are_freed_without_a_collection(tiny_export, runner):
    from streamdet.runtime_ort.detector import StreamingDetector
    from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner

    with _no_collector():
        det = StreamingDetector(tiny_export)
        alive = [weakref.ref(det)] + [weakref.ref(s) for s in det.sessions.values()]
        if runner:
            lanes = StreamingRunner(det, LaneConfig(schedule="phase-locked"))
            alive.append(weakref.ref(lanes))
            lanes.close()
            del lanes
        det.close()
        del det
        assert [r() is None for r in alive] == [True] * len(alive)


def test_close_lets_go_of_the_image_bev_and_the_lut_views_while_the_detector_is_held(tiny_export):
    """An application that keeps its closed detector (an attribute of its node) keeps none of its large arrays."""
    import numpy as np

    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    rng = np.random.default_rng(0)
    det.update_images({n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}, 1.0)
    held = [weakref.ref(s.bev) for s in det.image_state.quadrants]
    assert det.image_state is not None and det._views._quadrant_luts
    det.close()
    assert det.image_state is None and not det._views._quadrant_luts and not det._views._feeds
    assert all(r() is None for r in held)
    if det._terms is not None:
        assert not det._terms._terms and not det._terms._shares and not det._terms._luts
