"""A generic training loop: AdamW with cosine warm-up, EMA weights, atomic resumable checkpoints.

Every model of the pipeline trains through :func:`fit`; what differs (the ``LossModule`` and how
a batch is drawn) is passed in.
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
) -> AveragedModel:
    """Trains ``model`` by minimising the sum of ``loss_module``'s ``loss_*`` entries.

    Resumes from ``checkpoint_path`` when it exists (model, EMA, optimiser, schedule, step and
    random state); writes it every ``checkpoint_every`` steps and at the end. The checkpoint
    also holds ``make_payload(ema_model)`` (config, normalizers, ...): the EMA model is the one
    to evaluate and ship.

    Args:
        loss_module: returns a tensordict of ``loss_*`` scalars for a batch.
        model: the module whose parameters are trained (and averaged).
        next_batch: draws a training batch from a ``torch.Generator``.
        num_steps: optimisation steps.
        optim: optimiser, schedule and EMA settings.
        checkpoint_path: where the checkpoint lives.
        make_payload: extra checkpoint content built from the EMA model.
        seed: seeds batch sampling and the model's noise.
        autocast_dtype: e.g. ``torch.bfloat16`` to run forward passes under autocast.
    """
    check_at_least("num_steps", num_steps, 0)
    checkpoint_path = Path(checkpoint_path)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=optim.lr, betas=tuple(optim.betas), weight_decay=optim.weight_decay)
    schedule = get_cosine_schedule_with_warmup(optimizer, optim.warmup_steps, num_steps)
    ema = make_ema(model, optim)
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    step = 0
    if checkpoint_path.exists():
        try:
            state = safe_torch_load(checkpoint_path, "torchrl_dalir training checkpoint")
            check_entries(state if isinstance(state, dict) else {}, checkpoint_path, RESUME_ENTRIES, "training checkpoint")
        except UnsafeFileError:
            raise
        except ValueError as error:
            raise ValueError(f"cannot resume training: {error}. To train from the start instead, delete {checkpoint_path}") from None
        load_weights(model, state, "model", checkpoint_path)
        load_weights(ema, state, "ema", checkpoint_path)
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
        generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        step = state["step"]

    def checkpoint():
        save_checkpoint(
            checkpoint_path,
            {
                "model": model.state_dict(),
                "ema": ema.state_dict(),
                "optimizer": optimizer.state_dict(),
                "schedule": schedule.state_dict(),
                "generator": generator.get_state(),
                "torch_rng": torch.get_rng_state(),
                "step": step,
                "num_steps": num_steps,
                **make_payload(ema.module),
            },
        )

    device = next(model.parameters()).device
    bar = tqdm(total=num_steps, initial=step, desc="train", disable=not progress)
    start, first_step = time.perf_counter(), step
    model.train()
    while step < num_steps:
        batch = next_batch(generator).to(device)
        with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
            losses = loss_module(batch)
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
        if log is not None and (step % log_every == 0 or step == num_steps):
            log({**{k: v.item() for k, v in losses.items()}, "lr": schedule.get_last_lr()[0],
                 "steps_per_s": (step - first_step) / (time.perf_counter() - start)}, step)
        if step % checkpoint_every == 0 or step == num_steps:
            checkpoint()
    bar.close()
    if step == 0 or not checkpoint_path.exists():
        checkpoint()
    return ema
