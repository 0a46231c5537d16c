"""The lifter's 3D convolutions as 2D convolutions over folded z: the same function as the Conv3d layers."""

from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F

from streamdet.export.onnx_export import export_volumetric_lifter
from streamdet.models.detector import StreamDetector
from streamdet.models.lifter import VolumetricLifter
from streamdet.models.lifter_fold import (
    FoldedLifter,
    FoldedLifterConvs,
    LifterConvs,
    banded_weight,
    export_lifter,
    export_lifter_convs,
    fold_pays,
    folded_depth,
    folded_mac_ratio,
)
from streamdet.models.presets import LifterConfig, get_preset

TINY = get_preset("tiny")


def _random_bn(lifter: VolumetricLifter, gen: torch.Generator) -> None:
    """Eval statistics far from the identity, so a wrong BN fold shows."""
    with torch.no_grad():
        for m in lifter.modules():
            if isinstance(m, torch.nn.BatchNorm3d):
                m.running_mean.copy_(torch.randn(m.num_features, generator=gen))
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) * 1.5 + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.bias.copy_(torch.randn(m.num_features, generator=gen) * 0.5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("z_in,stride", [(3, 1), (4, 1), (4, 2), (5, 2), (6, 3)])
@pytest.mark.parametrize("seed", range(2))
def test_banded_weight_is_the_3d_convolution(z_in, stride, seed, dtype):
    gen = torch.Generator().manual_seed(seed)
    co, ci, y, x = 3, 2, 5, 6
    w3 = torch.randn(co, ci, 3, 3, 3, generator=gen, dtype=dtype)
    v = torch.randn(2, ci, z_in, y, x, generator=gen, dtype=dtype)  # (Q, C, Z, Y, X)
    ref = F.conv3d(v, w3, stride=(stride, 1, 1), padding=1)  # (Q, Co, Zo, Y, X)
    w2 = banded_weight(w3, z_in, stride, 1)
    zo = folded_depth(z_in, 3, stride, 1)
    got = F.conv2d(v.reshape(2, ci * z_in, y, x), w2, padding=1).reshape(2, co, zo, y, x)
    assert w2.shape == (co * zo, ci * z_in, 3, 3)
    torch.testing.assert_close(got, ref)


def test_banded_weight_naive_layout():
    """Entry by entry against the definition: output plane zo reads plane zo * s - 1 + t through tap t."""
    w3 = torch.arange(2 * 1 * 3 * 1 * 1, dtype=torch.float64).reshape(2, 1, 3, 1, 1) + 1
    w2 = banded_weight(w3, 4, 2, 1)  # Zo = 2
    for o in range(2):
        for zo in range(2):
            for zi in range(4):
                t = zi - (zo * 2 - 1)
                want = w3[o, 0, t, 0, 0] if 0 <= t < 3 else 0.0
                assert w2[o * 2 + zo, zi, 0, 0] == want


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("q", [1, 3])
def test_folded_convs_equal_the_lifter(seed, q, dtype):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    g, c = TINY.grid, TINY.channels
    lifter = VolumetricLifter(TINY.lifter, c).eval()
    _random_bn(lifter, gen)
    lifter = lifter.to(dtype)
    folded = FoldedLifterConvs.from_lifter(lifter, TINY.lifter, g.nz)  # in the lifter's dtype, not torch's default
    assert {p.dtype for p in folded.parameters()} == {dtype}
    assert {p.dtype for p in FoldedLifter(folded).parameters()} == {dtype}  # the z-major copy too
    v = torch.randn(q, c, g.nz, 9, 11, generator=gen, dtype=dtype)  # (Q, C, Z, Y, X)
    v[:, :, :, :3] = 0  # voxels no camera sees
    with torch.no_grad():
        ref = lifter.convs(v)
        got = folded(v)
    assert got.shape == (q, c, 9, 11)
    # float64 folds exactly (to rounding); weights rounded to float32 would leave about 1e-7 relative
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {}
    torch.testing.assert_close(got, ref, **tol)


@pytest.mark.parametrize("z_pool", [1, 2])
def test_folded_convs_with_planes_left_for_the_max(z_pool):
    """Z = 8 and z_stride 2 leave 4 planes: the average pool and the max over z run on real planes."""
    cfg = LifterConfig(z_conv_stride=2, z_pool=z_pool)
    gen = torch.Generator().manual_seed(0)
    lifter = VolumetricLifter(cfg, 4).eval()
    _random_bn(lifter, gen)
    folded = FoldedLifterConvs.from_lifter(lifter, cfg, 8)
    v = torch.randn(2, 4, 8, 5, 5, generator=gen)
    with torch.no_grad():
        torch.testing.assert_close(folded(v), lifter.convs(v))


def test_folded_lifter_equals_the_whole_lifter():
    gen = torch.Generator().manual_seed(1)
    g, c = TINY.grid, TINY.channels
    lifter = VolumetricLifter(TINY.lifter, c).eval()
    _random_bn(lifter, gen)
    j, hf, wf = 2, 5, 7
    shape = (2, 2, g.nz, 6, 6)  # (Q, K, Z, Yq, Xq)
    features = torch.randn(j, c, hf, wf, generator=gen)
    index = torch.randint(0, j * hf * wf + 1, shape, dtype=torch.int32, generator=gen)
    weight = torch.rand(shape, generator=gen)
    whole = export_lifter(lifter, TINY.lifter, g.nz)
    assert isinstance(whole, FoldedLifter)
    with torch.no_grad():
        torch.testing.assert_close(whole(features, index, weight), lifter(features, index, weight))


def test_which_presets_fold():
    small, paper = get_preset("small"), get_preset("paper")
    assert folded_mac_ratio(small.lifter, small.grid.nz) == pytest.approx(232 / 166)  # 1.40: Z = 4
    assert fold_pays(small.lifter, small.grid.nz) and fold_pays(TINY.lifter, TINY.grid.nz)
    assert not fold_pays(paper.lifter, paper.grid.nz)  # Z = 16: 4x the MACs
    lifter = VolumetricLifter(paper.lifter, 4).eval()
    assert export_lifter(lifter, paper.lifter, paper.grid.nz) is lifter
    assert isinstance(export_lifter_convs(lifter, paper.lifter, paper.grid.nz), LifterConvs)


def test_malformed_input_is_refused():
    lifter = VolumetricLifter(TINY.lifter, TINY.channels).eval()
    folded = FoldedLifterConvs.from_lifter(lifter, TINY.lifter, TINY.grid.nz)
    with pytest.raises(ValueError, match="planes"):
        folded(torch.zeros(1, TINY.channels, TINY.grid.nz + 1, 4, 4))
    with pytest.raises(ValueError, match="channels"):
        folded(torch.zeros(1, TINY.channels + 1, TINY.grid.nz, 4, 4))
    with pytest.raises(ValueError, match="Conv3d weight"):
        banded_weight(torch.zeros(2, 2, 3, 3), 4, 1, 1)
    with pytest.raises(ValueError, match="does not fit"):
        folded_depth(1, 5, 1, 1)
    with pytest.raises(ValueError, match="channels"):
        FoldedLifterConvs(TINY.lifter, TINY.channels * 2, TINY.grid.nz).load_from(lifter)
    other = VolumetricLifter(dataclasses.replace(TINY.lifter, z_conv_stride=1), TINY.channels)
    with pytest.raises(ValueError, match="z-stride"):
        FoldedLifterConvs(TINY.lifter, TINY.channels, TINY.grid.nz).load_from(other)


def test_exported_lifter_has_no_3d_convolution_and_matches_torch():
    torch.manual_seed(0)
    det = StreamDetector(TINY).eval()
    _random_bn(det.lifter, torch.Generator().manual_seed(2))
    g, c = TINY.grid, TINY.channels
    gen = torch.Generator().manual_seed(3)
    j, hf, wf = 2, 18, 32
    shape = (4, 2, g.nz, g.quadrant_ny, g.quadrant_nx)
    features = torch.randn(j, c, hf, wf, generator=gen)
    index = torch.randint(0, j * hf * wf + 1, shape, dtype=torch.int32, generator=gen)
    weight = torch.rand(shape, generator=gen)
    model = export_volumetric_lifter(det, features, index, weight)
    inits = {i.name: i for i in model.graph.initializer}
    conv_ranks = {len(inits[n.input[1]].dims) for n in model.graph.node if n.op_type == "Conv"}
    assert conv_ranks == {4}
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    (got,) = sess.run(None, {"features": features.numpy(), "lut_index": index.numpy(), "lut_weight": weight.numpy()})
    with torch.no_grad():
        ref = det.lifter(features, index, weight).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5)
    onnx.checker.check_model(model)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("preset_name", ["tiny", "small"])
def test_z_major_convs_are_the_same_function(preset_name, seed, dtype):
    """Channels renumbered z * C + c: the weights follow, the function does not change."""
    preset = get_preset(preset_name)
    gen = torch.Generator().manual_seed(seed)
    lifter = VolumetricLifter(preset.lifter, preset.channels).eval()
    _random_bn(lifter, gen)
    folded = FoldedLifterConvs.from_lifter(lifter, preset.lifter, preset.grid.nz)
    z_major = folded.to_z_major()
    assert z_major.z_major and not folded.z_major and z_major.to_z_major() is z_major
    folded, z_major = folded.to(dtype), z_major.to(dtype)  # the same (float32-folded) weights in dtype
    v = torch.randn(2, preset.channels, preset.grid.nz, 5, 6, generator=gen, dtype=dtype)  # (Q, C, Z, Y, X)
    with torch.no_grad():
        torch.testing.assert_close(z_major(v), folded(v))
        torch.testing.assert_close(z_major(v).float(), lifter.convs(v.float()), rtol=1e-4, atol=1e-5)
        # the folded entry point takes z-major channels as they come out of the gather
        q, c, z, y, x = v.shape
        torch.testing.assert_close(z_major.folded(v.permute(0, 2, 1, 3, 4).reshape(q, z * c, y, x)), folded(v))


def test_folded_lifter_gathers_z_major_and_exports(tmp_path):
    """The whole lifter in its export form against the PyTorch lifter, also through onnxruntime, empty slots included."""
    gen = torch.Generator().manual_seed(3)
    g, c = TINY.grid, TINY.channels
    lifter = VolumetricLifter(TINY.lifter, c).eval()
    _random_bn(lifter, gen)
    j, hf, wf = 3, 4, 6
    shape = (3, 2, g.nz, g.quadrant_ny, g.quadrant_nx)  # (Q, K, Z, Yq, Xq): static in the exported graph
    features = torch.randn(j, c, hf, wf, generator=gen)
    index = torch.randint(0, j * hf * wf + 1, shape, dtype=torch.int32, generator=gen)
    index[0] = j * hf * wf  # a quadrant no camera sees: every slot the sentinel
    weight = torch.rand(shape, generator=gen)
    whole = export_lifter(lifter, TINY.lifter, g.nz)
    assert whole.convs.z_major
    with torch.no_grad():
        ref = lifter(features, index, weight)
        torch.testing.assert_close(whole(features, index, weight), ref)
    det = StreamDetector(TINY).eval()
    det.lifter.load_state_dict(lifter.state_dict())
    model = export_volumetric_lifter(det, features, index, weight)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"features": features.numpy(), "lut_index": index.numpy(), "lut_weight": weight.numpy()})[0]
    np.testing.assert_allclose(got, ref.numpy(), rtol=1e-4, atol=1e-4)
