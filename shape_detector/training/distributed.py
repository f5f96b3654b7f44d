"""torch.distributed for training: one process per device, launched by ``torchrun``.

``torchrun --nproc_per_node N`` sets ``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE`` and the
rendezvous address; :func:`setup` joins the process group (``nccl`` on GPUs, ``gloo`` on
CPUs). A single process without those variables runs as world size 1 with no process group,
through the same code path. Every rank holds the whole frustum dataset; each epoch's
permutation is sharded by :class:`torch.utils.data.DistributedSampler` (rank ``r`` takes
every ``W``-th index), so local batch ``k`` of all ranks together is global batch ``k`` of
a single process; gradients are averaged by DistributedDataParallel; rank 0 validates and
writes checkpoints and weights.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class DistEnv:
    """This process's place in the job."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that validates, logs and writes files."""
        return self.rank == 0

    @property
    def active(self) -> bool:
        """More than one process (a process group is initialised)."""
        return self.world_size > 1


def setup(device: str | torch.device | None = None) -> tuple[DistEnv, torch.device | None]:
    """Join the process group when launched by ``torchrun`` (``WORLD_SIZE`` > 1).

    Returns the environment and the device this rank uses (``cuda:LOCAL_RANK`` when ``device``
    is a CUDA device or ``auto`` with CUDA available; else ``device`` unchanged)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistEnv(), None if device is None else torch.device(device) if device != "auto" else None
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = torch.cuda.is_available() and str(device or "auto").startswith(("cuda", "auto"))
    dev = torch.device(f"cuda:{local}") if use_cuda else torch.device("cpu")
    if use_cuda:
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if use_cuda else "gloo")
    return DistEnv(rank, world, local), dev


def current() -> DistEnv:
    """The environment of an already initialised process group (world size 1 without one)."""
    if dist.is_available() and dist.is_initialized():
        return DistEnv(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))
    return DistEnv()


def barrier(env: DistEnv) -> None:
    """Wait for every rank (no-op for one process)."""
    if env.active:
        dist.barrier()


def mean_scalars(env: DistEnv, values: dict[str, float]) -> dict[str, float]:
    """``values`` averaged over the ranks (the same dict back for one process)."""
    if not env.active or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64)
    dist.all_reduce(t)
    return {k: float(v) / env.world_size for k, v in zip(keys, t.tolist())}


def broadcast_flag(env: DistEnv, flag: bool) -> bool:
    """Rank 0's ``flag`` on every rank (a stop decision all ranks must share)."""
    if not env.active:
        return flag
    t = torch.tensor([1 if flag else 0], dtype=torch.int64)
    dist.broadcast(t, 0)
    return bool(t.item())


def wrap(model: torch.nn.Module, env: DistEnv, device: torch.device) -> torch.nn.Module:
    """``model`` wrapped in DistributedDataParallel when several processes train, else itself.
    Unused parameters are allowed (a phase's tasks may leave some trainable part without a
    gradient)."""
    if not env.active:
        return model
    from torch.nn.parallel import DistributedDataParallel

    ids = [device.index] if device.type == "cuda" else None
    return DistributedDataParallel(model, device_ids=ids, find_unused_parameters=True)


def epoch_indices(n: int, batch_size: int, env: DistEnv, seed: int, epoch: int) -> list[torch.Tensor]:
    """This rank's local batches of an epoch over ``n`` frustums: the permutation of
    :class:`DistributedSampler` (seeded by ``seed`` and ``epoch``; rank ``r`` takes every
    ``W``-th index), cut into ``n // batch_size`` batches of ``batch_size / W`` (one batch of
    everything when ``n < batch_size``). Local batch ``k`` of all ranks is the global batch
    ``k`` a single process takes."""
    from torch.utils.data import DistributedSampler

    if batch_size % env.world_size:
        raise ValueError(f"batch_size {batch_size} is not a multiple of the {env.world_size} processes")
    sampler = DistributedSampler(range(n), num_replicas=env.world_size, rank=env.rank, shuffle=True, seed=seed,
                                 drop_last=True)
    sampler.set_epoch(epoch)
    local = torch.tensor(list(sampler), dtype=torch.long)
    if n < batch_size:
        return [local]
    per = batch_size // env.world_size
    return [local[k * per:(k + 1) * per] for k in range(n // batch_size)]
