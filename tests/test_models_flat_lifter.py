"""The flat lifter (models/flat_lifter.py): against a naive numpy reference, its export form (BatchNorms folded, the
compact LUT), and a whole export of a flat-lifter model through the runtime against PyTorch."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.calibration.compact_lut import compact_lut
from streamdet.data.sample import load_bundled_sample
from streamdet.export.cli import main as export_main
from streamdet.models.compact_lifter import CompactLifter
from streamdet.models.detector import build_detector, build_lifter
from streamdet.models.export_form import to_export_form
from streamdet.models.flat_lifter import FlatLifter, FlatLifterExport
from streamdet.models.flops import count_gmac
from streamdet.models.image_half import ImageHalfLifter
from streamdet.models.presets import LifterConfig, get_preset
from streamdet.evaluation.dataset_eval import OnnxSweepDetector
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.training.checkpoint import save_weights
from streamdet.training.torch_eval import TorchSweepDetector


def _flat(name: str):
    p = get_preset(name)
    return dataclasses.replace(p, lifter=dataclasses.replace(p.lifter, form="flat"))


TINY_FLAT = _flat("tiny")


def _randomise_bn(module: torch.nn.Module, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for bn in module.modules():
            if isinstance(bn, torch.nn.BatchNorm2d):
                n = bn.num_features
                bn.running_mean.copy_(torch.randn(n, generator=gen) * 0.3)
                bn.running_var.copy_(torch.rand(n, generator=gen) + 0.5)
                bn.weight.copy_(torch.rand(n, generator=gen) + 0.5)
                bn.bias.copy_(torch.randn(n, generator=gen) * 0.2)


def _lut(rng: np.random.Generator, shape: tuple[int, ...], sentinel: int, multi_share: float = 0.3):
    index = rng.integers(0, sentinel, shape).astype(np.int32)  # (Q, K, Z, Yq, Xq)
    index[:, 0][rng.random(index[:, 0].shape) < 0.2] = sentinel
    index[:, 1][rng.random(index[:, 1].shape) >= multi_share] = sentinel
    weight = (rng.random(shape).astype(np.float32) + 0.1) * (index < sentinel)
    return index, weight


# ---- naive reference ------------------------------------------------------------------------------------------


def _np_bn(x: np.ndarray, bn: torch.nn.BatchNorm2d) -> np.ndarray:
    shape = (1, -1, 1, 1)
    mean, var = bn.running_mean.double().numpy(), bn.running_var.double().numpy()
    gamma, beta = bn.weight.detach().double().numpy(), bn.bias.detach().double().numpy()
    return (x - mean.reshape(shape)) / np.sqrt(var.reshape(shape) + bn.eps) * gamma.reshape(shape) + beta.reshape(shape)


def _np_conv2d(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Same-padded 2D convolution, stride 1, no bias: x (Q, C, Y, X), w (O, C, k, k)."""
    k = w.shape[2]
    p = k // 2
    xp = np.pad(x, ((0, 0), (0, 0), (p, p), (p, p)))
    q, _, y, xx = x.shape
    out = np.zeros((q, w.shape[0], y, xx))
    for dy in range(k):
        for dx in range(k):
            out += np.einsum("qcyx,oc->qoyx", xp[:, :, dy : dy + y, dx : dx + xx], w[:, :, dy, dx])
    return out


def _np_depthwise(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Same-padded depthwise 2D convolution: x (Q, C, Y, X), w (C, 1, k, k)."""
    return np.concatenate([_np_conv2d(x[:, i : i + 1], w[i : i + 1]) for i in range(x.shape[1])], axis=1)


def _np_flat_lifter(lifter: FlatLifter, features: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    j, c, hf, wf = features.shape
    table = np.concatenate([features.transpose(0, 2, 3, 1).reshape(-1, c), np.zeros((1, c))])  # sentinel row last
    volume = (table[index] * weight[..., None]).sum(axis=1)  # (Q, Z, Yq, Xq, C)
    q, z, yq, xq, _ = volume.shape
    v = volume.transpose(0, 1, 4, 2, 3).reshape(q, z * c, yq, xq)  # channel z * C + c

    def w(conv):
        return conv.weight.detach().double().numpy()

    v = _np_bn(v, lifter.input_norm)
    v = np.maximum(_np_bn(_np_conv2d(v, w(lifter.project[0])), lifter.project[1]), 0)
    convs = [m for m in lifter.residual if isinstance(m, torch.nn.Conv2d)]
    r = v
    for conv in convs:
        r = _np_depthwise(r, w(conv)) if conv.groups > 1 else _np_conv2d(r, w(conv))
    r = np.maximum(_np_bn(r, lifter.residual[len(convs)]), 0)
    return v + r


@pytest.mark.parametrize("residual", ["conv", "separable"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("q", [1, 3])
def test_flat_lifter_matches_the_naive_reference(seed, q, residual):
    torch.manual_seed(seed)
    c, nz = 4, 3
    lifter = FlatLifter(c, nz, residual).eval()
    _randomise_bn(lifter, seed)
    rng = np.random.default_rng(seed)
    j, hf, wf = 2, 5, 6
    index, weight = _lut(rng, (q, 2, nz, 7, 5), j * hf * wf)
    features = rng.standard_normal((j, c, hf, wf)).astype(np.float32)
    with torch.no_grad():
        got = lifter(torch.from_numpy(features), torch.from_numpy(index), torch.from_numpy(weight))
    want = _np_flat_lifter(lifter, features.astype(np.float64), index, weight.astype(np.float64))
    assert got.shape == (q, c, 7, 5)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_convs_from_the_volume_equal_the_gathered_path(seed, dtype):
    """``convs`` (the volume (Q, C, Z, Y, X), as VolumetricLifter.convs takes it) and ``forward`` agree."""
    torch.manual_seed(seed)
    lifter = FlatLifter(3, 4).eval().to(dtype)
    _randomise_bn(lifter, seed)
    rng = np.random.default_rng(seed)
    index, weight = _lut(rng, (2, 2, 4, 6, 6), 2 * 4 * 5)
    features = torch.randn(2, 3, 4, 5, dtype=dtype)
    from streamdet.models.lifter import gather_volume

    with torch.no_grad():
        w = torch.from_numpy(weight).to(dtype)
        want = lifter(features, torch.from_numpy(index), w)
        got = lifter.convs(gather_volume(features, torch.from_numpy(index), w))
    torch.testing.assert_close(got, want)


@pytest.mark.parametrize("residual", ["conv", "separable"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_folded_convs_keep_the_lifter_dtype(dtype, residual):
    """FlatLifterConvs in the source lifter's dtype (as slice_split.py's folds): a float64 lifter folds exactly."""
    torch.manual_seed(0)
    lifter = FlatLifter(3, 4, residual).eval().to(dtype)
    _randomise_bn(lifter, 0)
    folded = FlatLifterExport(lifter).convs
    assert {p.dtype for p in folded.parameters()} == {dtype}
    volume = torch.randn(2, 3, 4, 6, 5, dtype=dtype)  # (Q, C, Z, Y, X)
    with torch.no_grad():
        got, want = folded(volume), lifter.convs(volume)
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {}
    torch.testing.assert_close(got, want, **tol)


def test_empty_quadrant_batch_and_wrong_channels():
    lifter = FlatLifter(4, 2).eval()
    index = torch.zeros((0, 2, 2, 3, 3), dtype=torch.int32)
    with torch.no_grad():
        out = lifter(torch.randn(1, 4, 2, 2), index, torch.zeros(index.shape))
    assert out.shape == (0, 4, 3, 3)
    with pytest.raises(ValueError, match="expected 2 x 4 folded channels, got shape"):
        lifter.folded(torch.zeros(1, 7, 3, 3))


def test_residual_form_is_checked_and_costs_less_separable():
    with pytest.raises(ValueError, match="'grouped'"):
        LifterConfig(form="flat", residual="grouped")
    with pytest.raises(ValueError, match="needs form 'flat'"):
        LifterConfig(form="volume", residual="separable")
    with pytest.raises(ValueError, match="'grouped'"):
        FlatLifter(4, 2, "grouped")
    assert "residual" not in TINY_FLAT.to_dict()["lifter"]  # manifests of conv lifters keep their exact dict
    swift = get_preset("small_v3_swift")
    assert swift.lifter.residual == "separable" and type(swift).from_dict(swift.to_dict()) == swift
    c = 32
    x = torch.empty(1, c, 16, 16)
    with torch.device("meta"):
        full, separable = FlatLifter(c, 4, "conv").residual, FlatLifter(c, 4, "separable").residual
    assert count_gmac(separable, x.to("meta")) < count_gmac(full, x.to("meta")) / 5


def test_lifter_form_is_checked_and_old_presets_keep_the_volume():
    with pytest.raises(ValueError, match="'conv3d'"):
        LifterConfig(form="conv3d")
    assert LifterConfig().form == "volume" and get_preset("small").lifter.form == "volume"
    assert get_preset("paper").lifter.form == "volume"
    d = TINY_FLAT.to_dict()
    assert d["lifter"]["form"] == "flat"
    old = {**d, "lifter": {k: v for k, v in d["lifter"].items() if k != "form"}}  # a checkpoint from before the field
    assert type(TINY_FLAT).from_dict(old).lifter.form == "volume"


@pytest.mark.parametrize("name", ["tiny", "small", "small_v2"])
def test_flat_lifter_costs_a_fraction_of_the_volume_lifter(name):
    """The reason for the form: far fewer MACs for the same image BEV shape (the figures: flops_report)."""
    macs = {}
    for form in ("volume", "flat"):
        p = get_preset(name)
        p = dataclasses.replace(p, lifter=dataclasses.replace(p.lifter, form=form))
        g = p.grid
        with torch.device("meta"):
            lifter = build_lifter(p).eval()
            args = (torch.empty(6, p.channels, p.image.feature_height, p.image.feature_width),
                    torch.zeros((1, 2, g.nz, g.quadrant_ny, g.quadrant_nx), dtype=torch.int32),
                    torch.empty((1, 2, g.nz, g.quadrant_ny, g.quadrant_nx)))  # fmt: skip
        macs[form] = count_gmac(lifter, *args)
    assert macs["flat"] < macs["volume"] / 4


# ---- export form ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("residual", ["conv", "separable"])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("multi_share", [0.0, 0.3])
def test_export_form_folds_the_batchnorms_and_reads_the_compact_lut(seed, multi_share, residual):
    torch.manual_seed(seed)
    preset = dataclasses.replace(TINY_FLAT, lifter=dataclasses.replace(TINY_FLAT.lifter, residual=residual))
    det = build_detector(preset).eval()
    _randomise_bn(det.lifter, seed)
    form = to_export_form(det)
    assert isinstance(det.lifter, FlatLifter) and isinstance(form.volumetric_lifter, FlatLifterExport)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in form.volumetric_lifter.modules())
    g = TINY_FLAT.grid
    rng = np.random.default_rng(seed)
    j, hf, wf = 3, 4, 6
    sentinel = j * hf * wf
    index, weight = _lut(rng, (2, 2, g.nz, g.quadrant_ny, g.quadrant_nx), sentinel, multi_share)
    features = torch.randn(j, TINY_FLAT.channels, hf, wf)
    lut = compact_lut(index, weight, sentinel)
    voxels = lut.voxel_shape
    compact = [torch.from_numpy(a) for a in (lut.multi_index, lut.multi_weight, lut.final_index.reshape(voxels),
                                             lut.final_weight.reshape(voxels))]  # fmt: skip
    with torch.no_grad():
        want = det.lifter(features, torch.from_numpy(index), torch.from_numpy(weight))
        folded = form.volumetric_lifter(features, torch.from_numpy(index), torch.from_numpy(weight))
        from_compact = CompactLifter(form.volumetric_lifter)(features, *compact)
    torch.testing.assert_close(folded, want, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(from_compact, want, rtol=1e-4, atol=1e-5)
    half = to_export_form(det, image_layout="image_half", lut_layout="compact").volumetric_lifter
    assert isinstance(half, ImageHalfLifter) and isinstance(half.lifter, CompactLifter)


# ---- a whole export -------------------------------------------------------------------------------------------


def _model():
    torch.manual_seed(5)
    model = build_detector(TINY_FLAT).eval()
    _randomise_bn(model.lifter, 5)
    with torch.no_grad():  # spread the untrained heatmap logits, so scores are not one flat tie at the prior
        for task in model.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
    return model


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory) -> Path:
    ckpt = tmp_path_factory.mktemp("ckpt") / "flat.pt"
    save_weights(ckpt, TINY_FLAT, _model())
    out = tmp_path_factory.mktemp("export") / "flat"
    result = CliRunner().invoke(export_main, ["--checkpoint", str(ckpt), "--fp16", "--int8", "--slices", "8",
                                              "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_export_of_a_flat_lifter_passes_its_parity_checks(export_dir):
    m = read_manifest(export_dir)
    assert m.preset["lifter"]["form"] == "flat"
    assert m.parity and all(p.passed for p in m.parity)
    assert m.pipeline_parity is not None and m.pipeline_parity.passed


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_sweep_through_onnx_equals_pytorch(export_dir, precision):
    sample = load_bundled_sample()
    onnx = OnnxSweepDetector(export_dir, precision=precision, num_slices=8)(sample)
    ref = TorchSweepDetector(_model(), num_slices=8)(sample)
    assert len(onnx) > 0 and len(ref) > 0
    top = min(len(onnx), len(ref), 10)
    if precision == "fp32":
        np.testing.assert_allclose(onnx.scores[:top], ref.scores[:top], rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(onnx.boxes[:top, :3], ref.boxes[:top, :3], atol=2e-3)
    else:  # int8 image lane and slice graph: the same leading boxes, scores within quantisation error
        np.testing.assert_allclose(onnx.scores[:top], ref.scores[:top], atol=0.05)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("q", [0, 1, 3])
def test_training_gather_equals_the_exported_gather(seed, dtype, q):
    """embedding_bag (training) and index_select (export): the same sums and the same feature gradient."""
    from streamdet.models.flat_lifter import gather_z_major_bag
    from streamdet.models.lifter import gather_z_major

    rng = np.random.default_rng(seed)
    j, c, hf, wf = 3, 5, 4, 6
    index, weight = _lut(rng, (q, 4, 3, 6, 7), j * hf * wf)
    index_t, weight_t = torch.from_numpy(index), torch.from_numpy(weight).to(dtype)
    features = torch.randn(j, c, hf, wf, dtype=dtype, generator=torch.Generator().manual_seed(seed), requires_grad=True)
    want = gather_z_major(features, index_t, weight_t)
    got = gather_z_major_bag(features, index_t, weight_t)
    assert got.shape == want.shape == (q, 3 * c, 6, 7)
    torch.testing.assert_close(got, want)
    if q:
        grad = torch.randn_like(want)
        (g_want,) = torch.autograd.grad(want, features, grad)
        (g_got,) = torch.autograd.grad(got, features, grad)
        torch.testing.assert_close(g_got, g_want)


def test_the_export_builds_the_form_a_checkpoint_was_trained_with(tmp_path):
    """A checkpoint saved before the field (no lifter.form) is a volume lifter; one of the flat form is flat."""
    from streamdet.export.weights import checkpoint_lifter

    flat = tmp_path / "flat.pt"
    save_weights(flat, TINY_FLAT, build_detector(TINY_FLAT))
    assert checkpoint_lifter(flat).form == "flat"
    old = tmp_path / "old.pt"
    obj = torch.load(flat, weights_only=True)
    tiny = get_preset("tiny")
    obj["preset"] = {**tiny.to_dict(), "lifter": {k: v for k, v in tiny.to_dict()["lifter"].items() if k != "form"}}
    obj["model"] = build_detector(tiny).state_dict()
    torch.save(obj, old)
    assert checkpoint_lifter(old).form == "volume"
    assert checkpoint_lifter(None) is None
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    assert checkpoint_lifter(tmp_path / "junk.pt") is None


def test_the_export_builds_the_residual_a_checkpoint_was_trained_with(tmp_path):
    """A checkpoint without lifter.residual (before the field, or a "conv" one) has the full conv; a separable one is
    exported separable, whatever the preset of its name says."""
    from streamdet.export.exporter import _resolve_preset
    from streamdet.export.options import ExportOptions
    from streamdet.export.weights import checkpoint_lifter

    separable = dataclasses.replace(TINY_FLAT, lifter=dataclasses.replace(TINY_FLAT.lifter, residual="separable"))
    path = tmp_path / "sep.pt"
    save_weights(path, separable, build_detector(separable))
    assert checkpoint_lifter(path).residual == "separable"
    conv = tmp_path / "conv.pt"
    save_weights(conv, TINY_FLAT, build_detector(TINY_FLAT))
    assert checkpoint_lifter(conv).residual == "conv"
    preset, _, _ = _resolve_preset(ExportOptions(checkpoint=str(path)))
    assert preset.lifter.residual == "separable" and preset.lifter.form == "flat"


def test_the_export_builds_the_lut_heights_a_checkpoint_was_trained_with(tmp_path):
    """A checkpoint trained with other LUT heights per voxel than its preset's name says today exports with its
    own: the LUT it ships samples those heights (the weights alone cannot tell)."""
    from streamdet.export.exporter import _resolve_preset
    from streamdet.export.options import ExportOptions

    three = dataclasses.replace(TINY_FLAT, lifter=dataclasses.replace(TINY_FLAT.lifter, lut_heights_per_voxel=3))
    path = tmp_path / "three.pt"
    save_weights(path, three, build_detector(three))
    preset, _, _ = _resolve_preset(ExportOptions(checkpoint=str(path)))
    assert preset.lifter == three.lifter
    out = tmp_path / "export"
    result = CliRunner().invoke(export_main, ["--checkpoint", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert read_manifest(out).preset["lifter"]["lut_heights_per_voxel"] == 3


def test_a_checkpoint_with_a_malformed_lifter_is_refused_by_the_export(tmp_path):
    """An unknown or invalid lifter field: no lifter is taken from it, and the export says what is wrong."""
    from streamdet.export.exporter import _resolve_preset
    from streamdet.export.options import ExportOptions
    from streamdet.export.weights import CheckpointError, checkpoint_lifter, load_detector

    path = tmp_path / "bad.pt"
    save_weights(path, TINY_FLAT, build_detector(TINY_FLAT))
    for lifter in ({**TINY_FLAT.to_dict()["lifter"], "colour": "red"}, {**TINY_FLAT.to_dict()["lifter"], "form": "cube"}):
        obj = torch.load(path, weights_only=True)
        obj["preset"]["lifter"] = lifter
        torch.save(obj, path)
        assert checkpoint_lifter(path) is None
        preset, _, _ = _resolve_preset(ExportOptions(checkpoint=str(path)))
        with pytest.raises(CheckpointError, match="unreadable preset"):
            load_detector(preset, path)
