"""A generic training loop: AdamW with cosine warm-up, EMA weights, atomic resumable checkpoints.

Every model of the pipeline trains through :func:`fit`; what differs (the ``LossModule`` and how
a batch is drawn) is passed in. Under ``torchrun`` the same loop trains data-parallel
(:mod:`torchrl_dalir.training.distributed`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from diffusers.optimization import get_cosine_schedule_with_warmup
from tensordict import TensorDictBase
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.optim.swa_utils import AveragedModel
from torchrl.objectives import LossModule
from tqdm.auto import tqdm

from torchrl_dalir.checkpoints.files import (
    UnsafeFileError,
    check_entries,
    load_weights,
    safe_torch_load,
    save_checkpoint,
)
from torchrl_dalir.config import check_at_least
from torchrl_dalir.training import distributed


@dataclass
class OptimConfig:
    """Optimiser, schedule and EMA settings (DP3's by default).

    Example:
        >>> config = OptimConfig(lr=3e-4, warmup_steps=100)  # the cpu preset's, for the policy
        >>> [round(ema_decay(step, config.ema_power, config.ema_max_decay), 4) for step in (0, 10, 1000, 10**7)]
        [0.0, 0.8344, 0.9944, 0.9999]
    """

    lr: float = 1e-4
    betas: tuple[float, float] = (0.95, 0.999)
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    grad_clip: float | None = None


def ema_decay(step: int, power: float, max_decay: float) -> float:
    """DP3's warm-up EMA decay: ``1 - (1 + step) ** -power``, capped at ``max_decay``."""
    return min(max(1.0 - (1.0 + step) ** -power, 0.0), max_decay)


def make_ema(model: nn.Module, config: OptimConfig) -> AveragedModel:
    """An exponential moving average of ``model``'s parameters (buffers are copied, not averaged)."""

    def average(ema_param, param, num_averaged):
        decay = ema_decay(int(num_averaged), config.ema_power, config.ema_max_decay)
        return decay * ema_param + (1 - decay) * param

    return AveragedModel(model, avg_fn=average, use_buffers=False)


# What a fit() checkpoint must hold to resume training.
RESUME_ENTRIES = ("model", "ema", "optimizer", "schedule", "generator", "torch_rng", "step", "num_steps")


def data_parallel(loss_module: LossModule, params: list[nn.Parameter]) -> nn.Module:
    """``loss_module`` wrapped in :class:`~torch.nn.parallel.DistributedDataParallel` when the job
    runs on several processes (itself otherwise).

    The loss module, not the model, is wrapped: the losses call the model's own methods
    (``encode``, ``velocity``, ``imagine``), never its ``forward``, and DDP synchronises the
    gradients of what its ``forward`` runs. Every trained parameter must then belong to the loss
    module, or its gradient would stay per-rank and the ranks' weights would drift apart; and
    each must get a gradient at every step (DDP's default, without the cost of searching for
    unused ones: true of every loss of the library).
    """
    if distributed.world_size() == 1:
        return loss_module
    held = {id(p) for p in loss_module.parameters()}
    missing = sum(id(p) not in held for p in params)
    if missing:
        raise ValueError(
            f"{missing} trained parameters of the model are not parameters of the loss module "
            f"{type(loss_module).__name__}: their gradients could not be averaged over the processes"
        )
    return DistributedDataParallel(loss_module)


def fit(
    loss_module: LossModule,
    model: nn.Module,
    next_batch: Callable[[torch.Generator], TensorDictBase],
    num_steps: int,
    optim: OptimConfig,
    checkpoint_path: str | Path,
    make_payload: Callable[[nn.Module], dict],
    *,
    seed: int = 0,
    checkpoint_every: int = 500,
    log: Callable[[dict, int], None] | None = None,
    log_every: int = 50,
    autocast_dtype: torch.dtype | None = None,
    progress: bool = True,
    shard_dim: int = 0,
) -> AveragedModel:
    """Trains ``model`` by minimising the sum of ``loss_module``'s ``loss_*`` entries.

    Resumes from ``checkpoint_path`` when it exists (model, EMA, optimiser, schedule, step and
    random state); writes it every ``checkpoint_every`` steps and at the end. The checkpoint
    also holds ``make_payload(ema_model)`` (config, normalizers, ...): the EMA model is the one
    to evaluate and ship.

    Under ``torchrun`` (:mod:`~torchrl_dalir.training.distributed`) every rank draws the same
    global batch and trains on its slice along ``shard_dim``, gradients averaged by
    ``DistributedDataParallel``: N ranks take the same steps as one process on the same data
    (exactly, up to float rounding, for a loss without random draws). The loss's own random
    draws (noise, timesteps) use a torch generator seeded ``seed + rank``, so they differ per
    rank and a run on N > 1 ranks is not bit-identical to one on a single process. Only rank 0
    logs, shows progress and writes the checkpoint (which keeps every rank's random state); all
    ranks resume from it.

    Args:
        loss_module: returns a tensordict of ``loss_*`` scalars for a batch.
        model: the module whose parameters are trained (and averaged).
        next_batch: draws a training batch from a ``torch.Generator``.
        num_steps: optimisation steps.
        optim: optimiser, schedule and EMA settings.
        checkpoint_path: where the checkpoint lives.
        make_payload: extra checkpoint content built from the EMA model.
        seed: seeds batch sampling and the model's noise.
        log: receives the losses (averaged over the ranks) and the learning rate; called on rank 0 only.
        autocast_dtype: e.g. ``torch.bfloat16`` to run forward passes under autocast.
        progress: shows a progress bar (on rank 0).
        shard_dim: the batch dimension split over the ranks (its size must be a multiple of their number).
    """
    check_at_least("num_steps", num_steps, 0)
    checkpoint_path = Path(checkpoint_path)
    device = next(model.parameters()).device
    distributed.setup(device)
    main, rank = distributed.is_main(), distributed.rank()
    params = [p for p in model.parameters() if p.requires_grad]
    trained_loss = data_parallel(loss_module, params)
    optimizer = torch.optim.AdamW(params, lr=optim.lr, betas=tuple(optim.betas), weight_decay=optim.weight_decay)
    schedule = get_cosine_schedule_with_warmup(optimizer, optim.warmup_steps, num_steps)
    ema = make_ema(model, optim)
    generator = torch.Generator().manual_seed(seed)  # the same on every rank: the same global batches
    torch.manual_seed(seed + rank)
    step = 0
    if checkpoint_path.exists():
        try:
            state = safe_torch_load(checkpoint_path, "torchrl_dalir training checkpoint")
            check_entries(
                state if isinstance(state, dict) else {}, checkpoint_path, RESUME_ENTRIES, "training checkpoint"
            )
        except UnsafeFileError:
            raise
        except ValueError as error:
            raise ValueError(
                f"cannot resume training: {error}. To train from the start instead, delete {checkpoint_path}"
            ) from None
        load_weights(model, state, "model", checkpoint_path)
        load_weights(ema, state, "ema", checkpoint_path)
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
        generator.set_state(state["generator"])
        step = state["step"]
        _restore_torch_rng(state, seed, step)

    def checkpoint():
        rng_states = distributed.gather(torch.get_rng_state())  # a collective: every rank takes part
        if main:
            save_checkpoint(
                checkpoint_path,
                {
                    "model": model.state_dict(),
                    "ema": ema.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "schedule": schedule.state_dict(),
                    "generator": generator.get_state(),
                    "torch_rng": rng_states[0],
                    **({"rank_torch_rng": rng_states} if len(rng_states) > 1 else {}),
                    "step": step,
                    "num_steps": num_steps,
                    **make_payload(ema.module),
                },
            )
        distributed.barrier()  # no rank reads the file before it is whole

    bar = tqdm(total=num_steps, initial=step, desc="train", disable=not (progress and main))
    start, first_step = time.perf_counter(), step
    model.train()
    while step < num_steps:
        batch = distributed.shard(next_batch(generator), shard_dim).to(device)
        with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
            losses = trained_loss(batch)
        loss = sum(v for k, v in losses.items() if k.startswith("loss"))
        if not torch.isfinite(loss):
            raise FloatingPointError(f"the training loss became {loss.item()} at step {step}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if optim.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(params, optim.grad_clip)
        optimizer.step()
        schedule.step()
        ema.update_parameters(model)
        step += 1
        bar.update(1)
        if step % log_every == 0 or step == num_steps:
            losses = distributed.mean_over_ranks(dict(losses.items()))  # a collective: every rank takes part
            if log is not None and main:
                log(
                    {
                        **{k: v.item() for k, v in losses.items()},
                        "lr": schedule.get_last_lr()[0],
                        "steps_per_s": (step - first_step) / (time.perf_counter() - start),
                    },
                    step,
                )
        if step % checkpoint_every == 0 or step == num_steps:
            checkpoint()
    bar.close()
    if step == 0 or not checkpoint_path.exists():
        checkpoint()
    return ema


def _restore_torch_rng(state: dict, seed: int, step: int) -> None:
    """Restores this rank's torch random state from a checkpoint. A checkpoint written by a
    different number of ranks has no state for some ranks: each rank then reseeds from
    ``(seed, rank, step)`` (the data order, drawn by the shared generator, is unaffected)."""
    ranks, rank = distributed.world_size(), distributed.rank()
    states = state.get("rank_torch_rng", [state["torch_rng"]])
    if len(states) == ranks:
        torch.set_rng_state(states[rank])
    else:
        torch.manual_seed(hash((seed, rank, step)) % 2**63)
