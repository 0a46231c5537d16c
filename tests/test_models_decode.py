"""In-graph decode vs a naive numpy reference; the centre encoding is its exact inverse."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from streamdet.models.decode import SliceDecoder, decode_head_maps, encode_center
from streamdet.models.detector import SliceNet
from streamdet.models.presets import get_preset

NUM_CLASSES = 10


def random_maps(rng: np.random.Generator, q: int, h: int, w: int) -> list[np.ndarray]:
    return [
        rng.normal(0.0, 2.0, size=(q, NUM_CLASSES, h, w)),  # heatmap logits
        rng.uniform(-0.5, 0.5, size=(q, 2, h, w)),  # reg
        rng.normal(size=(q, 1, h, w)),  # height
        rng.normal(0.0, 0.5, size=(q, 3, h, w)),  # log size
        rng.normal(size=(q, 2, h, w)),  # sin, cos
        rng.normal(size=(q, 2, h, w)),  # vel
    ]


def naive_decode(maps: list[np.ndarray], cell_m: float, k: int):
    heat, reg, height, dim, rot, vel = maps
    q, ncls, h, w = heat.shape
    boxes = np.zeros((q, k, 9))
    scores = np.zeros((q, k))
    labels = np.zeros((q, k), np.int64)
    for qi in range(q):
        cands = []
        for c in range(ncls):
            for r in range(h):
                for col in range(w):
                    hood = heat[qi, c, max(r - 1, 0) : r + 2, max(col - 1, 0) : col + 2]
                    if heat[qi, c, r, col] >= hood.max():  # a peak of its 3x3 neighbourhood
                        cands.append((1.0 / (1.0 + np.exp(-heat[qi, c, r, col])), c, r, col))
        cands.sort(key=lambda t: -t[0])
        assert len(cands) >= k, "test maps must have at least k peaks"
        for i, (s, c, r, col) in enumerate(cands[:k]):
            scores[qi, i], labels[qi, i] = s, c
            boxes[qi, i] = [
                (col + 0.5 + reg[qi, 0, r, col]) * cell_m,
                (r + 0.5 + reg[qi, 1, r, col]) * cell_m,
                height[qi, 0, r, col],
                *np.exp(dim[qi, :, r, col]),
                np.arctan2(rot[qi, 0, r, col], rot[qi, 1, r, col]),
                *vel[qi, :, r, col],
            ]
    return boxes, scores, labels


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("q", [1, 3])
def test_decode_matches_naive(seed, dtype, q):
    rng = np.random.default_rng(seed)
    h, w, k, cell_m = 6, 9, 25, 0.8
    maps = random_maps(rng, q, h, w)
    maps = [m.astype(np.float32 if dtype == torch.float32 else np.float64) for m in maps]
    boxes, scores, labels = decode_head_maps(tuple(torch.from_numpy(m) for m in maps), cell_m, k)
    assert boxes.shape == (q, k, 9) and scores.shape == (q, k) and labels.shape == (q, k)
    assert boxes.dtype == dtype and labels.dtype == torch.int64
    ref_boxes, ref_scores, ref_labels = naive_decode([m.astype(np.float64) for m in maps], cell_m, k)
    np.testing.assert_array_equal(labels.numpy(), ref_labels)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(scores.numpy(), ref_scores, rtol=tol, atol=tol)
    np.testing.assert_allclose(boxes.numpy(), ref_boxes, rtol=tol, atol=tol)


def test_flat_plateau_keeps_every_equal_cell():
    """max-pool peak picking keeps ties (hmax == heat), as CenterPoint does."""
    heat = torch.zeros(1, NUM_CLASSES, 4, 4)
    heat[0, 3] = 1.0  # one class, all equal: every cell is a peak
    rest = [torch.zeros(1, ch, 4, 4) for ch in (2, 1, 3, 2, 2)]
    _, scores, labels = decode_head_maps((heat, *rest), 1.0, 16)
    assert torch.all(labels == 3)
    torch.testing.assert_close(scores, torch.full((1, 16), torch.sigmoid(torch.tensor(1.0)).item()))


def test_decode_empty_quadrant_stack():
    maps = tuple(torch.zeros(0, ch, 4, 4) for ch in (NUM_CLASSES, 2, 1, 3, 2, 2))
    boxes, scores, labels = decode_head_maps(maps, 1.0, 5)
    assert boxes.shape == (0, 5, 9) and scores.shape == (0, 5) and labels.shape == (0, 5)


def test_decode_rejects_top_k_beyond_cells():
    maps = tuple(torch.zeros(1, ch, 2, 2) for ch in (NUM_CLASSES, 2, 1, 3, 2, 2))
    with pytest.raises(ValueError, match=rf"top_k must be at most classes x cells of the head map \({NUM_CLASSES * 4}\), got {NUM_CLASSES * 4 + 1}$"):
        decode_head_maps(maps, 1.0, NUM_CLASSES * 4 + 1)
    boxes, scores, labels = decode_head_maps(maps, 1.0, NUM_CLASSES * 4)  # every class x cell: the most there is
    assert boxes.shape == (1, NUM_CLASSES * 4, 9) and scores.shape == labels.shape == (1, NUM_CLASSES * 4)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_encode_center_inverts_decode(seed):
    rng = np.random.default_rng(seed)
    cell_m = 0.8
    x = rng.uniform(0, 25.6, 100)
    y = rng.uniform(0, 25.6, 100)
    row, col, rx, ry = encode_center(x, y, cell_m)
    assert row.dtype == np.int64 and np.all((rx >= -0.5) & (rx < 0.5)) and np.all((ry >= -0.5) & (ry < 0.5))
    np.testing.assert_allclose((col + 0.5 + rx) * cell_m, x, atol=1e-5)
    np.testing.assert_allclose((row + 0.5 + ry) * cell_m, y, atol=1e-5)
    # decode reads the same cell: put the targets into maps and decode them back
    h = w = 32
    heat = np.full((1, NUM_CLASSES, h, w), -10.0)
    reg = np.zeros((1, 2, h, w))
    for i in range(3):  # three well separated objects
        heat[0, i, row[i], col[i]] = 5.0 + i
        reg[0, :, row[i], col[i]] = rx[i], ry[i]
    maps = [heat, reg] + [np.zeros((1, ch, h, w)) for ch in (1, 3, 2, 2)]
    boxes, _, labels = decode_head_maps(tuple(torch.from_numpy(m) for m in maps), cell_m, 3)
    order = np.argsort(labels[0].numpy())
    np.testing.assert_allclose(boxes[0, order, 0].numpy(), x[:3], atol=1e-9)
    np.testing.assert_allclose(boxes[0, order, 1].numpy(), y[:3], atol=1e-9)


def test_slice_decoder_uses_preset_cell_and_top_k():
    p = get_preset("tiny")
    p = dataclasses.replace(p, post=dataclasses.replace(p.post, top_k=10**6))
    torch.manual_seed(0)
    dec = SliceDecoder(SliceNet(p), p).eval()
    hh, wh = p.head_map_size
    assert dec.top_k == NUM_CLASSES * hh * wh and dec.cell_m == pytest.approx(0.8)
    g = p.grid
    with torch.no_grad():
        boxes, scores, labels = dec(
            torch.zeros(0, p.pillars.max_points_per_pillar, 11),
            torch.zeros(0, p.pillars.max_points_per_pillar),
            torch.zeros(0, dtype=torch.int64),
            torch.randn(2, p.channels, g.quadrant_ny, g.quadrant_nx),
        )
    assert boxes.shape == (2, dec.top_k, 9) and labels.max() < NUM_CLASSES
    assert torch.all(scores[:, :-1] >= scores[:, 1:])


class _Decode(torch.nn.Module):
    def forward(self, *maps: torch.Tensor):
        return decode_head_maps(maps, 0.8, 12)


@pytest.mark.parametrize("seed", [0, 1])
def test_exported_yaw_is_torchs_atan2_where_sin_and_cos_are_zero(seed, tmp_path):
    """ONNX has no Atan2 (the exporter divides sin by cos): an exact zero pair gives yaw 0 as in torch, not NaN."""
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    maps = [torch.from_numpy(m.astype(np.float32)) for m in random_maps(rng, 1, 4, 5)]
    rot = maps[4]  # (1, 2, H, W): sin, cos
    rot[0, :, :2] = 0.0  # both zero in the first two rows
    rot[0, 0, 2] = 0.0  # sin zero, cos of either sign
    rot[0, 1, 3] = 0.0  # cos zero, sin of either sign
    path = tmp_path / "decode.onnx"
    names = [f"m{i}" for i in range(len(maps))]
    torch.onnx.export(_Decode().eval(), tuple(maps), str(path), dynamo=False, opset_version=17, input_names=names)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got_boxes = sess.run(None, {n: m.numpy() for n, m in zip(names, maps)})[0]
    want_boxes = _Decode()(*maps)[0].numpy()
    assert np.isfinite(got_boxes).all()
    # the same heading: atan2(0, -c) is pi in torch and -pi in the exported graph
    dyaw = np.angle(np.exp(1j * (got_boxes[..., 6] - want_boxes[..., 6])))
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-5)
    np.testing.assert_allclose(np.delete(got_boxes, 6, axis=-1), np.delete(want_boxes, 6, axis=-1), rtol=1e-5, atol=1e-5)
    assert (want_boxes[..., 6] == 0).any(), "no peak landed on a zero pair: the test checks nothing"
