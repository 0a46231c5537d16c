"""Data parallelism on PyTorch's own engine: ``torchrun`` environment, process group, batch norm across processes.

``torchrun --nproc_per_node 2 -m streamdet.training.cli ...`` starts the processes and sets RANK / WORLD_SIZE /
LOCAL_RANK / MASTER_ADDR / MASTER_PORT; ``init_distributed`` joins them (gloo on CPU, nccl on CUDA).

Batch norm: PyTorch's ``SyncBatchNorm`` refuses CPU tensors, so ``CrossProcessBatchNorm`` does the same job with
a differentiable all-reduce (``_SumOverProcesses``): the mean and the variance are taken over the
global batch, so N processes holding one shard each compute what one process holding the whole batch computes.
Two passes (sum, then the sum of squared deviations) keep the variance as accurate as a local batch norm's.
"""

from __future__ import annotations

import gc
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.nn.modules.batchnorm import _BatchNorm

from streamdet.models.norms import FrozenBatchNorm2d


@dataclass(frozen=True)
class DistContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    initialised: bool = False  # True when this process joined a process group (even of size 1)

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def launched_by_torchrun() -> bool:
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def init_distributed(device: torch.device) -> DistContext:
    """Join the torchrun process group if this process was launched by torchrun; else a single process."""
    if not launched_by_torchrun():
        return DistContext()
    if not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend)
    return DistContext(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0)), True)


def process_device(device: torch.device, ctx: DistContext) -> torch.device:
    """The device this process trains on: under torchrun a CUDA device is the process's own GPU (``cuda:LOCAL_RANK``);
    a single process keeps the one it was given (``--device cuda:1`` trained on GPU 0 before)."""
    if device.type == "cuda" and ctx.initialised:
        return torch.device("cuda", ctx.local_rank)
    return device


def shutdown_distributed(wait: bool = True) -> None:
    """Leave the process group, if this process joined one. With ``wait`` (a normal end) every process waits for
    the others first: a process that tore gloo down while another still ran (rank 0 writing the checkpoint) aborted
    at exit about every other run ("terminate called without an active exception", SIGABRT). After an error, do not
    wait: the other processes may be blocked in a collective this one will never join."""
    if not (dist.is_available() and dist.is_initialized()):
        return
    try:
        if wait:
            dist.barrier()
    finally:
        gc.collect()  # drop what still refers to the group (DDP's reducer, autograd's collectives) before it goes
        dist.destroy_process_group()


def all_reduce_sum(x: Tensor, ctx: DistContext) -> Tensor:
    """Sum over processes (no autograd); a copy, the input is left alone."""
    x = x.detach().clone()
    if ctx.initialised and ctx.world_size > 1:
        dist.all_reduce(x, op=dist.ReduceOp.SUM)
    return x


class _SumOverProcesses(torch.autograd.Function):
    """y = sum over processes of x, differentiable: every process's x feeds every process's y, so each x's
    gradient is the sum over processes of y's gradients (another all-reduce). This is what
    ``torch.distributed.nn.functional.all_reduce`` computes; that function is deprecated in favour of a private
    module, so the few lines live here."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        y = x.clone()
        dist.all_reduce(y, op=dist.ReduceOp.SUM)
        return y

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        g = grad.contiguous().clone()
        dist.all_reduce(g, op=dist.ReduceOp.SUM)
        return g


def _differentiable_sum(x: Tensor) -> Tensor:
    return _SumOverProcesses.apply(x)


class CrossProcessBatchNorm(_BatchNorm):
    """BatchNorm over the batch of every process; any input (N, C, ...). Same parameters and buffers (and
    state-dict keys) as the BatchNorm it replaces; without a process group it is a plain batch norm."""

    def _check_input_dim(self, input: Tensor) -> None:
        if input.dim() < 2:
            raise ValueError(f"expected at least 2-D input (N, C, ...), got {input.dim()}-D")

    def forward(self, x: Tensor) -> Tensor:
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        c = x.shape[1]
        dims = [0] + list(range(2, x.dim()))
        shape = [1, c] + [1] * (x.dim() - 2)
        count = x.new_tensor([x.numel() / max(c, 1)])
        total = _differentiable_sum(torch.cat([x.sum(dims), count]))  # (C + 1,)
        n = total[c]
        mean = total[:c] / n
        centred = x - mean.view(shape)
        var = _differentiable_sum(centred.pow(2).sum(dims)) / n  # biased, as batch norm normalises with
        y = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked += 1
                momentum = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                unbiased = var.detach() * (n / (n - 1).clamp(min=1))
                self.running_mean.mul_(1 - momentum).add_(mean.detach() * momentum)
                self.running_var.mul_(1 - momentum).add_(unbiased * momentum)
        return y


def convert_batchnorm(module: nn.Module) -> nn.Module:
    """Replace every BatchNorm1d/2d/3d in ``module`` by a CrossProcessBatchNorm carrying its parameters and stats.

    A ``FrozenBatchNorm2d`` (models/norms.py) stays: it uses no batch statistics, so it has none to share.
    """
    frozen = isinstance(module, FrozenBatchNorm2d)
    if isinstance(module, _BatchNorm) and not isinstance(module, CrossProcessBatchNorm) and not frozen:
        # on the module's device and in its dtype (load_state_dict copies values, it does not move the new module)
        floats = [*module.parameters(recurse=False), *(b for b in module.buffers(recurse=False) if b.is_floating_point())]
        factory = {"device": floats[0].device, "dtype": floats[0].dtype} if floats else {}
        new = CrossProcessBatchNorm(module.num_features, module.eps, module.momentum, module.affine,
                                    module.track_running_stats, **factory)  # fmt: skip
        new.load_state_dict(module.state_dict())
        new.train(module.training)
        return new
    for name, child in module.named_children():
        converted = convert_batchnorm(child)
        if converted is not child:
            setattr(module, name, converted)
    return module
