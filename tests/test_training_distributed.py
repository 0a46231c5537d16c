"""Data parallel on CPU: ``torchrun --nproc_per_node 2`` (gloo) reaches the weights of one process that holds the
same global batch, and the cross-process batch norm equals a batch norm over the concatenated batch."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from streamdet.models.presets import get_preset
from streamdet.training.checkpoint import load_checkpoint
from streamdet.training.cli import main as train_main
from streamdet.training.distributed import DistContext, process_device

TINY = get_preset("tiny")
STEPS = 3


@pytest.fixture(scope="module")
def data_dir(tiny_train_data) -> Path:
    assert (TINY.image.width_px, TINY.image.height_px) == (128, 72)  # the shared dataset's image size (conftest)
    return tiny_train_data  # 4 training samples


def _args(data_dir: Path, out: Path, cache: Path, batch: int, no_image: bool, steps: int) -> list[str]:
    return ["--data", str(data_dir), "--out", str(out), "--preset", "tiny", "--steps", str(steps), "--batch-size", str(batch),
            "--lr", "1e-3", "--log-every", "1", "--cache-dir", str(cache), "--seed", "3"] + (["--no-image"] if no_image else [])  # fmt: skip


def _run_both(data_dir: Path, tmp_path: Path, no_image: bool, steps: int = STEPS) -> tuple[dict, dict, list, list]:
    cache = tmp_path / "cache"
    one = CliRunner().invoke(train_main, _args(data_dir, tmp_path / "one", cache, 2, no_image, steps))
    assert one.exit_code == 0, one.output
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "streamdet.training.cli", *_args(data_dir, tmp_path / "two", cache, 1, no_image, steps)]  # fmt: skip
    two = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert two.returncode == 0, two.stdout[-2000:] + two.stderr[-4000:]
    assert "2 process(es) x batch 1" in two.stdout
    a = load_checkpoint(tmp_path / "one" / "last.pt")
    b = load_checkpoint(tmp_path / "two" / "last.pt")
    assert a["step"] == b["step"] == steps
    la = [json.loads(line) for line in (tmp_path / "one" / "metrics.jsonl").read_text().splitlines()]
    lb = [json.loads(line) for line in (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()]
    assert len(la) == len(lb) == steps
    return a, b, la, lb


@pytest.mark.slow
def test_two_processes_match_one_process(data_dir, tmp_path):
    """LiDAR-only preset: same global batch, global batch-norm statistics (CrossProcessBatchNorm) and object-count
    normalisation give the one-process weights, up to the order of floating-point sums.

    Adam's first updates are sign-like: a weight whose gradient nearly cancels can take a full step either way on
    all-reduce rounding (seen on world-2 data: 2 of ~1,150 weights 5e-4 apart after the steps). So nearly every
    weight must agree tightly and every weight loosely; a real error (a wrong normalisation, a missing all-reduce)
    moves most weights."""
    a, b, la, lb = _run_both(data_dir, tmp_path, no_image=True)
    loose, total = 0, 0
    for k, va in a["model"].items():
        vb = b["model"][k]
        assert va.shape == vb.shape, k
        if va.is_floating_point():
            torch.testing.assert_close(vb, va, rtol=1e-3, atol=2e-3, msg=lambda m, k=k: f"{k}: {m}")
            loose += int((~torch.isclose(vb, va, rtol=1e-3, atol=2e-4)).sum())
            total += va.numel()
        else:
            assert torch.equal(va, vb), k  # num_batches_tracked
    assert loose <= max(2, total // 200), f"{loose} of {total} weights differ by more than 2e-4"
    for ra, rb in zip(la, lb):
        assert ra["loss"] == pytest.approx(rb["loss"], rel=1e-4)
        for part in ("heatmap", "reg", "loc_xy", "dim", "rot", "vel"):  # parts were logged 1 / world_size of their value
            assert ra[part] == pytest.approx(rb[part], rel=1e-3), part


@pytest.mark.slow
def test_two_processes_fused_first_step_matches(data_dir, tmp_path):
    """Camera + LiDAR preset: the first step's global loss (same weights, same data) is the one-process loss.
    The weights after a few steps are not compared: from scratch the image lane's gradients reach the first
    convolutions nearly cancelled, so Adam's sign-like first updates amplify all-reduce rounding (after a few steps
    the image encoder's first convolution differs between the two runs far more than the LiDAR lane's weights). So
    one step is run: the steps after it, and the epoch boundary, are the LiDAR-only test's."""
    a, b, la, lb = _run_both(data_dir, tmp_path, no_image=False, steps=1)
    assert la[0]["loss"] == pytest.approx(lb[0]["loss"], rel=1e-4)
    for part in ("heatmap", "reg"):
        assert la[0][part] == pytest.approx(lb[0][part], rel=1e-4), part
    for k, va in a["model"].items():
        if k.startswith("slice_net.head") and va.is_floating_point():
            assert torch.isfinite(b["model"][k]).all(), k


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _bn_worker(rank: int, port: int, out: str) -> None:
    import torch.distributed as dist

    from streamdet.training.distributed import CrossProcessBatchNorm, shutdown_distributed

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    torch.manual_seed(0)
    x = torch.randn(6, 4, 5, 3, dtype=torch.float64) * 3 + 1  # the same full batch on both ranks
    bn = CrossProcessBatchNorm(4).double()
    with torch.no_grad():
        bn.weight.uniform_(0.5, 2)
        bn.bias.uniform_(-1, 1)
    part = x[rank * 2 : rank * 2 + 2 + rank].clone().requires_grad_(True)  # uneven shards: 2 and 3 rows
    y = bn(part)
    (y * torch.arange(y.numel(), dtype=y.dtype).reshape(y.shape).sin()).sum().backward()
    torch.save({"y": y.detach(), "grad": part.grad, "rm": bn.running_mean, "rv": bn.running_var,
                "gw": bn.weight.grad, "gb": bn.bias.grad}, f"{out}/bn{rank}.pt")  # fmt: skip
    shutdown_distributed()  # barrier first: a rank that left while the other still communicated aborted at exit


@pytest.mark.slow
def test_cross_process_batchnorm_equals_one_batchnorm(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_bn_worker, args=(_free_port(), str(tmp_path)), nprocs=2, join=True)
    torch.manual_seed(0)
    x = torch.randn(6, 4, 5, 3, dtype=torch.float64) * 3 + 1
    bn = torch.nn.BatchNorm2d(4).double()
    with torch.no_grad():
        bn.weight.uniform_(0.5, 2)
        bn.bias.uniform_(-1, 1)
    x = x[:5].clone().requires_grad_(True)  # the shards above: rows 0-1 and 2-4
    y = bn(x)
    (y * torch.cat([torch.arange(2 * 60), torch.arange(3 * 60)]).to(y.dtype).reshape(y.shape).sin()).sum().backward()
    r = [torch.load(tmp_path / f"bn{i}.pt") for i in range(2)]
    torch.testing.assert_close(torch.cat([r[0]["y"], r[1]["y"]]), y.detach())
    torch.testing.assert_close(torch.cat([r[0]["grad"], r[1]["grad"]]), x.grad)
    for i in range(2):
        torch.testing.assert_close(r[i]["rm"], bn.running_mean)
        torch.testing.assert_close(r[i]["rv"], bn.running_var)
    # parameter gradients are per-process sums; DDP's average times the loss scale (world size) gives the total
    torch.testing.assert_close(r[0]["gw"] + r[1]["gw"], bn.weight.grad)
    torch.testing.assert_close(r[0]["gb"] + r[1]["gb"], bn.bias.grad)


@pytest.mark.parametrize("given, ctx, expected", [
    ("cuda:1", DistContext(), "cuda:1"),  # one process: the GPU asked for (it trained on cuda:0 before)
    ("cuda", DistContext(), "cuda"),
    ("cpu", DistContext(), "cpu"),
    ("cuda", DistContext(rank=3, world_size=4, local_rank=1, initialised=True), "cuda:1"),  # torchrun: its own GPU
    ("cuda:0", DistContext(rank=1, world_size=2, local_rank=1, initialised=True), "cuda:1"),
    ("cpu", DistContext(rank=1, world_size=2, local_rank=1, initialised=True), "cpu"),
])  # fmt: skip
def test_process_device(given, ctx, expected):
    assert process_device(torch.device(given), ctx) == torch.device(expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_convert_batchnorm_keeps_dtype_stats_and_mode(dtype):
    """The cross-process norm is made in the replaced one's dtype and device (it was float32 whatever the model's)."""
    from streamdet.training.distributed import CrossProcessBatchNorm, convert_batchnorm

    model = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 1), torch.nn.BatchNorm2d(4)).to(dtype)
    model[1].running_mean.fill_(0.25)
    model.eval()
    converted = convert_batchnorm(model)
    bn = converted[1]
    assert isinstance(bn, CrossProcessBatchNorm) and not bn.training
    assert bn.weight.dtype == bn.running_mean.dtype == dtype and bn.num_batches_tracked.dtype == torch.int64
    assert torch.equal(bn.running_mean, torch.full((4,), 0.25, dtype=dtype))
