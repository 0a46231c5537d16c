"""The three graph modules and StreamDetector: shapes for every preset, training step, LiDAR-only variant."""

from __future__ import annotations

import dataclasses
import time

import pytest
import torch

from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import SliceNet, StreamDetector, build_detector
from streamdet.models.presets import Preset, get_preset

K_CAMS = 2


def make_inputs(p: Preset, q: int, num_pillars: int, j: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    g = p.grid
    m = p.pillars.max_points_per_pillar
    rows = j * p.image.feature_height * p.image.feature_width
    lut_shape = (q, K_CAMS, g.nz, g.quadrant_ny, g.quadrant_nx)
    mask = (torch.rand(num_pillars, m, generator=gen) < 0.5).float()
    return {
        "images": torch.randint(0, 256, (j, p.image.height_px, p.image.width_px, 3), dtype=torch.uint8, generator=gen),
        "lut_index": torch.randint(0, rows + 1, lut_shape, dtype=torch.int32, generator=gen),
        "lut_weight": torch.rand(lut_shape, generator=gen) * 0.5,
        "pillar_features": torch.randn(num_pillars, m, 11, generator=gen) * mask[..., None],
        "pillar_mask": mask,
        "pillar_index": torch.randperm(q * g.quadrant_ny * g.quadrant_nx, generator=gen)[:num_pillars],
    }


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
@pytest.mark.parametrize("multi_head", [False, True])
def test_shapes_of_every_preset(name, multi_head):
    p = get_preset(name)
    p = dataclasses.replace(p, head=dataclasses.replace(p.head, multi_head=multi_head))
    g = p.grid
    q, j, num_pillars = 2, 2, 100
    with torch.device("meta"):
        det = build_detector(p).eval()
        x = {
            "images": torch.empty(j, p.image.height_px, p.image.width_px, 3, dtype=torch.uint8),
            "lut_index": torch.zeros(q, K_CAMS, g.nz, g.quadrant_ny, g.quadrant_nx, dtype=torch.int32),
            "lut_weight": torch.empty(q, K_CAMS, g.nz, g.quadrant_ny, g.quadrant_nx),
            "pillar_features": torch.empty(num_pillars, p.pillars.max_points_per_pillar, 11),
            "pillar_mask": torch.empty(num_pillars, p.pillars.max_points_per_pillar),
            "pillar_index": torch.zeros(num_pillars, dtype=torch.int64),
        }
        feats = det.image_encoder(x["images"])
        assert feats.shape == (j, p.channels, p.image.feature_height, p.image.feature_width)
        image_bev = det.lifter(feats, x["lut_index"], x["lut_weight"])
        assert image_bev.shape == (q, p.channels, g.quadrant_ny, g.quadrant_nx)
        maps = det.slice_net(x["pillar_features"], x["pillar_mask"], x["pillar_index"], image_bev)
        hh, wh = p.head_map_size
        assert [tuple(m.shape) for m in maps] == [(q, ch, hh, wh) for ch in (10, 2, 1, 3, 2, 2)]
        boxes, scores, labels = SliceDecoder(det.slice_net, p)(x["pillar_features"], x["pillar_mask"], x["pillar_index"], image_bev)
    assert boxes.shape == (q, p.top_k, 9) and scores.shape == (q, p.top_k) and labels.dtype == torch.int64


def test_tiny_training_step_is_fast_and_reaches_every_part():
    seed = 0
    torch.manual_seed(seed)
    p = get_preset("tiny")
    det = build_detector(p).train()
    x = make_inputs(p, q=2, num_pillars=300, seed=seed)

    def step() -> float:
        det.zero_grad()
        start = time.process_time()  # CPU time of one thread: robust to the other jobs on a shared machine
        maps = det(**x)
        sum(m.square().mean() for m in maps).backward()
        return time.process_time() - start

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        step()  # warm-up: the first forward and backward allocate
        best = min(step() for _ in range(2))
    finally:
        torch.set_num_threads(threads)
    assert best < 0.5, f"tiny forward + backward took {best:.3f} s of CPU"
    for name in ("image_encoder.backbone.conv1.weight", "lifter.project.weight", "slice_net.pillar_net.linear.weight"):
        grad = det.get_parameter(name).grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name


def test_lidar_only_ignores_image_bev_values():
    torch.manual_seed(0)
    p = dataclasses.replace(get_preset("tiny"), use_image=False)
    net = SliceNet(p).eval()
    x = make_inputs(p, q=3, num_pillars=50)
    args = (x["pillar_features"], x["pillar_mask"], x["pillar_index"])
    g = p.grid
    with torch.no_grad():
        a = net(*args, torch.zeros(3, p.channels, g.quadrant_ny, g.quadrant_nx))
        b = net(*args, torch.randn(3, p.channels, g.quadrant_ny, g.quadrant_nx))
    for ma, mb in zip(a, b):
        assert ma.shape[0] == 3
        torch.testing.assert_close(ma, mb, rtol=0, atol=0)


def test_lidar_only_detector_needs_no_images():
    p = dataclasses.replace(get_preset("tiny"), use_image=False)
    det = build_detector(p).eval()
    assert det.image_encoder is None and det.lifter is None
    x = make_inputs(p, q=2, num_pillars=20)
    with torch.no_grad():
        maps = det(None, None, None, x["pillar_features"], x["pillar_mask"], x["pillar_index"], num_quadrants=2)
    assert maps[0].shape == (2, 10, *p.head_map_size)
    with pytest.raises(ValueError, match="needs num_quadrants"):
        det(None, None, None, x["pillar_features"], x["pillar_mask"], x["pillar_index"])
    with pytest.raises(RuntimeError, match="use_image=False: there is no image lane"):
        det.image_bev(x["images"], x["lut_index"], x["lut_weight"])


def test_image_detector_requires_images():
    p = get_preset("tiny")
    det = StreamDetector(p).eval()
    x = make_inputs(p, q=1, num_pillars=5)
    with pytest.raises(ValueError, match="images, lut_index and lut_weight are required"):
        det(None, x["lut_index"], x["lut_weight"], x["pillar_features"], x["pillar_mask"], x["pillar_index"])


def test_empty_slice_runs():
    p = get_preset("tiny")
    det = build_detector(p).eval()
    x = make_inputs(p, q=1, num_pillars=0)
    with torch.no_grad():
        maps = det(**x)
    assert all(torch.isfinite(m).all() for m in maps)
