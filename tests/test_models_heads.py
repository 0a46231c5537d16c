"""CenterPoint heads: output layout, bias init, and the multi-head merge into CLASS_NAMES order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from streamdet.core.classes import CLASS_NAMES
from streamdet.models.bev_encoder import BevEncoder
from streamdet.models.heads import HEAD_OUTPUTS, CenterHead
from streamdet.models.presets import NUSCENES_TASKS, HeadConfig, get_preset

CHANNELS = {"heatmap": 10, "reg": 2, "height": 1, "dim": 3, "rot": 2, "vel": 2}


@pytest.mark.parametrize("multi_head", [False, True])
def test_output_layout_and_bias_init(multi_head):
    torch.manual_seed(0)
    head = CenterHead(HeadConfig(head_channels=8, multi_head=multi_head), 12).eval()
    with torch.no_grad():
        maps = head(torch.randn(3, 12, 5, 7))
    assert len(maps) == len(HEAD_OUTPUTS) == 6
    for name, m in zip(HEAD_OUTPUTS, maps):
        assert m.shape == (3, CHANNELS[name], 5, 7), name
    for task in head.tasks:
        torch.testing.assert_close(task.branches["heatmap"][-1].bias, torch.full_like(task.branches["heatmap"][-1].bias, -2.19))
    assert len(head.tasks) == (6 if multi_head else 1)


def test_task_grouping_is_nuscenes():
    head = CenterHead(HeadConfig(multi_head=True, head_channels=4), 4)
    names = [[CLASS_NAMES[k] for k in t] for t in head.task_classes]
    assert names == [list(t) for t in NUSCENES_TASKS]
    assert names == [
        ["car"],
        ["truck", "construction_vehicle"],
        ["bus", "trailer"],
        ["barrier"],
        ["motorcycle", "bicycle"],
        ["pedestrian", "traffic_cone"],
    ]


def test_multi_head_heatmap_channels_follow_class_names():
    head = CenterHead(HeadConfig(multi_head=True, head_channels=4), 4).eval()
    with torch.no_grad():
        for t, task in zip(head.task_classes, head.tasks):
            out = task.branches["heatmap"][-1]
            out.weight.zero_()
            out.bias.copy_(torch.tensor([100.0 + k for k in t]))  # channel of class k reads 100 + k
        heat = head(torch.randn(2, 4, 3, 3))[0]
    for k in range(len(CLASS_NAMES)):
        assert torch.all(heat[:, k] == 100.0 + k), CLASS_NAMES[k]


def naive_merge(per_task, task_classes):
    """Per cell: the heatmap in class order, regressions from the task of the highest-logit class."""
    q, _, h, w = per_task[0][0].shape
    heat = np.zeros((q, len(CLASS_NAMES), h, w), np.float32)
    for maps, classes in zip(per_task, task_classes):
        for i, k in enumerate(classes):
            heat[:, k] = maps[0][:, i].numpy()
    owner = {k: t for t, classes in enumerate(task_classes) for k in classes}
    merged = [heat]
    for out in range(1, 6):
        ch = per_task[0][out].shape[1]
        reg = np.zeros((q, ch, h, w), np.float32)
        for qi in range(q):
            for r in range(h):
                for c in range(w):
                    t = owner[int(np.argmax(heat[qi, :, r, c]))]
                    reg[qi, :, r, c] = per_task[t][out][qi, :, r, c].numpy()
        merged.append(reg)
    return merged


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_multi_head_merge_matches_naive(seed):
    torch.manual_seed(seed)
    head = CenterHead(HeadConfig(multi_head=True, head_channels=8), 6).eval()
    with torch.no_grad():
        for task in head.tasks:
            task.branches["heatmap"][-1].bias.normal_(0.0, 2.0)  # make every task win somewhere
        x = torch.randn(2, 6, 5, 6)
        merged = head(x)
        per_task = head.forward_tasks(x)
    for got, want in zip(merged, naive_merge(per_task, head.task_classes)):
        np.testing.assert_array_equal(got.numpy(), want)


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
def test_bev_encoder_reaches_head_stride(name):
    p = get_preset(name)
    g = p.grid
    with torch.device("meta"):
        enc = BevEncoder(p.bev, 2 * p.channels)
        out = enc(torch.empty(2, 2 * p.channels, g.quadrant_ny, g.quadrant_nx))
    assert out.shape == (2, p.bev.out_channels, *p.head_map_size)


def test_single_and_multi_head_share_the_head_input():
    p = get_preset("tiny")
    multi = dataclasses.replace(p.head, multi_head=True)
    a = CenterHead(p.head, 16)
    b = CenterHead(multi, 16)
    assert a.shared[0].weight.shape == b.shared[0].weight.shape
