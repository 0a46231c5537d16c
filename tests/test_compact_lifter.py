"""CompactLifter (models/compact_lifter.py) against the K-slot lifter it wraps (the naive reference), tiny preset."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from streamdet.calibration.compact_lut import compact_lut
from streamdet.models.compact_lifter import CompactLifter
from streamdet.models.detector import build_detector
from streamdet.models.export_form import to_export_form
from streamdet.models.lifter_fold import FoldedLifter
from streamdet.models.presets import get_preset


def _lut(rng: np.random.Generator, shape: tuple[int, ...], sentinel: int, multi_share: float):
    """A K = 2 LUT: every voxel's first slot valid or empty, its second valid for ``multi_share`` of the voxels."""
    index = rng.integers(0, sentinel, shape).astype(np.int32)  # (Q, K, Z, Yq, Xq)
    index[:, 0][rng.random(index[:, 0].shape) < 0.2] = sentinel  # seen by no camera
    index[:, 1][rng.random(index[:, 1].shape) >= multi_share] = sentinel
    weight = (rng.random(shape).astype(np.float32) + 0.1) * (index < sentinel)
    return index, weight


def _compact_args(index: np.ndarray, weight: np.ndarray, sentinel: int) -> tuple[torch.Tensor, ...]:
    lut = compact_lut(index, weight, sentinel)
    voxels = lut.voxel_shape  # (Q, Z, Yq, Xq)
    arrays = (lut.multi_index, lut.multi_weight, lut.final_index.reshape(voxels), lut.final_weight.reshape(voxels))
    return tuple(torch.from_numpy(a) for a in arrays)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("folded", [True, False])
@pytest.mark.parametrize("multi_share", [0.0, 0.3])  # 0.0: no voxel seen by two cameras (M = 0)
@pytest.mark.parametrize("q", [1, 2])
def test_compact_lifter_is_the_k_slot_lifter(seed, folded, multi_share, q):
    torch.manual_seed(seed)
    det = build_detector(get_preset("tiny")).eval()
    lifter = to_export_form(det).volumetric_lifter if folded else det.lifter
    assert isinstance(lifter, FoldedLifter) == folded
    g = det.preset.grid
    rng = np.random.default_rng(seed)
    j, hf, wf = 3, 5, 7
    sentinel = j * hf * wf
    index, weight = _lut(rng, (q, 2, g.nz, g.quadrant_ny, g.quadrant_nx), sentinel, multi_share)
    features = torch.randn(j, det.preset.channels, hf, wf)
    with torch.no_grad():
        want = lifter(features, torch.from_numpy(index), torch.from_numpy(weight))
        got = CompactLifter(lifter)(features, *_compact_args(index, weight, sentinel))
    assert got.shape == want.shape == (q, det.preset.channels, g.quadrant_ny, g.quadrant_nx)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_compact_lifter_refuses_another_module():
    with pytest.raises(TypeError, match="Linear"):
        CompactLifter(torch.nn.Linear(2, 2))
