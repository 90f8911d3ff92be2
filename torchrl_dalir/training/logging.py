"""Metric logging through TorchRL's loggers: CSV always, wandb only when asked for.

The training jobs' ``wandb`` setting (and the main job's, passed to both training stages) is one
of :data:`WANDB_MODES`:

- ``off`` (the default): CSV files only, ``<run folder>/logs/<run name>/scalars/<metric>.csv``.
- ``offline``: also a wandb run saved under ``<run folder>/wandb/`` (``wandb sync`` uploads it later).
- ``online``: also a wandb run streamed to the wandb server (after ``wandb login``).

What is logged: the training losses and learning rate (every ``log_every`` steps), the world
model's held-out metrics, and, in the main job, the calibration and evaluation results
(:func:`log_results`). The setting decides the mode; ``WANDB_MODE`` is not consulted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from torchrl.record.loggers import CSVLogger, WandbLogger

from torchrl_dalir.config import check_choice
from torchrl_dalir.training import distributed

WANDB_MODES = ("off", "offline", "online")
# The setting was a bool, True meaning an offline run: stored configurations and old command lines
# still say so (and OmegaConf reads ``wandb=off`` / ``wandb=on`` on a command line as booleans).
_FROM_BOOLEAN = {"false": "off", "true": "offline"}


def wandb_mode(value: str | bool) -> str:
    """``value`` as one of :data:`WANDB_MODES`, accepting the old booleans (``True``: ``offline``,
    ``False``: ``off``); a ``ValueError`` naming ``wandb`` otherwise."""
    mode = _FROM_BOOLEAN.get(str(value).lower(), str(value).lower())
    check_choice("wandb", mode if mode in WANDB_MODES else value, WANDB_MODES)
    return mode


def make_logger(
    run_dir: str | Path, name: str, wandb: str | bool = "off", config: dict | None = None, csv: bool = True
) -> Callable[[dict, int], None]:
    """A ``log(metrics, step)`` function writing CSV under ``run_dir / "logs"`` (unless not ``csv``)
    and, unless ``wandb`` is ``off`` (:func:`wandb_mode`), to a wandb run ``name`` of project
    ``torchrl_dalir`` saved under ``run_dir``, offline or online, with ``config`` as its
    configuration. A wandb run started earlier in the process is finished first. Under torchrun only
    rank 0 logs: the other ranks get a function that does nothing."""
    mode = wandb_mode(wandb)
    if not distributed.is_main():
        return lambda metrics, step: None
    run_dir = Path(run_dir)
    loggers = [CSVLogger(name, log_dir=str(run_dir / "logs"))] if csv else []
    if mode != "off":
        # mode= reaches wandb.init (TorchRL's offline=True would set WANDB_MODE for the whole process)
        wandb_logger = WandbLogger(
            name,
            offline=False,
            save_dir=str(run_dir),
            project="torchrl_dalir",
            log_env_packages=False,
            mode=mode,
            reinit="finish_previous",
        )
        if config is not None:
            wandb_logger.log_hparams(config)
        loggers.append(wandb_logger)

    def log(metrics: dict, step: int) -> None:
        for logger in loggers:
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=step)

    return log


def log_results(
    run_dir: str | Path, name: str, wandb: str | bool, numbers: dict[str, float], details: dict | None = None
) -> None:
    """Logs a finished stage's results to a wandb run ``name`` of their own (saved under
    ``run_dir``): ``numbers`` (success rates, p-values) at step 0, ``details`` (the chosen
    setting, the episodes) as the run's configuration. With ``wandb=off`` nothing: the stage's
    JSON record holds the same numbers. No CSV is written."""
    if wandb_mode(wandb) == "off":
        return
    make_logger(run_dir, name, wandb, config=details, csv=False)(numbers, 0)
