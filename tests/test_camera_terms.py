"""Per-camera lifts (runtime_ort/camera_terms.py, lifter_split.py): the partial graph against a naive numpy
reference, a quadrant update from cached terms against the export's own lifter graph (fp32 and int8), the cache
(a new frame recomputes only its camera, a calibration swap every camera), and the refusals."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from click.testing import CliRunner

from streamdet.calibration.camera_lut import CameraLut, gather_share
from streamdet.calibration.perturb import perturb_rig
from streamdet.data.sample import load_bundled_sample
from streamdet.export.cli import main as export_main
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.camera_terms import distinct_rows, share_slots, sparse_lut_value, stack_rows
from streamdet.runtime_ort.lifter_split import SplitError, first_conv, sparse_lut, tail_graph, term_graph
from streamdet.runtime_ort.sessions import ort_session
from streamdet.training.checkpoint import save_weights

PRESET = dataclasses.replace(get_preset("tiny"), lifter=dataclasses.replace(get_preset("tiny").lifter, form="flat"))


def _export(tmp_path_factory, preset) -> Path:
    torch.manual_seed(7)
    model = build_detector(preset).eval()
    gen = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for bn in model.lifter.modules():
            if isinstance(bn, torch.nn.BatchNorm2d):
                bn.running_mean.copy_(torch.randn(bn.num_features, generator=gen) * 0.3)
                bn.weight.copy_(torch.rand(bn.num_features, generator=gen) + 0.5)
    ckpt = tmp_path_factory.mktemp("ckpt") / "flat2.pt"
    save_weights(ckpt, preset, model)
    out = tmp_path_factory.mktemp("export") / "flat2"
    result = CliRunner().invoke(export_main, ["--checkpoint", str(ckpt), "--int8", "--slices", "8", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory) -> Path:
    """A tiny flat-lifter export (fp32 + int8, the compact LUT layout of one height per voxel), seeded weights with
    spread BatchNorms so that the lifter's output is not flat. (The shipped model's two heights per voxel give
    shares of two slots: the partial graph's tests cover S > 1.)"""
    return _export(tmp_path_factory, PRESET)


@pytest.fixture(scope="module")
def separable_export_dir(tmp_path_factory) -> Path:
    """``export_dir``'s model with the flat lifter's residual factorised (LifterConfig.residual "separable"): the tail
    cut after the first conv holds two convs instead of one."""
    return _export(tmp_path_factory, dataclasses.replace(PRESET, lifter=dataclasses.replace(PRESET.lifter, residual="separable")))


@pytest.fixture(scope="module")
def two_height_export_dir(tmp_path_factory) -> Path:
    """The bundled ``small_v3_swift`` (fp32): two heights per voxel in its LUT, as every shipped fused model, so a
    camera's share is two slots wide, or one where it sees a quadrant at one height only."""
    out = tmp_path_factory.mktemp("export") / "swift"
    result = CliRunner().invoke(export_main, ["--preset", "small_v3_swift", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def _images(det: StreamingDetector, seed: int, names=None) -> dict[str, np.ndarray]:
    img = det.image
    rng = np.random.default_rng(seed)
    names = det.camera_names if names is None else names
    return {n: rng.integers(0, 256, (img.height, img.width, 3), dtype=np.uint8) for n in names}


def _bev(det: StreamingDetector, q: int) -> np.ndarray:
    return det.image_state.quadrants[q].bev


def _rel_l2(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-12))


# ---- a camera's term against the naive gather and projection ------------------------------------------------


@pytest.mark.parametrize("sparse", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n,z,s", [(1, 1, 1), (7, 3, 2), (40, 4, 3)])
def test_term_graph_equals_the_naive_gather_and_projection(seed, n, z, s, sparse):
    """term_graph (the convolution before the gather; its sparse and dense forms) against gather_share @ weight.T."""
    rng = np.random.default_rng(seed)
    c, hf, wf, c_out = 5, 4, 6, 3
    features = rng.standard_normal((c, hf, wf)).astype(np.float32)
    index = rng.integers(0, hf * wf + 1, (n, z, s)).astype(np.int64)  # hf * wf: the zero row (padding)
    weight = (rng.random((n, z, s)).astype(np.float32) * (index < hf * wf)).astype(np.float32)
    share = CameraLut(0, "CAM", np.arange(n, dtype=np.int64), index, weight)
    w = rng.standard_normal((c_out, z * c)).astype(np.float32)
    slots, slot_weights = share_slots(share, hf * wf)
    sess = ort_session(term_graph(w, c, (hf, wf), z, sparse=sparse).SerializeToString())
    if sparse:
        feeds = {"features": ort.OrtValue.ortvalue_from_numpy(features[None]),
                 "lut": sparse_lut_value(slots, slot_weights, z * (hf * wf + 1))}  # fmt: skip
        got = sess.run_with_ort_values(["term"], feeds)[0].numpy()
    else:
        (got,) = sess.run(None, {"features": features[None], "slots": slots, "weights": slot_weights})
    want = gather_share(features, share) @ w.T  # (N, C_out)
    assert got.shape == (n, c_out) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n,j", [(0, 3), (1, 1), (30, 4)])
def test_sparse_lut_is_the_dense_weight_matrix(seed, n, j):
    """sparse_lut against the naive dense (N, R) matrix: repeated slots within a row summed, zero weights left out,
    entries in row-major order."""
    rng = np.random.default_rng(seed)
    r = 6
    slots = rng.integers(0, r, (n, j)).astype(np.int64)  # few columns: repeats within a row
    weights = (rng.random((n, j)) * (rng.random((n, j)) < 0.7)).astype(np.float32)  # some zeros (padding)
    dense = np.zeros((n, r), np.float64)
    for i in range(n):
        for k in range(j):
            dense[i, slots[i, k]] += weights[i, k]
    values, coo = sparse_lut(slots, weights, r)
    assert values.dtype == np.float32 and coo.dtype == np.int64 and coo.shape == (values.size, 2)
    assert np.all(values != 0)
    got = np.zeros((n, r), np.float64)
    got[coo[:, 0], coo[:, 1]] = values
    np.testing.assert_allclose(got, dense, rtol=1e-6)
    flat = coo[:, 0] * r + coo[:, 1]
    assert np.all(np.diff(flat) > 0)  # row-major, no repeats


def test_sparse_term_graph_of_rows_without_weights_is_zero():
    """A share whose rows read only padding (every weight zero): an empty sparse LUT, zero terms of the right shape."""
    w = np.ones((3, 2 * 5), np.float32)
    sess = ort_session(term_graph(w, 5, (2, 2), 2).SerializeToString())
    lut = sparse_lut_value(np.zeros((4, 2), np.int64), np.zeros((4, 2), np.float32), 2 * 5)
    features = ort.OrtValue.ortvalue_from_numpy(np.ones((1, 5, 2, 2), np.float32))
    got = sess.run_with_ort_values(["term"], {"features": features, "lut": lut})[0].numpy()
    np.testing.assert_array_equal(got, np.zeros((4, 3), np.float32))


@pytest.mark.parametrize("slots,weights,match", [
    (np.zeros((2, 3), np.int64), np.zeros((2, 2), np.float32), "same"),
    (np.zeros((3,), np.int64), np.zeros((3,), np.float32), "same"),
    (np.full((1, 2), 6, np.int64), np.ones((1, 2), np.float32), "lie in"),
    (np.full((1, 2), -1, np.int64), np.ones((1, 2), np.float32), "lie in"),
])  # fmt: skip
def test_sparse_lut_refuses_bad_slots(slots, weights, match):
    with pytest.raises(ValueError, match=match):
        sparse_lut(slots, weights, 6)


def test_dense_term_graph_where_the_sparse_one_does_not_run(export_dir, monkeypatch):
    """An onnxruntime without SparseToDenseMatMul or sparse tensors: the dense term graph, the same quadrants."""
    import streamdet.runtime_ort.camera_terms as ct

    def no_sparse(*args, **kw):
        raise AttributeError("module 'onnxruntime' has no attribute 'SparseTensor'")

    sparse = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    monkeypatch.setattr(ct, "sparse_lut_value", no_sparse)
    dense = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    assert sparse._terms.sparse and not dense._terms.sparse
    images = _images(sparse, 5)
    for q in range(4):
        cams = sparse.quadrant_cameras([q])
        for det in (sparse, dense):
            det.update_images({n: images[n] for n in cams}, 1.0, quadrants=[q])
        assert np.abs(_bev(sparse, q) - _bev(dense, q)).max() <= 1e-5 * max(np.ptp(_bev(dense, q)), 1e-6)


def test_dense_term_graph_where_an_accelerator_provider_runs_the_sessions(export_dir, monkeypatch):
    """SparseToDenseMatMul has CPU kernels only: with an accelerator provider first, the dense form (the whole term
    graph on it). Simulated: the providers as a CUDA build would resolve them."""
    import streamdet.runtime_ort.camera_terms as ct

    monkeypatch.setattr(ct, "resolve_providers", lambda requested: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    monkeypatch.setattr(ct, "ort_session", lambda model, config: ort_session(model))  # this build has no CUDA
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    assert det.camera_terms and not det._terms.sparse


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n", [0, 1, 50])
def test_distinct_rows_give_back_every_row(seed, n):
    """distinct_rows against the rows it came from: each row is its distinct row, the distinct rows differ from one
    another, and rows that differ only in a weight's bits stay apart."""
    rng = np.random.default_rng(seed)
    slots = rng.integers(0, 4, (n, 3)).astype(np.int64)  # few values: many repeats
    weights = rng.choice(np.array([0.25, 0.5, -0.0, 0.0], np.float32), (n, 3))
    u_slots, u_weights, inverse = distinct_rows(slots, weights)
    assert inverse.shape == (n,) and inverse.dtype == np.int64
    np.testing.assert_array_equal(u_slots[inverse], slots)
    np.testing.assert_array_equal(u_weights[inverse].view(np.int32), weights.view(np.int32))  # -0.0 kept apart from 0.0
    key = np.concatenate([u_slots, u_weights.view(np.int32)], 1)
    assert len({tuple(r) for r in key}) == len(key)  # no two the same


def test_prepared_terms_give_the_same_quadrants_as_terms_made_per_lift(export_dir):
    """prepare_terms runs each camera once for all its quadrants; the lifts from those terms equal the lifts that
    made their terms one (quadrant, camera) at a time."""
    prepared = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    lazy = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    images = _images(prepared, 11)
    encoded = prepared.encode_images(images)
    prepared.prepare_terms(encoded)
    for q in range(4):
        cams = prepared.quadrant_cameras([q])
        for det in (prepared, lazy):
            det.update_images({n: images[n] for n in cams}, 1.0, quadrants=[q], encoded={n: encoded[n] for n in cams})
        assert np.abs(_bev(prepared, q) - _bev(lazy, q)).max() <= 1e-6 * max(np.ptp(_bev(lazy, q)), 1e-6)


def test_a_first_conv_that_is_not_the_flat_lifters_does_not_split(tiny_export):
    """The volume lifter's export form also starts with a 1x1 Conv, but per z plane, and what follows reads the
    graph's inputs again: no tail can be cut; a first Conv narrower than Z x C makes no term graph."""
    volume = onnx.load(str(tiny_export / "volumetric_lifter.onnx"))
    conv, weight, _ = first_conv(volume)
    with pytest.raises(SplitError, match="flat lifter"):
        tail_graph(volume, conv.output[0], (8, 32, 32), np.zeros(8, np.float32))
    with pytest.raises(SplitError, match="flat lifter"):
        term_graph(weight, weight.shape[1], (4, 6), 4)


# ---- quadrant updates from terms against the lifter graph -----------------------------------------------------


@pytest.mark.parametrize("exported", ["export_dir", "separable_export_dir"])
@pytest.mark.parametrize("seed", [0, 1])
def test_fp32_quadrant_updates_from_terms_equal_the_lifter_graph(request, exported, seed):
    export_dir = request.getfixturevalue(exported)
    terms = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    graph = StreamingDetector(export_dir, DetectorConfig(camera_terms=False))
    assert terms.camera_terms and not graph.camera_terms
    images = _images(terms, seed)
    for q in range(4):
        terms.update_images(images, 1.0, quadrants=[q])
        graph.update_images(images, 1.0, quadrants=[q])
        a, b = _bev(terms, q), _bev(graph, q)
        assert a.shape == b.shape and np.ptp(b) > 0
        assert np.abs(a - b).max() <= 1e-5 * np.ptp(b)
    terms.update_images(images, 2.0)  # a full update through terms too: the same sums up to float order
    graph.update_images(images, 2.0)
    a, b = terms.image_state.bev, graph.image_state.bev  # (4, C, Yq, Xq)
    assert a.shape == b.shape and np.abs(a - b).max() <= 1e-5 * np.ptp(b)


@pytest.mark.parametrize("exported", ["export_dir", "separable_export_dir"])
def test_int8_quadrant_updates_from_terms_stay_within_the_int8_lifters_error(request, exported):
    export_dir = request.getfixturevalue(exported)
    cfg = dict(precision="fp32", image_lane_precision="int8")
    terms = StreamingDetector(export_dir, DetectorConfig(**cfg, camera_terms=True))
    graph = StreamingDetector(export_dir, DetectorConfig(**cfg, camera_terms=False))
    fp32 = StreamingDetector(export_dir, DetectorConfig(camera_terms=False))
    sample = load_bundled_sample()
    img = terms.image
    images = dict(zip(sample.rig.names, sample.load_images((img.width, img.height))))
    images = {n: images[n] for n in terms.camera_names}
    for q in range(4):
        for det in (terms, graph, fp32):
            det.update_images(images, 1.0, quadrants=[q])
        ref = _bev(fp32, q)
        err_graph = _rel_l2(_bev(graph, q), ref)  # the int8 lifter graph's own error
        err_terms = _rel_l2(_bev(terms, q), ref)  # fp32 terms, int8 tail
        assert err_terms <= max(2 * err_graph, 0.02), (q, err_terms, err_graph)
    for det in (terms, graph, fp32):  # full updates: terms against the whole int8 lifter graph
        det.update_images(images, 2.0)
    ref = fp32.image_state.bev
    err_graph, err_terms = _rel_l2(graph.image_state.bev, ref), _rel_l2(terms.image_state.bev, ref)
    assert err_terms <= max(2 * err_graph, 0.02), (err_terms, err_graph)


def test_a_full_update_through_terms_runs_each_camera_once_and_one_tail_per_quadrant(export_dir):
    """No lifter graph run; six term runs (one per camera, all its quadrants), four tails; a second full update
    of new frames the same again (nothing kept from the first applies)."""
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    for seed in (3, 4):
        det.update_images(_images(det, seed), float(seed))
    summary = det.stats.summary()
    assert "volumetric_lifter" not in summary
    assert summary["lifter_partial"]["count"] == 2 * len(det.camera_names)
    assert summary["lifter_tail"]["count"] == 2 * 4


def test_missing_cameras_contribute_nothing_as_zero_maps_do(export_dir):
    terms = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    graph = StreamingDetector(export_dir, DetectorConfig(camera_terms=False))
    q = 0
    cams = terms.quadrant_cameras([q])
    others = [n for n in terms.camera_names if n not in cams]
    images = _images(terms, 3, cams[:1])  # one of the quadrant's cameras
    terms.update_images(images, 1.0, quadrants=[q])
    graph.update_images(images, 1.0, quadrants=[q])
    assert np.abs(_bev(terms, q) - _bev(graph, q)).max() <= 1e-5 * max(np.ptp(_bev(graph, q)), 1e-6)
    # none of them: the update clears the quadrant, whose slices read the lift of no camera (the bias alone here)
    images = _images(terms, 3, others[:1])
    assert terms.update_images(images, 2.0, quadrants=[q]).cleared == (q,)
    assert graph.update_images(images, 2.0, quadrants=[q]).cleared == (q,)
    assert terms.image_state is None and graph.image_state is None
    blank, want = terms.blank_image_bev, graph.blank_image_bev
    assert np.abs(blank - want).max() <= 1e-5 * max(np.ptp(want), 1e-6) and np.ptp(want) > 0


# ---- the cache ------------------------------------------------------------------------------------------------


def _partials(det: StreamingDetector) -> int:
    return det.stats.summary().get("lifter_partial", {}).get("count", 0)


def test_prepared_terms_are_reused_and_a_new_frame_recomputes_only_its_camera(export_dir):
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    images = _images(det, 4)
    encoded = det.encode_images(images)
    made = det.prepare_terms(encoded)
    feeds = {q: det.quadrant_cameras([q]) for q in range(4)}
    assert made == sum(len(c) for c in feeds.values())
    runs = _partials(det)
    assert runs == len({n for c in feeds.values() for n in c})  # one term run per camera, all its quadrants at once
    for q in range(4):
        det.update_images({n: images[n] for n in feeds[q]}, 1.0, quadrants=[q], encoded={n: encoded[n] for n in feeds[q]})
    assert _partials(det) == runs  # every lift summed cached terms
    name = feeds[0][0]
    new = det.encode_images(_images(det, 5, [name]))
    for q in range(4):
        given = {n: (new[n] if n == name else encoded[n]) for n in feeds[q]}
        det.update_images({n: images[n] for n in feeds[q]}, 2.0, quadrants=[q], encoded=given)
    assert _partials(det) == runs + sum(name in c for c in feeds.values())  # only the new frame's terms


def test_terms_after_a_calibration_swap_use_the_new_lut(export_dir):
    terms = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    graph = StreamingDetector(export_dir, DetectorConfig(camera_terms=False))
    sample = load_bundled_sample()
    images = _images(terms, 6)
    encoded = terms.encode_images(images)
    terms.prepare_terms(encoded)
    rig = perturb_rig(sample.rig, 3.0, 0.3, seed=1).resized(terms.image.width, terms.image.height)
    for det in (terms, graph):
        det.set_calibration(rig, relift=False)
    for q in range(4):
        cams = terms.quadrant_cameras([q])
        terms.update_images({n: images[n] for n in cams}, 1.0, quadrants=[q], encoded={n: encoded[n] for n in cams})
        graph.update_images({n: images[n] for n in cams}, 1.0, quadrants=[q])
        assert np.abs(_bev(terms, q) - _bev(graph, q)).max() <= 1e-5 * max(np.ptp(_bev(graph, q)), 1e-6)


def test_a_calibration_swap_makes_the_new_luts_pieces_before_the_next_update(export_dir, monkeypatch):
    """set_calibration makes the new LUT's shares and sparse LUTs (the caller pays); the updates after it, full and
    per quadrant, build none."""
    import streamdet.runtime_ort.camera_terms as ct

    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    sample = load_bundled_sample()
    rig = perturb_rig(sample.rig, 3.0, 0.3, seed=5).resized(det.image.width, det.image.height)
    det.set_calibration(rig, relift=False)
    built = []
    monkeypatch.setattr(ct, "sparse_lut_value", lambda *a: built.append(a) or pytest.fail("a sparse LUT built in an update"))
    monkeypatch.setattr(ct, "camera_luts", lambda *a: pytest.fail("shares made in an update"))
    images = _images(det, 9)
    det.update_images(images, 1.0)
    for q in range(4):
        det.update_images(_images(det, 10 + q), 2.0 + q, quadrants=[q])
    assert not built


def test_the_tail_runs_on_one_thread_whatever_the_image_lanes_threads(export_dir):
    """onnxruntime's ScatterND-add races over its updates with more than one intra-op thread (a cell two cameras see
    lost one camera's term in some runs): the tail session keeps one thread, the term graph gets the lane's; the
    quadrants of repeated updates of the same images are then equal bit for bit."""
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True, image_lane_threads=2))
    assert det._terms._tail.get_session_options().intra_op_num_threads == 1
    assert det._terms._term_graph.get_session_options().intra_op_num_threads == 2
    images = _images(det, 12)
    det.update_images(images, 1.0)
    first = det.image_state.bev.copy()
    for k in range(5):
        det.update_images({n: im.copy() for n, im in images.items()}, 2.0 + k)
        np.testing.assert_array_equal(det.image_state.bev, first)


def test_sparse_luts_are_dropped_with_their_quadrant_luts(export_dir):
    """Calibration swaps make new LUTs: the sparse LUTs kept are only those of shares still kept (two LUTs)."""
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    sample = load_bundled_sample()
    images = _images(det, 2)
    for seed in range(4):
        rig = perturb_rig(sample.rig, 3.0, 0.3, seed=seed).resized(det.image.width, det.image.height)
        det.set_calibration(rig, relift=False)
        det.update_images(images, float(seed))
    terms = det._terms
    live = {id(s) for _, shares in terms._shares.values() for s in shares}
    assert len(terms._shares) == 8 and terms._luts
    assert all(set(key) <= live for key in terms._luts)


# ---- choices and refusals -------------------------------------------------------------------------------------


def test_auto_uses_terms_where_the_lifter_splits_and_not_elsewhere(export_dir, tiny_export):
    assert StreamingDetector(export_dir).camera_terms  # flat lifter, fp32 lane
    assert not StreamingDetector(tiny_export).camera_terms  # volume lifter
    assert not StreamingDetector(tiny_export, DetectorConfig(precision="fp16")).camera_terms  # not split
    assert StreamingDetector(export_dir).prepare_terms({}) == 0


def test_required_terms_on_a_volume_lifter_raise_naming_why(tiny_export):
    with pytest.raises(ValueError, match="camera_terms=True.*flat lifter"):
        StreamingDetector(tiny_export, DetectorConfig(camera_terms=True))


@pytest.mark.parametrize("bad", ["yes", 1, 0.0])
def test_camera_terms_config_must_be_none_or_a_bool(bad):
    with pytest.raises(ValueError, match="camera_terms"):
        DetectorConfig(camera_terms=bad)


def test_prepare_terms_refuses_bad_feature_maps(export_dir):
    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    name = det.camera_names[0]
    with pytest.raises(ValueError, match="unknown camera"):
        det.prepare_terms({"CAM_NOPE": np.zeros((1,), np.float32)})
    with pytest.raises(ValueError, match="float32 feature map"):
        det.prepare_terms({name: np.zeros((2, 2, 2), np.float32)})


def test_pieces_that_do_not_match_the_lifter_are_refused(export_dir, monkeypatch):
    """The check at load: terms that read the z-stacked channels in another order than the lifter (what a changed
    lifter form would do) differ from the fp32 lifter: auto falls back to the lifter graph, True raises."""
    import streamdet.runtime_ort.camera_terms as ct

    right = ct.term_graph

    def wrong_order(weight, channels, feature_hw, heights, **kw):
        swapped = weight.reshape(weight.shape[0], heights, channels)[:, :, ::-1].reshape(weight.shape)  # c reversed
        return right(np.ascontiguousarray(swapped), channels, feature_hw, heights, **kw)

    monkeypatch.setattr(ct, "term_graph", wrong_order)
    assert not StreamingDetector(export_dir).camera_terms
    with pytest.raises(ValueError, match="differ from the fp32 lifter"):
        StreamingDetector(export_dir, DetectorConfig(camera_terms=True))


def test_quadrant_map_scores_the_four_ways_of_lifting(export_dir, tiny_train_data):
    """benchmarks/quadrant_map.py: full updates and per-quadrant updates through the lifter graph score the same
    (the same function); per-camera lifts, full or per quadrant, score too (fp32: the same sums up to float order)."""
    import re

    from streamdet.benchmarks.quadrant_map import main

    result = CliRunner().invoke(main, ["--data", str(tiny_train_data), "--export-dir", str(export_dir), "--samples", "2"])
    assert result.exit_code == 0, result.output
    scores = dict(re.findall(r"fp32 image lane \+ fp32 slices, ([a-z, -]+): 2 samples, mAP ([\d.]+)", result.output))
    assert list(scores) == ["full update, lifter graph", "per-quadrant, lifter graph", "full update, per-camera lifts",
                            "per-quadrant, per-camera lifts"]  # fmt: skip
    assert scores["full update, lifter graph"] == scores["per-quadrant, lifter graph"]
    for label in ("full update, per-camera lifts", "per-quadrant, per-camera lifts"):
        assert abs(float(scores[label]) - float(scores["full update, lifter graph"])) <= 1.0


def test_quadrant_map_refuses_per_camera_lifts_on_a_volume_lifter(tiny_export, tiny_train_data):
    from streamdet.benchmarks.quadrant_map import main

    result = CliRunner().invoke(main, ["--data", str(tiny_train_data), "--export-dir", str(tiny_export), "--samples", "1"])
    assert result.exit_code == 1 and "flat lifter" in result.output


def test_warm_up_with_per_camera_lifts_leaves_the_same_quadrant_updates(export_dir):
    warm, cold = (StreamingDetector(export_dir, DetectorConfig(camera_terms=True)) for _ in range(2))
    warm.warm_up()
    assert warm.image_state is None and warm.stats.summary() == {}
    images = _images(warm, 8)
    for det in (warm, cold):
        for q in range(4):
            det.update_images(images, 1.0, quadrants=[q])
    np.testing.assert_array_equal(warm.image_state.bev, cold.image_state.bev)


def test_the_fp32_lifter_of_an_int8_lane_is_checked_too(export_dir, tmp_path):
    """An int8 image lane opens no session of the fp32 lifter (only its per-camera split reads it): a foreign graph
    there, its sha256 updated, is refused, not taken for a lifter that does not split (verification audit)."""
    import json
    import shutil

    from streamdet.runtime_ort.manifest import ManifestError, sha256_file

    d = tmp_path / "i8"
    shutil.copytree(export_dir, d)
    shutil.copy(d / "slice_head.onnx", d / "volumetric_lifter.onnx")
    m = json.loads((d / "manifest.json").read_text())
    for g in m["graphs"]:
        if g["file"] == "volumetric_lifter.onnx":
            g["sha256"] = sha256_file(d / "volumetric_lifter.onnx")
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ManifestError, match=r"volumetric_lifter.onnx \(volumetric_lifter, fp32\): the graph's inputs are"):
        StreamingDetector(d, DetectorConfig(image_lane_precision="int8"))


@pytest.mark.parametrize("quadrants", [None, [2]])
def test_close_during_a_terms_lift_raises_detector_closed(export_dir, quadrants):
    """close() from another thread while an update lifts through per-camera terms: that update raises DetectorClosed
    (what close() promises every later graph run), never an AttributeError of released terms."""
    from streamdet.runtime_ort.detector import DetectorClosed

    det = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    assert det.camera_terms
    lift = det._lift_quadrants

    def close_first(*args, **kwargs):  # the close lands after the update chose the terms path
        det.close()
        return lift(*args, **kwargs)

    det._lift_quadrants = close_first
    with pytest.raises(DetectorClosed, match="closed"):
        det.update_images(_images(det, 0), 1.0, quadrants=quadrants)


# ---- one camera's shares of different widths ------------------------------------------------------------------


def _lut_with_a_second_slot(lut, camera: str, quadrant: int):
    """``lut`` where ``camera`` holds a second slot (the next feature cell of its map) in every voxel of ``quadrant``
    that has a free slot, so that its share there is two slots wide and one slot wide in its other quadrants: what a
    camera that reaches a neighbouring quadrant at one height only makes of a LUT with two heights per voxel."""
    cells = lut.feature_width * lut.feature_height
    j = lut.camera_names.index(camera)
    index, weight = lut.index.copy(), lut.weight.copy()
    q_index = index[quadrant]  # (K, Z, Yq, Xq)
    valid = q_index != lut.sentinel
    mine = valid & (q_index // cells == j)
    row = np.where(mine, q_index, -1).max(axis=0)  # (Z, Yq, Xq) the camera's one slot (one height per voxel)
    z, y, x = np.nonzero(mine.any(axis=0) & ~valid[-1])
    second = np.where(row[z, y, x] % cells + 1 < cells, row[z, y, x] + 1, row[z, y, x] - 1)
    q_index[valid.sum(axis=0)[z, y, x], z, y, x] = second
    count = (q_index != lut.sentinel).sum(axis=0)  # (Z, Yq, Xq)
    index[quadrant] = q_index
    weight[quadrant] = np.where(q_index != lut.sentinel, 1.0 / np.maximum(count, 1), 0.0)
    return dataclasses.replace(lut, index=index, weight=weight)


@pytest.mark.parametrize("sparse", [True, False])
def test_a_camera_two_slots_wide_in_one_quadrant_and_one_in_another_lifts_as_the_lifter_graph(export_dir, monkeypatch, sparse):
    """A noisy calibration once made a camera reach a neighbouring quadrant at one height only: its shares differed
    in width, and set_calibration (the sparse LUTs of a camera's quadrants) and full updates (one term run per camera
    for all its quadrants) failed to stack them. Narrower shares are padded with zero-weight slots now."""
    import streamdet.runtime_ort.camera_terms as ct
    from streamdet.calibration.camera_lut import camera_luts

    def no_sparse(*args, **kw):
        raise AttributeError("module 'onnxruntime' has no attribute 'SparseTensor'")

    if not sparse:
        monkeypatch.setattr(ct, "sparse_lut_value", no_sparse)
    terms = StreamingDetector(export_dir, DetectorConfig(camera_terms=True))
    graph = StreamingDetector(export_dir, DetectorConfig(camera_terms=False))
    assert terms._terms.sparse == sparse
    camera = next(c for c in terms.camera_names if len([q for q in range(4) if c in terms.quadrant_cameras([q])]) > 1)
    quadrant = next(q for q in range(4) if camera in terms.quadrant_cameras([q]))
    lut = _lut_with_a_second_slot(terms.lut, camera, quadrant)
    cells = lut.feature_width * lut.feature_height
    widths = {q: s.index.shape[2] for q, ql in enumerate(terms._luts_of(lut)) for s in camera_luts(ql, cells) if s.camera_name == camera}
    assert widths[quadrant] == 2 and 1 in widths.values(), widths
    images = _images(terms, 8)
    for det in (terms, graph):
        det.set_calibration(lut, relift=False)
        det.update_images(images, 1.0)  # the full update: one term run per camera, all its quadrants
    a, b = terms.image_state.bev, graph.image_state.bev  # (4, C, Yq, Xq)
    assert a.shape == b.shape and np.ptp(b) > 0
    assert np.abs(a - b).max() <= 1e-5 * np.ptp(b)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stacked_rows_of_shares_of_different_widths_give_each_shares_sparse_rows(seed):
    rng = np.random.default_rng(seed)
    table_rows, pad_row = 50, 9
    widths, counts = (4, 8, 2), (3, 0, 5)
    slots = tuple(rng.integers(0, table_rows, (n, w)) for n, w in zip(counts, widths))
    weights = tuple(rng.random((n, w)).astype(np.float32) for n, w in zip(counts, widths))
    stacked_slots, stacked_weights = stack_rows(slots, weights, pad_row)
    assert stacked_slots.shape == stacked_weights.shape == (sum(counts), max(widths))
    dense = np.zeros((sum(counts), table_rows))  # the naive reference: each row's weights at its slots
    start = 0
    for s, w in zip(slots, weights):
        for i in range(s.shape[0]):
            np.add.at(dense[start + i], s[i], w[i])
        start += s.shape[0]
    values, coo = sparse_lut(stacked_slots, stacked_weights, table_rows)
    got = np.zeros_like(dense)
    got[coo[:, 0], coo[:, 1]] = values
    np.testing.assert_allclose(got, dense, rtol=1e-6, atol=1e-7)
    one_slots, one_weights = stack_rows(slots[:1], weights[:1], pad_row)
    assert one_slots is slots[0] and one_weights is weights[0]


@pytest.mark.parametrize("angle_deg,shift_m,seed,mixed", [(5.0, 0.5, 0, False), (5.0, 0.5, 1, False), (10.0, 1.0, 7, True)])
def test_noisy_calibrations_of_a_two_height_lut_lift_as_the_lifter_graph(two_height_export_dir, angle_deg, shift_m, seed, mixed):
    """set_calibration with noisy rigs, then a full update: per-camera terms give the lifter graph's BEV. At (10 deg,
    1 m) seed 7 CAM_FRONT_LEFT reaches a neighbouring quadrant at one height only: its shares are one and two slots
    wide, which set_calibration failed to stack before the padding (``mixed``: that case, checked)."""
    from streamdet.calibration.camera_lut import camera_luts

    terms = StreamingDetector(two_height_export_dir, DetectorConfig(camera_terms=True))
    graph = StreamingDetector(two_height_export_dir, DetectorConfig(camera_terms=False))
    rig = perturb_rig(load_bundled_sample().rig, angle_deg, shift_m, seed=seed).resized(terms.image.width, terms.image.height)
    images = _images(terms, seed)
    for det in (terms, graph):
        det.set_calibration(rig, relift=False)
        det.update_images(images, 1.0)
    cells = terms._terms.feature_hw[0] * terms._terms.feature_hw[1]
    widths: dict[str, set[int]] = {}
    for qlut in terms._luts_of(terms.lut):
        for share in camera_luts(qlut, cells):
            widths.setdefault(share.camera_name, set()).add(share.index.shape[2])
    assert any(len(w) > 1 for w in widths.values()) == mixed, widths
    a, b = terms.image_state.bev, graph.image_state.bev  # (4, C, Yq, Xq)
    assert a.shape == b.shape and np.ptp(b) > 0
    assert np.abs(a - b).max() <= 1e-5 * np.ptp(b)


def test_partial_lift_benchmark_reports_a_quadrant_no_camera_sees(export_dir, tmp_path):
    """benchmarks/partial_lift.py on a LUT whose quadrant 3 no camera sees: that quadrant is reported as having
    nothing to lift, the others are checked against the lifter and timed."""
    import json
    import shutil

    from streamdet.benchmarks import partial_lift
    from streamdet.calibration.lut import Lut
    from streamdet.runtime_ort.manifest import sha256_file

    out = tmp_path / "blind"
    shutil.copytree(export_dir, out)
    lut = Lut.load(out / "lut.npz")
    index, weight = lut.index.copy(), lut.weight.copy()
    index[3], weight[3] = lut.sentinel, 0.0
    dataclasses.replace(lut, index=index, weight=weight).save(out / "lut.npz")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["lut"]["sha256"] = sha256_file(out / "lut.npz")  # a re-export with that LUT
    (out / "manifest.json").write_text(json.dumps(manifest))
    result = partial_lift.run(out, rounds=3, threads=1)
    parity = {p["quadrant"]: p for p in result["parity"]}
    assert parity[3]["max_abs_diff"] is None
    assert all(parity[q]["max_abs_diff"] <= 1e-4 * max(parity[q]["output_range"], 1.0) for q in range(3))
    assert {r["quadrant"] for r in result["per_camera_update"]} == {0, 1, 2}
    lines = partial_lift.report(result)
    assert "quadrant 3: no camera sees it, nothing to lift" in lines
    assert not any(line.startswith("q3:") for line in lines)
