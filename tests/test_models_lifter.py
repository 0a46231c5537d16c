"""Volumetric lifter vs a naive per-voxel loop and a numpy re-implementation of its 3D convolutions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from streamdet.models.lifter import VolumetricLifter, batch_lut_index, gather_volume
from streamdet.models.presets import LifterConfig

J, C, HF, WF = 2, 4, 5, 7
Q, K, Z, YQ, XQ = 2, 2, 4, 3, 5


def random_lut(rng: np.random.Generator, j: int = J, q: int = Q) -> tuple[np.ndarray, np.ndarray]:
    """A LUT like calibration/lut.py writes: per voxel 0..K cameras on distinct slots, weights 1/count."""
    rows = j * HF * WF
    index = np.full((q, K, Z, YQ, XQ), rows, np.int32)
    weight = np.zeros((q, K, Z, YQ, XQ), np.float32)
    seen = rng.integers(0, K + 1, size=(q, Z, YQ, XQ))  # cameras seeing each voxel
    for k in range(K):
        valid = seen > k
        index[:, k][valid] = rng.integers(0, rows, size=valid.sum())
        weight[:, k][valid] = 1.0 / seen[valid]
    return index, weight


def naive_gather(features: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    j, c, hf, wf = features.shape
    sentinel = j * hf * wf
    q, k, z, yq, xq = index.shape
    out = np.zeros((q, c, z, yq, xq), np.float64)
    for qi in range(q):
        for zi in range(z):
            for yi in range(yq):
                for xi in range(xq):
                    for ki in range(k):
                        r = int(index[qi, ki, zi, yi, xi])
                        if r == sentinel:
                            continue
                        cam, rem = divmod(r, hf * wf)
                        v, u = divmod(rem, wf)
                        out[qi, :, zi, yi, xi] += weight[qi, ki, zi, yi, xi] * features[cam, :, v, u]
    return out


def np_conv3d(x: np.ndarray, w: np.ndarray, b: np.ndarray | None, stride_z: int) -> np.ndarray:
    """Same-padded 3D convolution (kernel 1 or 3), stride only along z. x (Q, C, Z, Y, X), w (O, C, kz, ky, kx)."""
    kz = w.shape[2]
    p = kz // 2
    xp = np.pad(x, ((0, 0), (0, 0), (p, p), (p, p), (p, p)))
    q, _, z, y, xx = x.shape
    zo = (z + 2 * p - kz) // stride_z + 1
    out = np.zeros((q, w.shape[0], zo, y, xx))
    for dz in range(kz):
        for dy in range(kz):
            for dx in range(kz):
                win = xp[:, :, dz : dz + stride_z * (zo - 1) + 1 : stride_z, dy : dy + y, dx : dx + xx]
                out += np.einsum("qczyx,oc->qozyx", win, w[:, :, dz, dy, dx])
    if b is not None:
        out += b[None, :, None, None, None]
    return out


def np_bn(x: np.ndarray, bn: torch.nn.BatchNorm3d) -> np.ndarray:
    shape = (1, -1, 1, 1, 1)
    mean, var = bn.running_mean.double().numpy(), bn.running_var.double().numpy()
    gamma, beta = bn.weight.detach().double().numpy(), bn.bias.detach().double().numpy()
    return (x - mean.reshape(shape)) / np.sqrt(var.reshape(shape) + bn.eps) * gamma.reshape(shape) + beta.reshape(shape)


def np_lifter(lifter: VolumetricLifter, features, index, weight) -> np.ndarray:
    def w(conv):
        return conv.weight.detach().double().numpy()

    v = naive_gather(features, index, weight)
    v = np_bn(v, lifter.input_norm)
    v = np.maximum(np_conv3d(v, w(lifter.project), lifter.project.bias.detach().double().numpy(), 1), 0)
    v = v + np.maximum(np_bn(np_conv3d(v, w(lifter.residual[0]), None, 1), lifter.residual[1]), 0)
    v = np.maximum(np_bn(np_conv3d(v, w(lifter.z_down[0]), None, 2), lifter.z_down[1]), 0)
    q, c, z, y, x = v.shape
    v = v.reshape(q, c, z // 2, 2, y, x).mean(axis=3)  # AvgPool z 2
    return v.max(axis=2)  # (Q, C, Y, X)


def randomise_bn(module: torch.nn.Module, gen: torch.Generator) -> None:
    for m in module.modules():
        if isinstance(m, torch.nn.BatchNorm3d):
            m.running_mean.copy_(torch.randn(m.num_features, generator=gen) * 0.3)
            m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
            m.bias.data.copy_(torch.randn(m.num_features, generator=gen) * 0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gather_matches_naive_loop(seed):
    rng = np.random.default_rng(seed)
    feats = rng.normal(size=(J, C, HF, WF)).astype(np.float32)
    index, weight = random_lut(rng)
    out = gather_volume(torch.from_numpy(feats), torch.from_numpy(index), torch.from_numpy(weight))
    assert out.shape == (Q, C, Z, YQ, XQ)
    np.testing.assert_allclose(out.numpy(), naive_gather(feats, index, weight), rtol=1e-5, atol=1e-6)


def test_gather_all_sentinels_is_zero():
    feats = torch.randn(J, C, HF, WF)
    index = torch.full((Q, K, Z, YQ, XQ), J * HF * WF, dtype=torch.int32)
    weight = torch.zeros(Q, K, Z, YQ, XQ)
    assert torch.count_nonzero(gather_volume(feats, index, weight)) == 0


def test_gather_rejects_out_of_range_index():
    index = torch.full((Q, K, Z, YQ, XQ), J * HF * WF + 1, dtype=torch.int32)  # one past the sentinel
    with pytest.raises((IndexError, RuntimeError)):
        gather_volume(torch.randn(J, C, HF, WF), index, torch.zeros(index.shape))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lifter_matches_numpy_reference(seed, dtype):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    lifter = VolumetricLifter(LifterConfig(), C).eval()
    with torch.no_grad():
        randomise_bn(lifter, gen)
    lifter = lifter.to(dtype)
    rng = np.random.default_rng(seed)
    feats = rng.normal(size=(J, C, HF, WF))
    index, weight = random_lut(rng)
    with torch.no_grad():
        out = lifter(torch.from_numpy(feats).to(dtype), torch.from_numpy(index), torch.from_numpy(weight).to(dtype))
    assert out.shape == (Q, C, YQ, XQ) and out.dtype == dtype
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(out.double().numpy(), np_lifter(lifter, feats, index, weight), rtol=tol, atol=tol)


def test_lifter_backward_reaches_features():
    lifter = VolumetricLifter(LifterConfig(), C).train()
    feats = torch.randn(J, C, HF, WF, requires_grad=True)
    index, weight = random_lut(np.random.default_rng(0))
    lifter(feats, torch.from_numpy(index), torch.from_numpy(weight)).sum().backward()
    assert feats.grad is not None and torch.isfinite(feats.grad).all() and feats.grad.abs().sum() > 0


def test_batch_lut_index_matches_separate_gathers():
    rng = np.random.default_rng(3)
    feats_a = torch.from_numpy(rng.normal(size=(2, C, HF, WF)).astype(np.float32))
    feats_b = torch.from_numpy(rng.normal(size=(1, C, HF, WF)).astype(np.float32))
    idx_a, w_a = random_lut(rng, j=2, q=2)
    idx_b, w_b = random_lut(rng, j=1, q=1)
    idx = batch_lut_index([torch.from_numpy(idx_a), torch.from_numpy(idx_b)], [2, 1], HF * WF)
    assert idx.dtype == torch.int32 and idx.shape == (3, K, Z, YQ, XQ)
    joint = gather_volume(torch.cat([feats_a, feats_b]), idx, torch.from_numpy(np.concatenate([w_a, w_b])))
    torch.testing.assert_close(joint[:2], gather_volume(feats_a, torch.from_numpy(idx_a), torch.from_numpy(w_a)))
    torch.testing.assert_close(joint[2:], gather_volume(feats_b, torch.from_numpy(idx_b), torch.from_numpy(w_b)))
    assert int(idx.max()) == 3 * HF * WF  # every sentinel moved to the batch's one sentinel


def test_batch_lut_index_malformed():
    with pytest.raises(ValueError, match="got 1 LUT indices but 2 image counts"):
        batch_lut_index([torch.zeros(1, K, Z, YQ, XQ, dtype=torch.int32)], [1, 1], HF * WF)
    with pytest.raises(ValueError, match="at least one sample"):
        batch_lut_index([], [], HF * WF)
