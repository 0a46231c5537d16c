"""Focal and L1 losses vs element-by-element formulas; task split; normalisation; config validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from streamdet.training.losses import CenterPointLoss, LossConfig, focal_loss_sum, gather_cells, l1_loss_sum, loss_terms


def make_case(seed, dtype=torch.float32, q=3, c=4, h=6, w=7, k=5):
    g = torch.Generator().manual_seed(seed)
    logits = (torch.randn(q, c, h, w, generator=g) * 3).to(dtype)
    target = torch.rand(q, c, h, w, generator=g) ** 4
    index = torch.randint(0, h * w, (q, k), generator=g)
    mask = torch.rand(q, k, generator=g) < 0.6
    label = torch.randint(0, c, (q, k), generator=g)
    for i in range(q):  # CenterPoint's targets are exactly 1 at every object's cell
        for j in range(k):
            if mask[i, j]:
                target[i, label[i, j]].view(-1)[index[i, j]] = 1.0
    return logits, target, index, mask, label


def naive_focal(logits, target, index, mask, label):
    p = np.clip(1 / (1 + np.exp(-logits.double().numpy())), 1e-4, 1 - 1e-4)
    t = target.double().numpy()
    neg = 0.0
    for v in np.ndindex(p.shape):
        neg += math.log(1 - p[v]) * p[v] ** 2 * (1 - t[v]) ** 4
    pos = 0.0
    q, k = index.shape
    w = p.shape[3]
    for i in range(q):
        for j in range(k):
            if mask[i, j]:
                cell = int(index[i, j])
                pp = p[i, int(label[i, j]), cell // w, cell % w]
                pos += math.log(pp) * (1 - pp) ** 2
    return -(neg + pos)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_focal_matches_naive(seed, dtype):
    logits, target, index, mask, label = make_case(seed, dtype)
    ours = float(focal_loss_sum(logits, target, index, mask, label))
    ref = naive_focal(logits.float(), target, index, mask, label)  # the loss upcasts to float32 first
    assert ours == pytest.approx(ref, rel=1e-5)


@pytest.mark.parametrize("seed", range(4))
def test_l1_and_gather_match_naive(seed):
    g = torch.Generator().manual_seed(seed)
    pred = torch.randn(2, 10, 5, 6, generator=g)
    index = torch.randint(0, 30, (2, 4), generator=g)
    mask = torch.rand(2, 4, generator=g) < 0.5
    target = torch.randn(2, 4, 10, generator=g)
    got = gather_cells(pred, index)
    for i in range(2):
        for j in range(4):
            cell = int(index[i, j])
            assert torch.equal(got[i, j], pred[i, :, cell // 6, cell % 6])
    ref = torch.zeros(10)
    for i in range(2):
        for j in range(4):
            if mask[i, j]:
                ref += (got[i, j] - target[i, j]).abs()
    torch.testing.assert_close(l1_loss_sum(pred, target, index, mask), ref)


def test_focal_perfect_prediction_is_small_and_wrong_is_large():
    target = torch.zeros(1, 1, 4, 4)
    target[0, 0, 1, 2] = 1.0
    index, mask, label = torch.tensor([[6]]), torch.tensor([[True]]), torch.tensor([[0]])
    good = torch.full((1, 1, 4, 4), -10.0)
    good[0, 0, 1, 2] = 10.0
    bad = -good
    assert focal_loss_sum(good, target, index, mask, label) < 1e-6
    assert focal_loss_sum(bad, target, index, mask, label) > 5


def test_loss_terms_split_tasks_and_combine():
    logits, target, index, mask, label = make_case(0, c=3)
    box = torch.randn(*index.shape, 10)
    reg = [torch.randn(3, ch, 6, 7) for ch in (2, 1, 3, 2, 2)]
    one = loss_terms([(logits, *reg)], ((0, 1, 2),), target, index, mask, label, box)
    # two tasks: class 1 alone, classes (2, 0) in that order; each task sees only its objects
    t1 = (logits[:, [1]], *reg)
    t2 = (logits[:, [2, 0]], *reg)
    two = loss_terms([t1, t2], ((1,), (2, 0)), target, index, mask, label, box)
    assert float(two.num_objects.sum()) == float(one.num_objects[0]) == float(mask.sum())
    torch.testing.assert_close(two.box.sum(0), one.box[0])
    # the single task's focal numerator equals the two tasks' negatives + positives over the same channels
    torch.testing.assert_close(two.heatmap.sum(), one.heatmap[0])
    crit = CenterPointLoss(LossConfig())
    total, parts = crit(one)
    n = float(mask.sum())
    weights = torch.tensor(LossConfig().code_weights)
    expect = float(one.heatmap[0]) / n + 0.25 * float((one.box[0] / n * weights).sum())
    assert float(total) == pytest.approx(expect, rel=1e-6)
    assert float(parts["heatmap"]) == pytest.approx(float(one.heatmap[0]) / n, rel=1e-6)
    # a global count and a world-size scale enter linearly
    total2, _ = crit(one, torch.tensor([2 * n]), scale=2.0)
    assert float(total2) == pytest.approx(float(total), rel=1e-6)


def test_no_objects_normalises_by_one():
    logits, target, index, mask, label = make_case(1)
    mask[:] = False
    terms = loss_terms([(logits, *[torch.zeros(3, ch, 6, 7) for ch in (2, 1, 3, 2, 2)])], ((0, 1, 2, 3),),
                       target, index, mask, label, torch.zeros(*index.shape, 10))  # fmt: skip
    total, _ = CenterPointLoss()(terms)
    assert torch.isfinite(total) and float(total) == pytest.approx(float(terms.heatmap[0]))


def test_gradient_flows_to_logits_and_regression():
    logits, target, index, mask, label = make_case(2)
    logits.requires_grad_(True)
    reg = [torch.randn(3, ch, 6, 7, requires_grad=True) for ch in (2, 1, 3, 2, 2)]
    terms = loss_terms([(logits, *reg)], ((0, 1, 2, 3),), target, index, mask, label, torch.randn(*index.shape, 10))
    CenterPointLoss()(terms)[0].backward()
    assert logits.grad.abs().sum() > 0 and all(r.grad.abs().sum() > 0 for r in reg)


@pytest.mark.parametrize("kwargs", [{"code_weights": (1.0,) * 9}, {"reg_weight": -1.0}, {"heatmap_weight": float("nan")}])
def test_config_validation(kwargs):
    with pytest.raises(ValueError, match="LossConfig"):
        LossConfig(**kwargs)
