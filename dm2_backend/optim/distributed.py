"""Data-parallel optimisation on torch.distributed: the ranks, which anchors each rank takes, the
DistributedDataParallel wrapper over the optimiser's parameters, and the reductions the training loop needs.

Every rank holds the same parameters and draws the same permutation of anchors; each step's global batch is
split between the ranks, DDP averages their gradients (the pose parameters, the occupancy field and L-Net)
and every rank takes the same Adam step, so the parameters stay identical on all ranks.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import numpy as np
import torch
import torch.distributed as td
from torch import nn
from torch.nn.parallel import DistributedDataParallel

#: how long a rank waits for another at a barrier outside the training steps (preparation, writing outputs)
LONG_WAIT = timedelta(hours=24)


@dataclass(frozen=True)
class Dist:
    """This process's place in the run; ``world == 1`` is a single process (no torch.distributed)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @classmethod
    def from_env(cls) -> Dist:
        """The rank torchrun (or any launcher setting RANK / WORLD_SIZE / LOCAL_RANK) started this process as."""
        env = os.environ
        return cls(int(env.get("RANK", 0)), int(env.get("WORLD_SIZE", 1)), int(env.get("LOCAL_RANK", 0)))


def rank_device(name: str, dist: Dist) -> torch.device:
    """The device of a rank: ``cuda:<local rank>`` when the run uses CUDA (one GPU per process), else the CPU."""
    use_cuda = name.startswith("cuda") or (name == "auto" and torch.cuda.is_available())
    if not use_cuda:
        return torch.device(name if name != "auto" else "cpu")
    if not dist.enabled:
        return torch.device(name if name != "auto" else "cuda")
    if dist.local_rank >= torch.cuda.device_count():
        raise RuntimeError(f"rank {dist.rank} needs GPU {dist.local_rank}: only {torch.cuda.device_count()} "
                           "visible (one process per GPU)")
    return torch.device("cuda", dist.local_rank)


def init(dist: Dist, device: torch.device, init_method: str = "env://") -> None:
    """Join the process group: NCCL between GPUs, gloo on CPU."""
    if device.type == "cuda":
        torch.cuda.set_device(device)
    td.init_process_group("nccl" if device.type == "cuda" else "gloo", init_method=init_method, rank=dist.rank,
                          world_size=dist.world)


def wait_group():
    """A gloo group with a long timeout, for barriers around long single-rank work (preparation)."""
    return td.new_group(backend="gloo", timeout=LONG_WAIT)


def shard(anchors: np.ndarray, dist: Dist) -> tuple[np.ndarray, float]:
    """This rank's contiguous share of a step's anchors and its weight (its fraction of the anchors). A rank
    left without anchors (fewer anchors than ranks) computes the first anchor's loss with weight 0, so that
    it still takes part in the gradient all-reduce."""
    mine = np.array_split(anchors, dist.world)[dist.rank]
    if len(mine) == 0:
        return anchors[:1], 0.0
    return mine, len(mine) / len(anchors)


def generator_seed(seed: int, dist: Dist) -> int:
    """Seed of a rank's free-space sample generator: the single-process seed on rank 0, others derived."""
    return seed if dist.rank == 0 else int(np.random.default_rng([seed, dist.rank]).integers(2**31))


class _StepLoss(nn.Module):
    """The optimiser's step loss as a module over its parameters (what DDP wraps)."""

    def __init__(self, opt) -> None:
        super().__init__()
        self.model, self.field = opt.model, opt.field
        self.step_loss = opt._step_loss

    def forward(self, anchors: np.ndarray, generator: torch.Generator) -> dict[str, torch.Tensor]:
        return self.step_loss(anchors, generator)


def data_parallel(opt) -> DistributedDataParallel:
    """DDP over the optimiser's pose model and occupancy field; it averages their gradients in backward.
    Buffers (warm start, L-Net's points) are the same on every rank and never broadcast."""
    ids = [opt.device.index] if opt.device.type == "cuda" else None
    # unless the BCE is forced on, the occupancy field may take no part in a step
    return DistributedDataParallel(_StepLoss(opt), device_ids=ids, forward_sync_buffers=False,
                                   find_unused_parameters=opt.cfg.use_bce != "on")


def reduce_parts(parts: dict[str, torch.Tensor], weight: float) -> dict[str, torch.Tensor]:
    """The step's loss terms over all ranks: the sum of each rank's terms times its weight."""
    values = torch.stack([v.detach().double() for v in parts.values()]) * weight
    td.all_reduce(values)
    return dict(zip(parts, values.cpu()))


def broadcast(obj):
    """Rank 0's ``obj`` on every rank (pickled)."""
    box = [obj]
    td.broadcast_object_list(box, src=0)
    return box[0]
