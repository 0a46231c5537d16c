"""Pillar feature net and the scatter to stacked quadrant maps, against naive loops."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from streamdet.models.pillars import PillarFeatureNet, gather_pillars, scatter_pillars

M, C = 6, 5


def naive_pfn(net: PillarFeatureNet, feats: np.ndarray, mask: np.ndarray) -> np.ndarray:
    w = net.linear.weight.detach().double().numpy()  # (C, 11)
    bn = net.norm
    mean, var = bn.running_mean.double().numpy(), bn.running_var.double().numpy()
    gamma, beta = bn.weight.detach().double().numpy(), bn.bias.detach().double().numpy()
    out = np.zeros((feats.shape[0], w.shape[0]))
    for p in range(feats.shape[0]):
        best = np.zeros(w.shape[0])  # a pillar without real points stays zero
        for m in range(feats.shape[1]):
            if mask[p, m] == 0:
                continue
            y = (w @ feats[p, m] - mean) / np.sqrt(var + bn.eps) * gamma + beta
            best = np.maximum(best, np.maximum(y, 0))
        out[p] = best
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pillar_net_matches_naive(seed, dtype):
    torch.manual_seed(seed)
    net = PillarFeatureNet(11, C).eval()
    with torch.no_grad():
        net.norm.running_mean.normal_()
        net.norm.running_var.uniform_(0.5, 2.0)
        net.norm.bias.normal_()
    net = net.to(dtype)
    rng = np.random.default_rng(seed)
    p = 9
    mask = (rng.random((p, M)) < 0.6).astype(np.float64)
    mask[0] = 0  # an all-padding pillar
    feats = rng.normal(size=(p, M, 11)) * mask[..., None]  # padding rows are zero, as pillarize writes them
    with torch.no_grad():
        out = net(torch.from_numpy(feats).to(dtype), torch.from_numpy(mask).to(dtype))
    assert out.shape == (p, C) and out.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(out.double().numpy(), naive_pfn(net, feats, mask), rtol=tol, atol=tol)


def test_eval_fusion_equals_the_unfused_layers():
    """Eval folds BN into the linear layer; it must compute BN(running stats) exactly as the layers would."""
    torch.manual_seed(0)
    net = PillarFeatureNet(11, C).eval()
    with torch.no_grad():
        net.norm.running_mean.normal_()
        net.norm.running_var.uniform_(0.5, 2.0)
        net.norm.weight.uniform_(0.5, 1.5)
        net.norm.bias.normal_()
        mask = (torch.rand(50, M) < 0.5).float()
        feats = torch.randn(50, M, 11) * mask[..., None]
        y = net.norm(net.linear(feats).reshape(-1, C)).reshape(50, M, C)
        ref = (torch.relu(y) * mask[..., None]).amax(dim=1)
        torch.testing.assert_close(net(feats, mask), ref)


def naive_scatter(pf: np.ndarray, index: np.ndarray, q: int, yq: int, xq: int) -> np.ndarray:
    out = np.zeros((q, pf.shape[1], yq, xq), pf.dtype)
    for p, flat in enumerate(index):
        qi, rem = divmod(int(flat), yq * xq)
        row, col = divmod(rem, xq)
        out[qi, :, row, col] = pf[p]
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("q", [1, 2, 4])
def test_scatter_matches_naive(seed, q):
    rng = np.random.default_rng(seed)
    yq, xq = 6, 8
    p = int(rng.integers(1, q * yq * xq))
    index = rng.permutation(q * yq * xq)[:p].astype(np.int64)
    pf = rng.normal(size=(p, C)).astype(np.float32)
    like = torch.empty(q, 3, yq, xq)  # only the shape counts, channels may differ
    out = scatter_pillars(torch.from_numpy(pf), torch.from_numpy(index), like)
    assert out.shape == (q, C, yq, xq)
    np.testing.assert_array_equal(out.numpy(), naive_scatter(pf, index, q, yq, xq))


def test_scatter_empty_slice_gives_zero_maps():
    out = scatter_pillars(torch.zeros(0, C), torch.zeros(0, dtype=torch.int64), torch.empty(2, C, 4, 4))
    assert out.shape == (2, C, 4, 4) and torch.count_nonzero(out) == 0


def test_scatter_out_of_range_index_raises():
    with pytest.raises((IndexError, RuntimeError)):
        scatter_pillars(torch.ones(1, C), torch.tensor([2 * 4 * 4]), torch.empty(2, C, 4, 4))


@pytest.mark.parametrize("seed", [0, 1])
def test_training_mode_uses_batch_statistics_over_all_slots(seed):
    torch.manual_seed(seed)
    net = PillarFeatureNet(11, C).train()
    rng = np.random.default_rng(seed)
    mask = (rng.random((7, M)) < 0.6).astype(np.float32)
    feats = (rng.normal(size=(7, M, 11)) * mask[..., None]).astype(np.float32)
    out = net(torch.from_numpy(feats), torch.from_numpy(mask))
    y = feats.reshape(-1, 11).astype(np.float64) @ net.linear.weight.detach().double().numpy().T  # (P*M, C)
    y = (y - y.mean(0)) / np.sqrt(y.var(0) + net.norm.eps)  # BN with gamma 1, beta 0 at init
    ref = (np.maximum(y, 0).reshape(7, M, C) * mask[..., None]).max(axis=1)
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-4, atol=1e-5)
    out.sum().backward()
    assert net.linear.weight.grad is not None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("q", [1, 3])
def test_gather_pillars_equals_scatter(seed, q, dtype):
    gen = torch.Generator().manual_seed(seed)
    yq, xq = 6, 8
    p = int(torch.randint(0, q * yq * xq + 1, (1,), generator=gen))  # 0 to every cell
    index = torch.randperm(q * yq * xq, generator=gen)[:p].sort().values
    feats = torch.randn(p, C, generator=gen, dtype=dtype)
    like = torch.empty(q, C, yq, xq, dtype=dtype)
    got = gather_pillars(feats, index, like)
    assert got.shape == (q, C, yq, xq) and got.dtype == dtype
    torch.testing.assert_close(got, scatter_pillars(feats, index, like), rtol=0, atol=0)


def test_gather_pillars_empty_slice_and_bad_index():
    out = gather_pillars(torch.zeros(0, C), torch.zeros(0, dtype=torch.int64), torch.empty(2, C, 4, 4))
    assert out.shape == (2, C, 4, 4) and torch.count_nonzero(out) == 0
    with pytest.raises((IndexError, RuntimeError)):
        gather_pillars(torch.ones(1, C), torch.tensor([2 * 4 * 4]), torch.empty(2, C, 4, 4))

