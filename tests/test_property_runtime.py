"""Property tests of the running detector: generated point arrays, image dicts and call interleavings.

Each call returns a correct result or raises the project's named error (a ValueError), never another exception; a
refused call never changes the cached image state; whatever the interleaving of image updates, calibration swaps
and slices, the cache ends with the image set started last, lifted with the calibration in use; the runner's
submits never raise for another job's state and every future ends in a result, a drop or a cancellation.
Profiles: tests/conftest.py (CI bounded; HYPOTHESIS_PROFILE=long).
"""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")

from hypothesis import event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

from streamdet.calibration.perturb import perturb_rig  # noqa: E402
from streamdet.core.slicing import split_sweep  # noqa: E402
from streamdet.data.sample import load_bundled_sample  # noqa: E402
from streamdet.core.classes import CLASS_NAMES  # noqa: E402
from streamdet.runtime_ort.detector import ImageUpdate, SliceResult, StreamingDetector  # noqa: E402
from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, SliceDropped, StreamingRunner  # noqa: E402


def _costly(ci_examples: int) -> int:
    """Examples for a property whose inputs cost a graph run or a file tree: a few in CI, 1/20 of the profile's beyond."""
    return max(ci_examples, settings().max_examples // 20)


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


@pytest.fixture(scope="module")
def det(tiny_export) -> StreamingDetector:
    return StreamingDetector(tiny_export)


@pytest.fixture(scope="module")
def slices(sample):
    return split_sweep(sample.points, 8)


@pytest.fixture(scope="module")
def rigs(sample):
    return [sample.rig] + [perturb_rig(sample.rig, 1.0, 0.2, seed=s) for s in range(2)]


def _image_set(det: StreamingDetector, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}


# ---- point arrays --------------------------------------------------------------------------------------------------
FLOATS = st.one_of(
    st.floats(-30.0, 30.0, width=32),  # mostly inside the tiny grid (25.6 m square)
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, -0.0, 12.8, -12.8, 1e30, np.nan, np.inf]),
)


@st.composite
def point_arrays(draw):
    kind = draw(st.sampled_from(["float32"] * 6 + ["float64", "int32", "bool", "columns", "object", "1d"]))
    n = draw(st.integers(0, 200))
    if kind == "columns":
        return draw(hnp.arrays(np.float32, (n, draw(st.sampled_from([0, 5, 7]))), elements=FLOATS))
    if kind == "object":
        return [[0.0] * 6] * n
    if kind == "1d":
        return np.zeros(6 * n, np.float32)
    dtype = {"float32": np.float32, "float64": np.float64, "int32": np.int32, "bool": np.bool_}[kind]
    elements = FLOATS if kind == "float32" else None
    return draw(hnp.arrays(dtype, (n, 6), elements=elements))


@given(points=point_arrays(),
       k=st.one_of(st.integers(0, 7), st.integers(0, 7), st.integers(-2, 9), st.booleans(), st.sampled_from([np.int64(3), 2.0])),
       n=st.sampled_from([None] * 6 + [1, 2, 4, 8, 16, 0, 3, True]))  # fmt: skip
def test_detect_slice_results_or_value_errors(det, points, k, n):
    before = det.image_state
    try:
        res = det.detect_slice(points, k, timestamp=1.0, num_slices=n)
    except ValueError:
        event("refused")
        assert det.image_state is before
        return
    event("detected")
    assert isinstance(res, SliceResult)
    assert isinstance(points, np.ndarray) and points.dtype == np.float32
    assert res.num_points == len(points)
    nonfinite = int((~np.isfinite(points).all(axis=1)).sum())
    assert res.num_nonfinite_dropped == nonfinite
    assert nonfinite + res.num_outside_dropped + res.num_points_dropped <= len(points)
    d = res.detections
    assert np.isfinite(d.boxes).all() and ((d.labels >= 0) & (d.labels < len(CLASS_NAMES))).all()
    assert (d.scores >= det.postprocess.score_threshold).all()
    assert det.image_state is before


# ---- image dicts ---------------------------------------------------------------------------------------------------
@st.composite
def image_dicts(draw, names: tuple[str, ...], size: tuple[int, int]):
    w, h = size
    if draw(st.integers(0, 9)) == 0:
        return draw(st.sampled_from([None, [], "CAM_FRONT", np.zeros((1, h, w, 3), np.uint8), 3]))
    valid = draw(st.booleans())  # half the dicts are well-formed (any subset of the cameras), half carry a defect
    choices = list(names) if valid else [*names, "CAM_NOPE", ""]
    keys = draw(st.lists(st.sampled_from(choices), max_size=len(names) + 1, unique=True))
    out = {}
    for key in keys:
        kind = "ok" if valid else draw(st.sampled_from(["ok", "ok", "dtype", "shape", "none", "list"]))
        if kind == "ok":
            out[key] = draw(hnp.arrays(np.uint8, (h, w, 3)))
        elif kind == "dtype":
            out[key] = np.zeros((h, w, 3), draw(st.sampled_from([np.float32, np.int16, np.bool_])))
        elif kind == "shape":
            out[key] = np.zeros(draw(st.sampled_from([(w, h, 3), (h, w), (h, w, 4), (0, 0, 3)])), np.uint8)
        else:
            out[key] = None if kind == "none" else [[0, 0, 0]]
    return out


@settings(max_examples=_costly(25))
@given(data=st.data())
def test_update_images_results_or_value_errors(det, data):
    images = data.draw(image_dicts(det.camera_names, (det.image.width, det.image.height)))
    before = det.image_state
    try:
        update = det.update_images(images, timestamp=float(data.draw(st.integers(0, 100))))
    except ValueError:
        event("refused")
        assert det.image_state is before  # a refused image set never touches the cache
        return
    event("updated")
    assert isinstance(update, ImageUpdate) and not update.superseded
    assert set(update.cameras_used) == set(images) and det.image_state.seq > (before.seq if before else 0)


# ---- call interleavings ----------------------------------------------------------------------------------------------
OPS = st.lists(
    st.one_of(
        st.tuples(st.just("images"), st.integers(0, 3), st.floats(-10, 10)),
        st.tuples(st.just("calibration"), st.integers(0, 2), st.just(0.0)),
        st.tuples(st.just("slice"), st.integers(0, 7), st.floats(-10, 10)),
    ),
    min_size=1,
    max_size=8,
)


@settings(max_examples=_costly(20))
@given(ops=OPS, threads=st.integers(1, 3))
def test_interleaved_calls_keep_the_newest_images_under_the_current_calibration(det, slices, rigs, ops, threads):
    image_sets = {seed: _image_set(det, seed) for seed in range(4)}
    errors: list[BaseException] = []
    chunks = [ops[i::threads] for i in range(threads)]

    def run(chunk):
        try:
            for op, arg, ts in chunk:
                if op == "images":
                    det.update_images(image_sets[arg], timestamp=ts)
                elif op == "calibration":
                    det.set_calibration(rigs[arg])
                else:
                    det.detect_slice(slices[arg], arg, timestamp=ts)
        except BaseException as e:  # noqa: BLE001 - any exception fails the property below
            errors.append(e)

    workers = [threading.Thread(target=run, args=(c,)) for c in chunks]
    for t in workers:
        t.start()
    for t in workers:
        t.join(60)
    assert not errors
    state = det.image_state
    if state is not None:
        assert state.seq == det._image_seq  # the image set started last is the one cached
        assert state.lut is det.lut  # lifted with the calibration in use
        assert np.array_equal(state.bev, det._lift(state.features, det.lut))


@settings(max_examples=_costly(15))
@given(
    ops=st.lists(st.one_of(st.tuples(st.just("slice"), st.integers(0, 7)), st.tuples(st.just("images"), st.integers(0, 3)),
                           st.tuples(st.just("cancel"), st.integers(0, 30))), min_size=1, max_size=14),
    in_flight=st.integers(1, 3),
    queue=st.integers(1, 3),
)  # fmt: skip
def test_runner_submits_never_raise_and_every_future_ends(det, slices, ops, in_flight, queue):
    image_sets = {seed: _image_set(det, seed) for seed in range(4)}
    runner = StreamingRunner(det, LaneConfig(max_in_flight=in_flight, queue_size=queue))
    futures = []
    for op, arg in ops:
        if op == "slice":
            futures.append(("slice", runner.submit_slice(slices[arg], arg, timestamp=1.0)))
        elif op == "images":
            futures.append(("images", runner.submit_images(image_sets[arg], timestamp=1.0)))
        elif futures:
            futures[arg % len(futures)][1].cancel()
    assert runner.close(timeout=60)
    dropped = 0
    for kind, f in futures:
        assert f.done()
        try:
            f.result(0)
        except CancelledError:
            pass
        except SliceDropped:
            assert kind == "slice"
            dropped += 1
        except ImagesSuperseded:
            assert kind == "images"
    assert dropped == runner.slices_dropped
