"""Per-camera shares of a quadrant LUT (calibration/camera_lut.py) and the per-camera partial lift built on them
(benchmarks/partial_lift.py): the shares' sum is the K-slot gather, the split lifter graph is the lifter."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.calibration.camera_lut import camera_luts, gather_share
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.quadrant_lut import QuadrantLut, quadrant_luts
from streamdet.data.sample import load_bundled_sample


def _naive_quadrant(features: np.ndarray, qlut: QuadrantLut) -> np.ndarray:
    """(Yq * Xq, Z * C) z-major rows of the quadrant, voxel by voxel and slot by slot from the (J', C, Hf, Wf) maps."""
    j, c, hf, wf = features.shape
    _, k, z, yq, xq = qlut.index.shape
    table = np.concatenate([features.transpose(0, 2, 3, 1).reshape(j * hf * wf, c), np.zeros((1, c), features.dtype)])
    out = np.zeros((yq * xq, z * c), features.dtype)
    for y in range(yq):
        for x in range(xq):
            for zz in range(z):
                for kk in range(k):
                    out[y * xq + x, zz * c : (zz + 1) * c] += qlut.weight[0, kk, zz, y, x] * table[qlut.index[0, kk, zz, y, x]]
    return out


def _summed_shares(features: np.ndarray, qlut: QuadrantLut, cells_per_map: int) -> np.ndarray:
    _, c, _, _ = features.shape
    _, _, z, yq, xq = qlut.index.shape
    out = np.zeros((yq * xq, z * c), features.dtype)
    for j, share in enumerate(camera_luts(qlut, cells_per_map)):
        assert share.camera_name == qlut.camera_names[j]
        out[share.cells] += gather_share(features[j], share)
    return out


def _random_qlut(rng: np.random.Generator, cameras: int, cells_per_map: int, k: int = 4, z: int = 2, yq: int = 5, xq: int = 6) -> QuadrantLut:
    """A quadrant LUT with valid slots first in every voxel (the Lut's order), some voxels seen by no camera."""
    sentinel = cameras * cells_per_map
    count = rng.integers(0, k + 1, (z, yq, xq))  # valid slots per voxel
    valid = np.arange(k)[:, None, None, None] < count[None]  # (K, Z, Yq, Xq)
    index = np.where(valid, rng.integers(0, sentinel, (k, z, yq, xq)), sentinel).astype(np.int32)
    weight = np.where(valid, rng.uniform(0.1, 1.0, (k, z, yq, xq)), 0.0).astype(np.float32)
    names = tuple(f"CAM_{i}" for i in range(cameras))
    return QuadrantLut(0, tuple(range(cameras)), names, index[None], weight[None])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_shares_sum_to_the_slot_gather_on_random_luts(seed, dtype):
    rng = np.random.default_rng(seed)
    hf, wf, cameras, c = 3, 4, 3, 5
    qlut = _random_qlut(rng, cameras, hf * wf)
    features = rng.standard_normal((cameras, c, hf, wf)).astype(dtype)
    got = _summed_shares(features, qlut, hf * wf)
    ref = _naive_quadrant(features, qlut)
    np.testing.assert_allclose(got, ref, rtol=1e-5 if dtype == np.float32 else 1e-12, atol=1e-6 if dtype == np.float32 else 1e-12)


@pytest.mark.parametrize("quadrant", [0, 1, 2, 3])
def test_shares_of_a_real_lut_with_two_heights(quadrant):
    """The bundled nuScenes rig, two heights per voxel (the shipped preset's): every valid slot lands in exactly one
    share, each share's cells are the cells its camera sees, and the sum is the gather."""
    sample = load_bundled_sample()
    lut = build_lut(sample.rig, feature_stride=8, image_size=(192, 108), heights_per_voxel=2)
    qlut = quadrant_luts(lut)[quadrant]
    cells = lut.feature_height * lut.feature_width
    shares = camera_luts(qlut, cells)
    sentinel = qlut.num_feature_maps * cells
    valid = qlut.index[0] != sentinel  # (K, Z, Yq, Xq)
    assert sum(int((s.weight != 0).sum()) for s in shares) == int((valid & (qlut.weight[0] != 0)).sum())
    for j, share in enumerate(shares):
        sees = (valid & (qlut.index[0] // cells == j)).any(axis=(0, 1)).reshape(-1)
        np.testing.assert_array_equal(share.cells, np.flatnonzero(sees))
        assert share.index.max() <= cells and share.index.min() >= 0 and share.index.dtype == np.int64
    rng = np.random.default_rng(quadrant)
    features = rng.standard_normal((qlut.num_feature_maps, 4, lut.feature_height, lut.feature_width)).astype(np.float32)
    table = np.concatenate([features.transpose(0, 2, 3, 1).reshape(-1, 4), np.zeros((1, 4), np.float32)])
    k, z, yq, xq = qlut.index.shape[1:]
    ref = (table[qlut.index[0]] * qlut.weight[0][..., None]).sum(axis=0)  # (Z, Yq, Xq, C)
    ref = ref.transpose(1, 2, 0, 3).reshape(yq * xq, z * 4)
    np.testing.assert_allclose(_summed_shares(features, qlut, cells), ref, rtol=1e-5, atol=1e-6)


def test_a_quadrant_no_camera_sees_has_no_shares():
    qlut = QuadrantLut(2, (), (), np.full((1, 1, 2, 3, 3), 12, np.int32), np.zeros((1, 1, 2, 3, 3), np.float32))
    assert camera_luts(qlut, 12) == ()


@pytest.mark.parametrize("bad", [0, -3, True, 2.5, "12"])
def test_cells_per_map_must_be_a_positive_int(bad):
    qlut = _random_qlut(np.random.default_rng(0), 2, 12)
    with pytest.raises(ValueError, match="cells_per_map"):
        camera_luts(qlut, bad)


def test_malformed_luts_are_refused():
    rng = np.random.default_rng(0)
    qlut = _random_qlut(rng, 2, 12)
    too_far = QuadrantLut(0, qlut.camera_indices, qlut.camera_names, qlut.index + 100, qlut.weight)
    with pytest.raises(ValueError, match="LUT rows must lie in"):
        camera_luts(too_far, 12)
    flat = QuadrantLut(0, qlut.camera_indices, qlut.camera_names, qlut.index[0], qlut.weight[0])
    with pytest.raises(ValueError, match=r"\(1, K, Z, Yq, Xq\)"):
        camera_luts(flat, 12)


# ---- the split lifter graph (runtime_ort/lifter_split.py) ------------------------------------------------------


@pytest.mark.parametrize("sparse", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_partial_graphs_and_tail_rebuild_a_flat_lifter(tmp_path, seed, sparse):
    """A small flat lifter exported as the exporter does (FlatLifterExport), cut after its first convolution:
    one term per camera (runtime_ort/camera_terms.py) + the tail graph give the lifter's output, with every row's
    term or with the distinct rows' terms and each row's index into them (what the runtime feeds)."""
    torch = pytest.importorskip("torch")
    import onnx
    import onnxruntime as ort

    from streamdet.benchmarks.timing import ort_session
    from streamdet.runtime_ort.camera_terms import distinct_rows, share_slots, sparse_lut_value
    from streamdet.runtime_ort.lifter_split import first_conv, tail_graph, term_graph
    from streamdet.models.flat_lifter import FlatLifter, FlatLifterExport

    torch.manual_seed(seed)
    c, nz, hf, wf, cameras = 6, 2, 3, 4, 3
    lifter = FlatLifter(c, nz)
    for m in lifter.modules():  # non-trivial BatchNorm statistics, so the folding matters
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    export = FlatLifterExport(lifter.eval()).eval()
    rng = np.random.default_rng(seed)
    qlut = _random_qlut(rng, cameras, hf * wf, k=4, z=nz, yq=5, xq=6)
    features = rng.standard_normal((cameras, c, hf, wf)).astype(np.float32)
    path = tmp_path / "lifter.onnx"
    args = (torch.from_numpy(features), torch.from_numpy(qlut.index), torch.from_numpy(qlut.weight))
    torch.onnx.export(export, args, str(path), input_names=["features", "lut_index", "lut_weight"],
                      output_names=["image_bev"], opset_version=17, dynamo=False)  # fmt: skip
    (ref,) = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        None, {"features": features, "lut_index": qlut.index, "lut_weight": qlut.weight})  # fmt: skip
    model = onnx.load(str(path))
    conv, weight, bias = first_conv(model)
    term = ort_session(term_graph(weight, c, (hf, wf), nz, sparse=sparse), 1)

    def run_term(j: int, slots: np.ndarray, slot_weights: np.ndarray) -> np.ndarray:
        if not sparse:
            return term.run(None, {"features": features[j : j + 1], "slots": slots, "weights": slot_weights})[0]
        lut = sparse_lut_value(slots, slot_weights, nz * (hf * wf + 1))
        return term.run_with_ort_values(["term"], {"features": ort.OrtValue.ortvalue_from_numpy(features[j : j + 1]), "lut": lut})[0].numpy()

    terms, cells, distinct, rows = [], [], [], []
    for j, share in enumerate(camera_luts(qlut, hf * wf)):
        slots, slot_weights = share_slots(share, hf * wf)
        terms.append(run_term(j, slots, slot_weights))
        cells.append(share.cells)
        u_slots, u_weights, inverse = distinct_rows(slots, slot_weights)
        rows.append(inverse + sum(len(d) for d in distinct))
        distinct.append(run_term(j, u_slots, u_weights))
    tail = ort_session(tail_graph(model, conv.output[0], (c, 5, 6), bias), 1)
    stacked = np.concatenate(terms)
    cells = np.concatenate(cells)[:, None]
    (got,) = tail.run(None, {"terms": stacked, "rows": np.arange(len(stacked), dtype=np.int64), "cells": cells})
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    (got,) = tail.run(None, {"terms": np.concatenate(distinct), "rows": np.concatenate(rows), "cells": cells})
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def test_first_conv_refuses_a_volume_lifter(tmp_path):
    torch = pytest.importorskip("torch")
    import onnx

    from streamdet.runtime_ort.lifter_split import first_conv

    net = torch.nn.Sequential(torch.nn.Conv3d(2, 2, 3, padding=1))
    path = tmp_path / "vol.onnx"
    torch.onnx.export(net, (torch.zeros(1, 2, 3, 4, 4),), str(path), opset_version=17, dynamo=False)
    with pytest.raises(ValueError, match="not a 2D 1x1"):
        first_conv(onnx.load(str(path)))
