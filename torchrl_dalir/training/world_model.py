"""Training DALI-R's latent imagination module on the mixed-quality data, the policy frozen.

Three stages, each resumable:

1. **Scorer**: the latent encoder (a copy of the policy's encoders) and the task-completion
   scorer are trained together with binary cross-entropy on the discounted Monte-Carlo targets
   (the paper). With ``encoder=frozen`` the copy keeps the policy's weights, every row's latent
   is computed once and the scorer alone learns from them, for the paper's full number of
   epochs at a fraction of the cost.
2. **World model**: the encoder is frozen, every row's latent is computed once, and the world
   model learns ``s_{t+k} - s_t`` from ``(s_t, a_{t:t+k})``. Frozen targets cannot collapse; the
   held-out MSE is reported next to the "no change" predictor ``s_hat = s_t``.
3. **Scorer ensemble**: every training window's recorded chunk is imagined once with the frozen
   world model, and an ensemble of scorers learns the completion target at ``t + k`` from the
   imagined latent: DALI-R scores imagined latents at inference, and the ensemble is trained on
   imagined latents too (of the world model's own training windows, so with in-sample imagination
   error); its members' disagreement feeds the pessimistic selection rules
   (:mod:`torchrl_dalir.reranking.selection`).

Trajectories (not rows) are split into training and held-out sets, so held-out metrics never
see a step of a training trajectory.

Under torchrun the three trainings run data-parallel; the steps between them (encoding every
row, imagining every window) are deterministic and run on every rank (they take the same time
as in one process), and only rank 0 computes the held-out metrics and writes ``world_model.pt``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.checkpoints import load_policy, save_world_model
from torchrl_dalir.config import check_at_least, check_choice, config_dict
from torchrl_dalir.data import TrajectoryDataset, dense_reward_targets
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.envs.tasks import get_task
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, ScorerEnsemble, TaskCompletionScorer
from torchrl_dalir.modules.policy_interface import ChunkPolicy, check_chunk_policy
from torchrl_dalir.modules.world_model import POLICY_ENCODERS
from torchrl_dalir.objectives import ImaginedCompletionLoss, LatentDynamicsLoss, TaskCompletionLoss
from torchrl_dalir.objectives.imagined_completion import IMAGINED_LATENT
from torchrl_dalir.objectives.latent_dynamics import LATENT
from torchrl_dalir.training import distributed
from torchrl_dalir.training.logging import make_logger, wandb_mode
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.training.precision import PRECISIONS, autocast_dtype
from torchrl_dalir.utils import weights_digest

# The scorer's training target: the sparse terminal labels' Monte-Carlo targets (the method), or
# the simulator's dense reward-to-go (an oracle, for the ablation).
SCORER_TARGETS = {"completion": keys.COMPLETION_TARGET, "dense_reward": keys.DENSE_REWARD_TARGET}
# Tasks whose simulator reward is no oracle: gymnasium-robotics' Door-v1 dense reward (since
# 1.2.1) grows with the palm-to-handle distance, so it rewards moving away from the handle.
MISLEADING_DENSE_REWARD = {
    "door": "its dense reward grows with the palm-to-handle distance (gymnasium-robotics >= 1.2.1)"
}
ENCODER_MODES = ("finetune", "frozen")


def scorer_optim() -> OptimConfig:
    """The optimiser of the latent encoder and scorer (the paper's): AdamW 1e-4, weight decay 1e-3."""
    return OptimConfig(lr=1e-4, betas=(0.9, 0.999), weight_decay=1e-3, warmup_steps=0)


def dynamics_optim() -> OptimConfig:
    """The optimiser of the latent world model: AdamW 3e-4, weight decay 1e-4."""
    return OptimConfig(lr=3e-4, betas=(0.9, 0.999), weight_decay=1e-4, warmup_steps=0)


@dataclass
class WorldModelTrainingConfig:
    """``examples/train_world_model.py``'s configuration (the paper's hyper-parameters by default).

    Example:
        >>> from torchrl_dalir.config import parse_config
        >>> cfg = parse_config(WorldModelTrainingConfig, ["preset=smoke", "task=reach", "encoder=frozen"], PRESETS)
        >>> cfg.wm_hidden, cfg.ensemble_members, cfg.run_dir().as_posix()  # the variant is in the run's name
        (32, 2, 'outputs/world_models/reach/seed0_frozen')
    """

    task: str = "disassemble"
    preset: str = "cpu"
    seed: int = 0
    device: str = "cpu"  # under torchrun, cuda means cuda:<LOCAL_RANK> for each rank
    data: str = "outputs/data"  # the mixed data is read from <data>/<task>/<mixed_name>
    mixed_name: str = "mixed"
    extra_data: list[str] = field(default_factory=list)  # more datasets of <data>/<task>/ added to the mixed data
    # finetune (the paper: trained with the scorer) | frozen (the policy's encoder, latents computed once)
    encoder: str = "finetune"
    policy_checkpoint: str = "outputs/policies/disassemble/fm_seed0/checkpoint.pt"
    out: str = "outputs/world_models"  # the run writes <out>/<task>/seed<seed>/
    held_out_fraction: float = 0.1
    mixed_trajectories: int = (
        0  # train on this many of the training trajectories (0: all); the held-out set stays the same
    )
    scorer_target: str = "completion"  # completion (sparse labels) | dense_reward (the oracle ablation)
    dense_reward_gamma: float = 0.99
    scorer_hidden: int = 256
    scorer_batch_size: int = 128  # batch sizes are global: under torchrun each of N ranks trains on 1/N of each batch
    scorer_epochs: int = 30
    scorer_steps: int = 0  # 0: derive from scorer_epochs
    frozen_scorer_steps: int = 0  # with encoder=frozen (0: derive from scorer_epochs)
    scorer_optim: OptimConfig = field(default_factory=scorer_optim)
    wm_hidden: int = 256
    wm_layers: int = 3
    wm_heads: int = 4
    wm_batch_size: int = 512
    wm_epochs: int = 100
    wm_steps: int = 0  # 0: derive from wm_epochs
    wm_optim: OptimConfig = field(default_factory=dynamics_optim)
    ensemble_sources: list[str] = field(
        default_factory=list
    )  # train the ensemble on these sources only (e.g. [base_policy,exploration]); empty: all
    ensemble_members: int = 5
    ensemble_hidden: int = 256
    ensemble_batch_size: int = 256
    ensemble_steps: int = 3000  # cheap: the imagined latents are computed once
    ensemble_optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(lr=3e-4, betas=(0.9, 0.999), weight_decay=1e-3, warmup_steps=0)
    )
    precision: str = "auto"  # auto (bf16 autocast where the hardware runs it natively) | bf16 | fp32
    checkpoint_every: int = 500
    log_every: int = 50
    wandb: str = "off"  # off (CSV only) | offline | online (training/logging.py); true/false: offline/off
    progress: bool = True

    def __post_init__(self):
        get_task(self.task)  # an unknown name fails here, with the list of known ones
        check_choice("scorer_target", self.scorer_target, SCORER_TARGETS)
        if self.scorer_target == "dense_reward" and self.task in MISLEADING_DENSE_REWARD:
            raise ValueError(
                f"scorer_target=dense_reward is no oracle on {self.task}: {MISLEADING_DENSE_REWARD[self.task]}; "
                "use the sparse labels (scorer_target=completion)"
            )
        check_choice("encoder", self.encoder, ENCODER_MODES)
        check_choice("precision", self.precision, PRECISIONS)
        self.wandb = wandb_mode(self.wandb)
        for name in (
            "scorer_batch_size",
            "wm_batch_size",
            "ensemble_batch_size",
            "scorer_epochs",
            "wm_epochs",
            "ensemble_members",
            "checkpoint_every",
            "log_every",
        ):
            check_at_least(name, getattr(self, name), 1)
        for name in ("scorer_steps", "frozen_scorer_steps", "wm_steps", "ensemble_steps", "mixed_trajectories"):
            check_at_least(name, getattr(self, name), 0)
        for name in ("scorer_batch_size", "wm_batch_size", "ensemble_batch_size"):
            distributed.check_global_batch(name, getattr(self, name))

    def variant(self) -> str:
        """What sets this run apart from the paper's: ``""``, or e.g. ``"_frozen+explore"`` or
        ``"_frozen_ens-base_policy-exploration+explore"``."""
        parts = [self.scorer_target] if self.scorer_target != "completion" else []
        parts += [self.encoder] if self.encoder != "finetune" else []
        parts += ["ens-" + "-".join(self.ensemble_sources)] if self.ensemble_sources else []
        parts += [f"mixed{self.mixed_trajectories}"] if self.mixed_trajectories else []
        return "".join(f"_{p}" for p in parts) + "".join(f"+{name}" for name in self.extra_data)

    def run_dir(self) -> Path:
        return Path(self.out) / self.task / f"seed{self.seed}{self.variant()}"


#: Named overrides of :class:`WorldModelTrainingConfig` (``preset=paper|cpu|smoke``); ``paper`` is the paper's setting.
PRESETS: dict[str, dict] = {
    "paper": {},
    # About 10 minutes on a 2-core CPU: the policy's encoder frozen (latents computed once, the
    # scorer alone for 30 epochs; the fine-tuned encoder took ~30 min here, and `scorer_steps`
    # applies to it only), a smaller world model on smaller batches (a batch-512 step of the
    # paper's model takes ~0.6 s here).
    "cpu": {"encoder": "frozen", "scorer_steps": 1000, "wm_steps": 1500, "wm_batch_size": 256, "wm_hidden": 128},
    "smoke": {
        "scorer_steps": 20,
        "scorer_batch_size": 16,
        "wm_steps": 20,
        "wm_batch_size": 16,
        "wm_hidden": 32,
        "wm_layers": 1,
        "wm_heads": 2,
        "scorer_hidden": 32,
        "ensemble_members": 2,
        "ensemble_hidden": 16,
        "ensemble_steps": 20,
        "ensemble_batch_size": 16,
        "checkpoint_every": 10,
        "log_every": 10,
        "wandb": False,
        "held_out_fraction": 0.4,
        "precision": "fp32",  # the same numbers on every machine
    },
}


def training_data(cfg: WorldModelTrainingConfig) -> TrajectoryDataset:
    """The mixed data of ``cfg`` with its ``extra_data`` datasets appended (trajectory ids renumbered)."""
    root = Path(cfg.data) / cfg.task
    datasets = [TrajectoryDataset.load(root / name, task=cfg.task) for name in (cfg.mixed_name, *cfg.extra_data)]
    return datasets[0] if len(datasets) == 1 else TrajectoryDataset.concat(datasets)


def source_mask(dataset: TrajectoryDataset, names: list[str]) -> torch.Tensor:
    """A bool mask over ``dataset``'s source indices: ``True`` for the sources named ``names``."""
    known = [source["name"] for source in dataset.meta.sources]
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise ValueError(f"{dataset.root} has no source {unknown}; its sources are {known}")
    return torch.tensor([name in names for name in known])


def split_trajectories(num_trajectories: int, held_out_fraction: float, seed: int) -> torch.Tensor:
    """A bool mask over trajectories: ``True`` for held-out ones (at least one)."""
    order = torch.randperm(num_trajectories, generator=torch.Generator().manual_seed(seed))
    held = torch.zeros(num_trajectories, dtype=torch.bool)
    held[order[: max(1, round(held_out_fraction * num_trajectories))]] = True
    return held


def keep_trajectories(held: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """A bool mask over trajectories: ``count`` of the training ones (``~held``) drawn at random,
    nested for growing ``count`` (the data-scale ablation, paper Table 3b); all for ``count=0``."""
    train = torch.nonzero(~held).squeeze(-1)
    if count > len(train):
        raise ValueError(
            f"mixed_trajectories={count} but only {len(train)} training trajectories exist "
            f"({int(held.sum())} are held out): collect more mixed data or ask for fewer"
        )
    keep = ~held
    if count:
        order = train[torch.randperm(len(train), generator=torch.Generator().manual_seed(seed))]
        keep = torch.zeros_like(held)
        keep[order[:count]] = True
    return keep


@torch.no_grad()
def encode_rows(encoder: LatentEncoder, rows: TensorDict, batch_size: int = 1024, device="cpu") -> torch.Tensor:
    """The latent of every row, ``[R, L]``, written into one tensor allocated up front.

    Collecting per-batch pieces instead left small live blocks between each batch's large freed
    activations: a heap that is never trimmed (the examples' malloc tunables) then grew with every batch
    (``examples/benchmarks/benchmark_encoder_memory.py``, three passes over 20,000 rows: a 7.9 GiB peak,
    against 2.4 GiB written in place).
    """
    latents = torch.empty(len(rows), encoder.latent_dim)
    for start in range(0, len(rows), batch_size):
        chunk = rows[start : start + batch_size]
        latents[start : start + len(chunk)] = encoder(
            chunk[keys.POINT_CLOUD].to(device), chunk[keys.AGENT_POS].to(device)
        )
    return latents


def _scorer_metrics(probabilities: torch.Tensor, targets: torch.Tensor, bins: int = 10) -> dict:
    """Brier score and expected calibration error against the Monte-Carlo targets."""
    edges = torch.linspace(0, 1, bins + 1)
    which = torch.bucketize(probabilities, edges[1:-1])
    ece = sum(
        (which == b).float().mean() * (probabilities[which == b].mean() - targets[which == b].mean()).abs()
        for b in range(bins)
        if (which == b).any()
    )
    return {"brier": ((probabilities - targets) ** 2).mean().item(), "calibration_error": float(ece)}


def frozen_policy(
    cfg: WorldModelTrainingConfig, policy: ChunkPolicy | str | Path | None = None
) -> tuple[ChunkPolicy, WorldModelTrainingConfig]:
    """The policy a world model is trained on top of, and ``cfg`` with its ``policy_checkpoint`` set to
    where it came from: loaded from ``cfg.policy_checkpoint`` (``policy=None``) or from a path, or a
    policy object (any :class:`~torchrl_dalir.modules.ChunkPolicy`; recorded as its ``checkpoint`` if
    it names one, else as its class and weights' digest). A policy of another task is refused."""
    if policy is None:
        return load_policy(cfg.policy_checkpoint, task=cfg.task), cfg
    if isinstance(policy, (str, Path)):
        return load_policy(policy, task=cfg.task), replace(cfg, policy_checkpoint=str(policy))
    check_chunk_policy(policy, "train_world_model")
    task = getattr(policy, "task", None)
    if task is not None and task != cfg.task:
        raise ValueError(f"the policy was trained on task {task!r}; this world model is for {cfg.task!r}")
    source = (
        getattr(policy, "checkpoint", None)
        or f"{type(policy).__name__} object (weights digest {weights_digest(policy)[:12]})"
    )
    return policy, replace(cfg, policy_checkpoint=str(source))


def train_world_model(cfg: WorldModelTrainingConfig, policy: ChunkPolicy | str | Path | None = None) -> Path:
    """Trains (or resumes) the latent encoder, scorer and world model; returns the checkpoint.
    Under torchrun, data-parallel over the ranks (only rank 0 writes).

    Args:
        cfg: the configuration.
        policy: the frozen policy to train on top of: ``None`` loads ``cfg.policy_checkpoint``; a
            path loads that checkpoint; or a policy object, this library's or any
            :class:`~torchrl_dalir.modules.ChunkPolicy` (the checkpoint records the digest of its
            ``state_dict``, and :meth:`~torchrl_dalir.reranking.RerankingActor.on_policy` refuses
            other weights). The latent encoder starts as a copy of the policy's encoders if it has
            DP3's (:data:`~torchrl_dalir.modules.world_model.POLICY_ENCODERS`); otherwise it is a
            new encoder of DP3's architecture, its normalizers fitted on the training rows, trained
            with the scorer (``encoder=finetune``; ``frozen`` needs the policy's encoders).
    """
    run_dir = cfg.run_dir()
    final = run_dir / "world_model.pt"
    if final.exists():
        return final
    device = distributed.setup(cfg.device)
    torch.manual_seed(cfg.seed)
    policy, cfg = frozen_policy(cfg, policy)
    mixed = training_data(cfg)
    rows = mixed.rows
    ensemble_sources = (
        source_mask(mixed, cfg.ensemble_sources) if cfg.ensemble_sources else None
    )  # fails before any training
    target_key = SCORER_TARGETS[cfg.scorer_target]
    if cfg.scorer_target == "dense_reward":  # an in-memory target next to the memory-mapped rows
        rows = TensorDict(dict(rows.items()), batch_size=rows.batch_size)
        rows[target_key] = dense_reward_targets(rows, cfg.dense_reward_gamma)
    held = split_trajectories(mixed.num_trajectories, cfg.held_out_fraction, cfg.seed)
    held_rows = held[rows[keys.TRAJECTORY_ID]]
    kept = keep_trajectories(held, cfg.mixed_trajectories, cfg.seed)
    train_rows = torch.nonzero(kept[rows[keys.TRAJECTORY_ID]]).squeeze(-1)
    if ensemble_sources is not None and not ensemble_sources[rows[keys.SOURCE][train_rows]].any():
        raise ValueError(
            f"no training trajectory of the sources {cfg.ensemble_sources} (all held out?): "
            "add data of them or name others"
        )
    logger = make_logger(run_dir, f"{cfg.task}_world_model_seed{cfg.seed}", wandb=cfg.wandb, config=config_dict(cfg))
    autocast = autocast_dtype(cfg.precision, device)

    def train_stage(loss_module, model, data, train_index, batch_shape, steps, optim, name, dtype=None):
        """Trains one stage on random batches ``[*batch_shape]`` of ``data[train_index]`` (split over
        torchrun's ranks along the last dimension); resumes from ``<name>.pt``."""
        return fit(
            loss_module,
            model,
            lambda g: data[train_index[torch.randint(len(train_index), batch_shape, generator=g)]],
            steps,
            optim,
            run_dir / f"{name}.pt",
            lambda ema: {},
            seed=cfg.seed,
            checkpoint_every=cfg.checkpoint_every,
            log=lambda m, s: logger({f"{name}/{k}": v for k, v in m.items()}, s),
            log_every=cfg.log_every,
            autocast_dtype=dtype,
            progress=cfg.progress,
            shard_dim=len(batch_shape) - 1,
        ).module

    # Stage 1: latent encoder + task-completion scorer (or the scorer alone on frozen latents).
    if all(hasattr(policy, name) for name in POLICY_ENCODERS):
        encoder = LatentEncoder.from_policy(policy).to(device)
    elif cfg.encoder == "frozen":
        raise ValueError(
            f"encoder=frozen keeps the policy's own encoders, and {type(policy).__name__} has none to copy "
            f"({', '.join(POLICY_ENCODERS)}): use encoder=finetune, which trains a new encoder with the scorer"
        )
    else:  # a policy of another design: a new encoder of DP3's architecture, trained with the scorer
        encoder = LatentEncoder.fresh(rows[keys.AGENT_POS].shape[-1])
        encoder = encoder.fit_normalizers(rows[keys.POINT_CLOUD][train_rows], rows[keys.AGENT_POS][train_rows]).to(
            device
        )
    scorer = TaskCompletionScorer(encoder.latent_dim, cfg.scorer_hidden).to(device)
    epoch_steps = cfg.scorer_epochs * -(-len(train_rows) // cfg.scorer_batch_size)
    if cfg.encoder == "finetune":
        pair = nn.ModuleDict({"encoder": encoder, "scorer": scorer})
        ema_pair = train_stage(
            TaskCompletionLoss(encoder, scorer, target_key),
            pair,
            rows,
            train_rows,
            (cfg.scorer_batch_size,),
            cfg.scorer_steps or epoch_steps,
            cfg.scorer_optim,
            "scorer",
            autocast,
        )
        encoder, scorer = ema_pair["encoder"].eval(), ema_pair["scorer"].eval()
    encoder.eval().requires_grad_(False)
    latents = encode_rows(encoder, rows, device=device)
    if cfg.encoder == "frozen":
        table = TensorDict({LATENT: latents, target_key: rows[target_key]}, [len(rows)])
        scorer = train_stage(
            TaskCompletionLoss(None, scorer, target_key),
            scorer,
            table,
            train_rows,
            (cfg.scorer_batch_size,),
            cfg.frozen_scorer_steps or epoch_steps,
            cfg.scorer_optim,
            "scorer",
        ).eval()

    # Stage 2: world model on latents of the frozen encoder.
    latent_rows = TensorDict(
        {
            LATENT: latents,
            **{
                k: rows[k]
                for k in (
                    keys.ACTION,
                    keys.IS_FINAL,
                    keys.TRAJECTORY_ID,
                    keys.STEP,
                    keys.COMPLETION_TARGET,
                    target_key,
                    keys.TERMINAL_LABEL,
                    keys.QUALITY,
                )
            },
        },
        batch_size=[len(rows)],
    )
    k = policy.action_steps
    future_keys = (
        (LATENT,) if target_key == keys.COMPLETION_TARGET else (LATENT, target_key)
    )  # the ensemble's target at t + k
    windows = TrajectoryWindows(
        TrajectoryDataset(mixed.root, mixed.meta, latent_rows),
        obs_steps=1,
        horizon=k,
        future_offset=k,
        observation_keys=future_keys,
    )
    anchor_trajectories = windows.dataset.rows[keys.TRAJECTORY_ID][windows.anchors]
    held_anchor = held[anchor_trajectories]
    train_anchors = torch.nonzero(kept[anchor_trajectories]).squeeze(-1)

    def wm_batch(indices):
        batch = windows[indices]
        batch[LATENT] = batch[LATENT][:, -1]
        return batch

    world_model = LatentWorldModel(encoder.latent_dim, policy.action_dim, k, cfg.wm_hidden, cfg.wm_layers, cfg.wm_heads)
    world_model.action_normalizer.fit(rows[keys.ACTION][~rows[keys.IS_FINAL]])
    world_model.to(device)
    wm_steps = cfg.wm_steps or cfg.wm_epochs * -(-len(train_anchors) // cfg.wm_batch_size)
    train_windows = wm_batch(train_anchors)  # small (latents and actions only): gathered once
    world_model = train_stage(
        LatentDynamicsLoss(world_model),
        world_model,
        train_windows,
        torch.arange(len(train_windows)),
        (cfg.wm_batch_size,),
        wm_steps,
        cfg.wm_optim,
        "dynamics",
    ).eval()

    # Stage 3: the scorer ensemble on imagined latents of the recorded chunks, against the
    # target at t + k (each member on its own random batches); with ``ensemble_sources``, only
    # the chunks of those sources (e.g. the base policy's own rollouts: its outcomes from there on).
    imagined = TensorDict(
        {IMAGINED_LATENT: imagine_windows(world_model, train_windows), keys.FUTURE: train_windows[keys.FUTURE]},
        [len(train_windows)],
    )
    ensemble_index = torch.arange(len(imagined))
    if ensemble_sources is not None:
        ensemble_index = torch.nonzero(ensemble_sources[rows[keys.SOURCE][windows.anchors[train_anchors]]]).squeeze(-1)
    ensemble = ScorerEnsemble(encoder.latent_dim, cfg.ensemble_hidden, cfg.ensemble_members).to(device)
    ensemble_loss = ImaginedCompletionLoss(ensemble)
    ensemble_loss.set_keys(target=(keys.FUTURE, target_key))
    ensemble = train_stage(
        ensemble_loss,
        ensemble,
        imagined,
        ensemble_index,
        (cfg.ensemble_members, cfg.ensemble_batch_size),
        cfg.ensemble_steps,
        cfg.ensemble_optim,
        "ensemble",
    ).eval()

    if not distributed.is_main():
        distributed.barrier()  # until rank 0 has written the checkpoint
        return final
    encoder, scorer, world_model, ensemble = (
        encoder.cpu(),
        scorer.cpu(),
        world_model.cpu(),
        ensemble.cpu(),
    )  # metrics and checkpoint on the CPU
    metrics = held_out_metrics(
        encoder,
        scorer,
        world_model,
        latent_rows,
        held_rows,
        windows,
        torch.nonzero(held_anchor).squeeze(-1),
        wm_batch,
        target_key,
    )
    metrics.update(
        held_out_imagined_metrics(
            scorer, ensemble, world_model, wm_batch(torch.nonzero(held_anchor).squeeze(-1)), target_key
        )
    )
    metrics["ensemble_windows"] = len(ensemble_index)
    logger({f"held_out/{k}": v for k, v in metrics.items()}, wm_steps)
    save_world_model(
        final,
        policy=policy,
        policy_checkpoint=cfg.policy_checkpoint,
        task=cfg.task,
        encoder=encoder,
        scorer=scorer,
        world_model=world_model,
        ensemble=ensemble,
        world_model_args=dict(
            latent_dim=encoder.latent_dim,
            action_dim=policy.action_dim,
            action_steps=k,
            hidden=cfg.wm_hidden,
            layers=cfg.wm_layers,
            heads=cfg.wm_heads,
        ),
        scorer_hidden=cfg.scorer_hidden,
        ensemble_args=dict(latent_dim=encoder.latent_dim, hidden=cfg.ensemble_hidden, members=cfg.ensemble_members),
        held_out_trajectories=torch.nonzero(held).squeeze(-1).tolist(),
        metrics=metrics,
        encoder_mode=cfg.encoder,
        config=config_dict(cfg),
    )
    distributed.barrier()
    return final


@torch.no_grad()
def held_out_metrics(
    encoder,
    scorer,
    world_model,
    latent_rows,
    held_rows,
    windows,
    held_anchors,
    wm_batch,
    target_key=keys.COMPLETION_TARGET,
) -> dict:
    """Scorer Brier score and calibration error against its targets on held-out rows; world-model
    MSE on held-out windows next to the "no change" predictor."""
    latents = latent_rows[LATENT][held_rows]
    probabilities = torch.sigmoid(scorer(latents))
    metrics = _scorer_metrics(probabilities, latent_rows[target_key][held_rows].float())
    batch = wm_batch(held_anchors)
    imagined = world_model.imagine(batch[LATENT], batch[keys.ACTION_CHUNK])
    future = batch["future", LATENT]
    metrics["wm_mse"] = ((imagined - future) ** 2).mean().item()
    metrics["no_change_mse"] = ((batch[LATENT] - future) ** 2).mean().item()
    metrics["held_out_rows"] = int(held_rows.sum())
    return metrics


@torch.no_grad()
def imagine_windows(world_model: LatentWorldModel, windows: TensorDict, batch_size: int = 4096) -> torch.Tensor:
    """``s_hat_{t+k}`` of every window's recorded chunk, ``[W, L]``."""
    device = next(world_model.parameters()).device
    return torch.cat(
        [
            world_model.imagine(part[LATENT].to(device), part[keys.ACTION_CHUNK].to(device)).cpu()
            for part in windows.split(batch_size)
        ]
    )


@torch.no_grad()
def held_out_imagined_metrics(scorer, ensemble, world_model, batch, target_key=keys.COMPLETION_TARGET) -> dict:
    """Brier score and calibration error, on the imagined latents of held-out windows against the
    target at ``t + k``, of the state scorer (as DALI-R applies it) and of the ensemble's mean;
    and the ensemble members' mean disagreement (std of their probabilities)."""
    imagined = imagine_windows(world_model, batch)
    target = batch[keys.FUTURE, target_key].float()
    members = torch.sigmoid(ensemble(imagined))
    state = _scorer_metrics(torch.sigmoid(scorer(imagined)), target)
    mean = _scorer_metrics(members.mean(0), target)
    return {
        "imagined_brier_state_scorer": state["brier"],
        "imagined_calibration_error_state_scorer": state["calibration_error"],
        "imagined_brier_ensemble": mean["brier"],
        "imagined_calibration_error_ensemble": mean["calibration_error"],
        "ensemble_std": members.std(0, correction=0).mean().item(),
    }
