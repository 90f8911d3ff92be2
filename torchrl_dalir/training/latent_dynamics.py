"""The latent world model alone, with and without action input, on data without a policy (the paper's Table 4).

DALI-R's world model learns on the latents of an encoder copied from the base policy. Released
real-robot data (:func:`~torchrl_dalir.data.import_dp3_zarr`) come with no policy and no simulator,
so :func:`compare_action_input` trains:

1. a latent encoder of DP3's architecture (:class:`~torchrl_dalir.modules.LatentEncoder`, its
   normalizers fitted on the training trajectories): ``encoder=progress`` fine-tunes it with a
   task-completion scorer on the completion targets, as stage 1 of
   :func:`~torchrl_dalir.training.train_world_model` does (on demonstrations, all labeled successes,
   the target ``gamma^(T - t)`` is the progress along the demo), and ``encoder=random`` keeps its
   seeded initialisation. It is then frozen and every row is encoded once;
2. on those latents, the same :class:`~torchrl_dalir.modules.LatentWorldModel` twice, from the same
   initial weights on the same batches: with the action chunk and without it (``action_input=False``).

It reports the latent MSE of both on held-out trajectories (no step of which is trained on), next
to the "no change" predictor's ``s_hat_{t+k} = s_t``. The two models read the same latents, so
their errors compare directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.data import TrajectoryDataset
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.modules import (
    LatentEncoder,
    LatentWorldModel,
    MinMaxNormalizer,
    PointCloudEncoder,
    StateEncoder,
    TaskCompletionScorer,
)
from torchrl_dalir.objectives import LatentDynamicsLoss, TaskCompletionLoss
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.precision import PRECISIONS, autocast_dtype
from torchrl_dalir.training.world_model import (
    dynamics_optim,
    encode_rows,
    imagine_windows,
    scorer_optim,
    split_trajectories,
)

ENCODERS = ("progress", "random")
VARIANTS = {"with_action": True, "without_action": False}  # result name -> the world model's action_input
# The row entries a window gathers besides the latent (see TrajectoryWindows).
WINDOW_KEYS = (
    keys.ACTION,
    keys.IS_FINAL,
    keys.TRAJECTORY_ID,
    keys.STEP,
    keys.COMPLETION_TARGET,
    keys.TERMINAL_LABEL,
    keys.QUALITY,
)


@dataclass
class LatentDynamicsConfig:
    """What :func:`compare_action_input` trains (the library's world-model hyper-parameters by default)."""

    # progress (fine-tuned with a completion scorer, then frozen) | random (frozen at its seeded initialisation)
    encoder: str = "progress"
    point_hidden: list[int] = field(default_factory=lambda: [64, 128, 256])  # DP3's point encoder
    point_out: int = 64
    state_out: int = 64
    scorer_hidden: int = 256
    encoder_batch_size: int = 128
    encoder_steps: int = 3000
    encoder_optim: OptimConfig = field(default_factory=scorer_optim)
    action_steps: int = 8  # k: the chunk the world model reads, and how far ahead it predicts
    wm_hidden: int = 256
    wm_layers: int = 3
    wm_heads: int = 4
    wm_batch_size: int = 512
    wm_steps: int = 5000
    wm_optim: OptimConfig = field(default_factory=dynamics_optim)
    held_out_fraction: float = 0.2  # of the trajectories
    seed: int = 0  # the split, the initial weights and the batches
    device: str = "cpu"
    precision: str = "auto"  # of the encoder's training (the world models train in fp32, as in train_world_model)
    checkpoint_every: int = 500
    progress: bool = True

    def __post_init__(self):
        check_choice("encoder", self.encoder, ENCODERS)
        check_choice("precision", self.precision, PRECISIONS)
        for name in (
            "point_out",
            "state_out",
            "scorer_hidden",
            "encoder_batch_size",
            "action_steps",
            "wm_hidden",
            "wm_layers",
            "wm_heads",
            "wm_batch_size",
            "checkpoint_every",
        ):
            check_at_least(name, getattr(self, name), 1)
        for name in ("encoder_steps", "wm_steps", "seed"):
            check_at_least(name, getattr(self, name), 0)
        if not 0.0 < self.held_out_fraction < 1.0:
            raise ValueError(f"held_out_fraction must lie in (0, 1), got {self.held_out_fraction}")


def latent_encoder(cfg: LatentDynamicsConfig, rows: TensorDict) -> LatentEncoder:
    """A latent encoder of DP3's architecture at its (seeded) initialisation, its normalizers fitted on ``rows``."""
    state_dim = rows[keys.AGENT_POS].shape[-1]
    return LatentEncoder(
        MinMaxNormalizer(3).fit(rows[keys.POINT_CLOUD]),
        PointCloudEncoder(tuple(cfg.point_hidden), cfg.point_out),
        MinMaxNormalizer(state_dim).fit(rows[keys.AGENT_POS]),
        StateEncoder(state_dim, out_dim=cfg.state_out),
    )


def latent_windows(dataset: TrajectoryDataset, latents: torch.Tensor, action_steps: int) -> TensorDict:
    """Every window of ``dataset`` on the rows' ``latents`` ``[R, L]``: ``latent`` ``s_t``, ``action_chunk`` (the
    ``k`` actions from ``t``, the last one repeated past the end), ``("future", "latent")`` ``s_{t+k}`` (``s_T``
    past the end) and the anchor's ``trajectory_id``."""
    rows = TensorDict({keys.LATENT: latents, **{k: dataset.rows[k] for k in WINDOW_KEYS}}, batch_size=[len(latents)])
    windows = TrajectoryWindows(
        TrajectoryDataset(dataset.root, dataset.meta, rows),
        obs_steps=1,
        horizon=action_steps,
        future_offset=action_steps,
        observation_keys=(keys.LATENT,),
    )
    batch = windows[torch.arange(len(windows))]
    batch[keys.LATENT] = batch[keys.LATENT][:, -1]  # the one-step history
    return batch


@torch.no_grad()
def latent_mse(world_model: LatentWorldModel | None, windows: TensorDict) -> float:
    """Mean squared error of ``world_model``'s ``s_hat_{t+k}`` against the encoded ``s_{t+k}`` over ``windows``;
    ``None`` is the "no change" predictor ``s_hat_{t+k} = s_t``."""
    imagined = windows[keys.LATENT] if world_model is None else imagine_windows(world_model, windows)
    return ((imagined - windows[keys.FUTURE, keys.LATENT]) ** 2).mean().item()


def _fit(
    cfg: LatentDynamicsConfig,
    loss_module,
    model: nn.Module,
    data: TensorDict,
    batch_size: int,
    steps: int,
    optim: OptimConfig,
    checkpoint: Path,
    dtype=None,
) -> nn.Module:
    """``model`` trained (or resumed from ``checkpoint``) on random batches of ``data``; its EMA weights."""
    return fit(
        loss_module,
        model,
        lambda g: data[torch.randint(len(data), (batch_size,), generator=g)],
        steps,
        optim,
        checkpoint,
        lambda ema: {},
        seed=cfg.seed,
        checkpoint_every=cfg.checkpoint_every,
        autocast_dtype=dtype,
        progress=cfg.progress,
    ).module


def compare_action_input(dataset: TrajectoryDataset, cfg: LatentDynamicsConfig, run_dir: str | Path) -> dict:
    """Trains the latent encoder and the world model with and without action input on ``dataset``'s training
    trajectories; returns their held-out latent MSEs (``with_action``, ``without_action``, ``no_change``) and the split.

    Training checkpoints go to ``run_dir`` (``encoder.pt``, ``dynamics_with_action.pt``,
    ``dynamics_without_action.pt``); a run that finds them resumes from them.

    Example:
        >>> import tempfile
        >>> import numpy as np
        >>> from torchrl_dalir.data import import_dp3_zarr, write_dp3_zarr
        >>> folder = Path(tempfile.mkdtemp())
        >>> rng = np.random.default_rng(0)
        >>> episodes = [{"point_cloud": rng.random((30, 64, 6)), "state": rng.random((30, 2)),
        ...              "action": rng.random((30, 2))} for _ in range(5)]
        >>> dataset = import_dp3_zarr(write_dp3_zarr(folder / "doc.zarr", episodes), folder / "dataset", num_points=32)
        >>> cfg = LatentDynamicsConfig(encoder="random", point_hidden=[16], wm_steps=20, wm_hidden=16, wm_layers=1,
        ...                            wm_heads=2, progress=False)
        >>> result = compare_action_input(dataset, cfg, folder / "run")
        >>> result["held_out_trajectories"], result["with_action"] != result["without_action"]
        ([4], True)
    """
    run_dir = Path(run_dir)
    torch.manual_seed(cfg.seed)
    rows = dataset.rows
    held = split_trajectories(dataset.num_trajectories, cfg.held_out_fraction, cfg.seed)
    train_rows = torch.nonzero(~held[rows[keys.TRAJECTORY_ID]]).squeeze(-1)
    observed = rows.select(keys.POINT_CLOUD, keys.AGENT_POS, keys.COMPLETION_TARGET)[train_rows]
    encoder = latent_encoder(cfg, observed).to(cfg.device)
    if cfg.encoder == "progress":
        pair = nn.ModuleDict(
            {"encoder": encoder, "scorer": TaskCompletionScorer(encoder.latent_dim, cfg.scorer_hidden).to(cfg.device)}
        )
        encoder = _fit(
            cfg,
            TaskCompletionLoss(pair["encoder"], pair["scorer"]),
            pair,
            observed,
            cfg.encoder_batch_size,
            cfg.encoder_steps,
            cfg.encoder_optim,
            run_dir / "encoder.pt",
            autocast_dtype(cfg.precision, cfg.device),
        )["encoder"]
    encoder.eval().requires_grad_(False)
    windows = latent_windows(dataset, encode_rows(encoder, rows, device=cfg.device), cfg.action_steps)
    held_windows = held[windows[keys.TRAJECTORY_ID]]
    train, test = windows[~held_windows], windows[held_windows]
    actions = rows[keys.ACTION][train_rows][~rows[keys.IS_FINAL][train_rows]]
    result = {"no_change": latent_mse(None, test)}
    for name, action_input in VARIANTS.items():
        torch.manual_seed(cfg.seed)  # the same initial weights for both
        world_model = LatentWorldModel(
            encoder.latent_dim,
            actions.shape[-1],
            cfg.action_steps,
            cfg.wm_hidden,
            cfg.wm_layers,
            cfg.wm_heads,
            action_input=action_input,
        )
        world_model.action_normalizer.fit(actions)
        world_model = (
            _fit(
                cfg,
                LatentDynamicsLoss(world_model),
                world_model.to(cfg.device),
                train,
                cfg.wm_batch_size,
                cfg.wm_steps,
                cfg.wm_optim,
                run_dir / f"dynamics_{name}.pt",
            )
            .eval()
            .cpu()
        )
        result[name] = latent_mse(world_model, test)
    return {
        **result,
        "latent_dim": encoder.latent_dim,
        "trajectories": dataset.num_trajectories,
        "held_out_trajectories": torch.nonzero(held).squeeze(-1).tolist(),
        "train_windows": len(train),
        "held_out_windows": len(test),
    }
