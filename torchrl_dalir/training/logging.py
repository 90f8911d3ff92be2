"""Metric logging through TorchRL's loggers: CSV always, wandb (offline by default) on request."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from torchrl.record.loggers import CSVLogger, WandbLogger

from torchrl_dalir.training import distributed


def make_logger(run_dir: str | Path, name: str, use_wandb: bool = True, config: dict | None = None) -> Callable[[dict, int], None]:
    """A ``log(metrics, step)`` function writing CSV under ``run_dir`` and, with ``use_wandb``,
    a wandb run that stays offline unless ``WANDB_MODE`` says otherwise. Under torchrun only rank 0
    logs: the other ranks get a function that does nothing."""
    if not distributed.is_main():
        return lambda metrics, step: None
    run_dir = Path(run_dir)
    loggers = [CSVLogger(name, log_dir=str(run_dir / "logs"))]
    if use_wandb:
        offline = os.environ.get("WANDB_MODE", "offline") == "offline"
        wandb_logger = WandbLogger(name, offline=offline, save_dir=str(run_dir), project="torchrl_dalir", log_env_packages=False)
        if config is not None:
            wandb_logger.log_hparams(config)
        loggers.append(wandb_logger)

    def log(metrics: dict, step: int) -> None:
        for logger in loggers:
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=step)

    return log
