"""Each of the three tiny graphs exports (TorchScript exporter) with the dynamic axes of the contract and runs
in onnxruntime at other sizes than it was traced with, matching PyTorch."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import onnxruntime as ort
import pytest
import torch

from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset

TINY = get_preset("tiny")
K_CAMS = 2


def export(module: torch.nn.Module, args: tuple, path, inputs: list[str], outputs: list[str], dynamic: dict) -> ort.InferenceSession:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter is deprecated in favour of dynamo
        torch.onnx.export(
            module, args, str(path), dynamo=False, opset_version=17,
            input_names=inputs, output_names=outputs, dynamic_axes=dynamic,
        )
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def detector():
    torch.manual_seed(0)
    det = build_detector(TINY).eval()
    with torch.no_grad():
        # spread the scores so near-equal peaks (whose order fp rounding may swap) are rare
        heat = det.slice_net.head.tasks[0].branches["heatmap"][-1]
        heat.weight.normal_(0.0, 0.5)
        heat.bias.zero_()
    return det


def test_image_encoder_dynamic_images(detector, tmp_path):
    images = torch.randint(0, 256, (2, 72, 128, 3), dtype=torch.uint8)
    sess = export(detector.image_encoder, (images,), tmp_path / "enc.onnx", ["images"], ["features"],
                  {"images": {0: "J", 1: "H", 2: "W"}, "features": {0: "J", 2: "Hf", 3: "Wf"}})
    for shape in [(1, 72, 128, 3), (3, 70, 130, 3)]:
        x = torch.randint(0, 256, shape, dtype=torch.uint8)
        (out,) = sess.run(None, {"images": x.numpy()})
        with torch.no_grad():
            ref = detector.image_encoder(x).numpy()
        assert out.shape == ref.shape
        np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4)


def test_lifter_dynamic_cameras_and_quadrants(detector, tmp_path):
    g = TINY.grid
    hf, wf = TINY.image.feature_height, TINY.image.feature_width

    def inputs(j: int, q: int, seed: int):
        gen = torch.Generator().manual_seed(seed)
        shape = (q, K_CAMS, g.nz, g.quadrant_ny, g.quadrant_nx)
        return (
            torch.randn(j, TINY.channels, hf, wf, generator=gen),
            torch.randint(0, j * hf * wf + 1, shape, dtype=torch.int32, generator=gen),
            torch.rand(shape, generator=gen),
        )

    names = ["features", "lut_index", "lut_weight"]
    sess = export(detector.lifter, inputs(2, 2, 0), tmp_path / "lift.onnx", names, ["image_bev"],
                  {"features": {0: "J"}, "lut_index": {0: "Q"}, "lut_weight": {0: "Q"}, "image_bev": {0: "Q"}})
    for j, q in [(1, 1), (3, 4)]:
        x = inputs(j, q, j + q)
        (out,) = sess.run(None, {n: t.numpy() for n, t in zip(names, x)})
        with torch.no_grad():
            ref = detector.lifter(*x).numpy()
        assert out.shape == (q, TINY.channels, g.quadrant_ny, g.quadrant_nx)
        np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-5)


def slice_inputs(p, num_pillars: int, q: int, seed: int) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(seed)
    g = p.grid
    m = p.pillars.max_points_per_pillar
    mask = (torch.rand(num_pillars, m, generator=gen) < 0.5).float()
    return (
        torch.randn(num_pillars, m, 11, generator=gen) * mask[..., None],
        mask,
        torch.randperm(q * g.quadrant_ny * g.quadrant_nx, generator=gen)[:num_pillars],
        torch.randn(q, p.channels, g.quadrant_ny, g.quadrant_nx, generator=gen),
    )


def assert_same_detections(got: list[np.ndarray], ref: tuple[torch.Tensor, ...]) -> None:
    """Order-tolerant: every reference detection clearly inside the top K (score above the K-th by a margin)
    has an ORT detection of the same label at the same place with the same box."""
    boxes, scores, labels = got
    rb, rs, rl = (t.numpy() for t in ref)
    assert boxes.shape == rb.shape and labels.dtype == np.int64
    for qi in range(rb.shape[0]):
        np.testing.assert_allclose(np.sort(scores[qi]), np.sort(rs[qi]), rtol=1e-5, atol=1e-6)
        for i in np.flatnonzero(rs[qi] > rs[qi, -1] + 1e-5):
            d = np.abs(boxes[qi, :, :2] - rb[qi, i, :2]).max(axis=1) + 1e3 * (labels[qi] != rl[qi, i])
            j = int(np.argmin(d))
            assert d[j] < 1e-4, f"quadrant {qi}: reference detection {i} has no ORT counterpart"
            np.testing.assert_allclose(boxes[qi, j], rb[qi, i], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("use_image, multi_head", [(True, False), (False, False), (True, True)])
def test_slice_head_dynamic_pillars_and_quadrants(detector, tmp_path, use_image, multi_head):
    p = dataclasses.replace(TINY, use_image=use_image, head=dataclasses.replace(TINY.head, multi_head=multi_head))
    if use_image and not multi_head:
        net = detector.slice_net
    else:
        torch.manual_seed(1)
        net = build_detector(p).slice_net.eval()
        with torch.no_grad():
            for task in net.head.tasks:
                task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
                task.branches["heatmap"][-1].bias.zero_()
    dec = SliceDecoder(net, p).eval()
    names = ["pillar_features", "pillar_mask", "pillar_index", "image_bev"]
    outs = ["det_boxes", "det_scores", "det_labels"]
    dynamic = {"pillar_features": {0: "P"}, "pillar_mask": {0: "P"}, "pillar_index": {0: "P"}, "image_bev": {0: "Q"}}
    dynamic.update({n: {0: "Q"} for n in outs})
    sess = export(dec, slice_inputs(p, 100, 2, 0), tmp_path / "slice.onnx", names, outs, dynamic)
    assert [i.name for i in sess.get_inputs()] == names  # the LiDAR-only graph keeps image_bev as an input
    for num_pillars, q in [(37, 1), (250, 3), (0, 2)]:
        x = slice_inputs(p, num_pillars, q, num_pillars + q)
        got = sess.run(None, {n: t.numpy() for n, t in zip(names, x)})
        with torch.no_grad():
            ref = dec(*x)
        assert got[0].shape == (q, p.top_k, 9)
        assert_same_detections(got, ref)
