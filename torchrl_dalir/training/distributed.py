"""Data-parallel training under ``torchrun``: the process group, ranks, and the batch split.

A job launched as ``torchrun --nproc_per_node=N examples/train_policy.py ...`` runs N copies of
itself; torchrun tells each its ``RANK``, ``LOCAL_RANK`` and ``WORLD_SIZE``. :func:`setup` joins
them into one process group (gloo on the CPU, nccl on GPUs, each rank on ``cuda:<LOCAL_RANK>``),
and :func:`~torchrl_dalir.training.fit` then averages gradients over the ranks. Without
torchrun (``WORLD_SIZE`` unset or 1) everything here is a no-op: one process, as before.

Every rank draws the same *global* batch from the same generator and trains on its contiguous
``1/N`` slice (:func:`shard`), so a job's batch size is the global one and N ranks take the same
steps on the same data as one process would. Only rank 0 (:func:`is_main`) writes checkpoints,
logs and results; the other ranks wait for it at a :func:`barrier` before reading them.
"""

from __future__ import annotations

import atexit
import os

import torch
import torch.distributed as dist
from tensordict import TensorDictBase


def world_size() -> int:
    """The number of processes of this job: the process group's size, else torchrun's ``WORLD_SIZE``, else 1."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size()
    return int(os.environ.get("WORLD_SIZE", 1))


def rank() -> int:
    """This process's rank in the job (0 without torchrun)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank()
    return int(os.environ.get("RANK", 0))


def is_main() -> bool:
    """Whether this process is rank 0, the one that writes checkpoints, logs and results."""
    return rank() == 0


def setup(device: str | torch.device = "cpu") -> torch.device:
    """Joins torchrun's processes into one process group (once; a no-op for a single process) and
    returns the device this rank trains on.

    The backend is nccl for ``device=cuda`` (each rank takes ``cuda:<LOCAL_RANK>``) and gloo
    otherwise; the rendezvous comes from torchrun's environment (``MASTER_ADDR``,
    ``MASTER_PORT``, ``RANK``, ``WORLD_SIZE``). The group is destroyed at exit.

    Example:
        >>> setup("cpu")  # no torchrun here: one process, no process group
        device(type='cpu')
    """
    device = torch.device(device)
    if world_size() == 1:
        return device
    if device.type == "cuda":
        local = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        if device.index not in (None, local.index):
            raise ValueError(
                f"device={device} on rank {rank()} under torchrun: each rank trains on cuda:<LOCAL_RANK> "
                f"(here {local}); pass device=cuda"
            )
        device = local
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        atexit.register(teardown)
    return device


def teardown() -> None:
    """Leaves the process group (if any)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def barrier() -> None:
    """Waits until every rank gets here (a no-op for a single process): e.g. after rank 0 writes a
    file the others will read."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        dist.barrier()


def check_global_batch(name: str, value: int) -> None:
    """A ``ValueError`` naming the setting unless the global batch ``value`` splits evenly over the ranks."""
    ranks = world_size()
    if value % ranks:
        raise ValueError(
            f"{name}={value} is the global batch and cannot be split over {ranks} processes: use a multiple of {ranks}"
        )


def shard(batch: TensorDictBase, dim: int = 0) -> TensorDictBase:
    """This rank's contiguous ``1/N`` slice of a global ``batch`` along batch dimension ``dim``
    (the whole batch for a single process)."""
    ranks = world_size()
    if ranks == 1:
        return batch
    dim = dim % batch.batch_dims
    size = batch.batch_size[dim]
    check_global_batch(f"the batch dimension {dim} of size {size}", size)
    part = size // ranks
    return batch[(slice(None),) * dim + (slice(rank() * part, (rank() + 1) * part),)]


def mean_over_ranks(values: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Scalars averaged over the ranks (e.g. each rank's loss on its slice: the global batch's loss)."""
    if world_size() == 1:
        return values
    stacked = torch.stack([v.detach().float() for v in values.values()])
    dist.all_reduce(stacked)
    return dict(zip(values, stacked / world_size()))


def gather(value) -> list:
    """Every rank's ``value`` (picklable), in rank order, on every rank."""
    if world_size() == 1:
        return [value]
    out = [None] * world_size()
    dist.all_gather_object(out, value)
    return out
