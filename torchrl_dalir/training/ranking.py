"""Training a scorer that ranks a decision's candidates, on branched outcomes, and measuring it.

Three inputs, side by side (issue: the world model's error on the candidates exceeds their spread):

- ``state_chunk``: the policy's condition of the decision's observation history (or the rows' own
  ``policy_condition``, precomputed), with the candidate's executed actions (min-max normalised on the
  data): a Q-function of the chunk that never passes through the world model;
- ``imagined``: the world model's imagined latent after the chunk, as the paper's scorer reads it
  (needs a world model and its latent encoder);
- ``privileged_chunk``: the simulator's low-dimensional state at the decision (the rows'
  ``privileged_state``, standardised on the training rows) with the executed actions: a privileged
  teacher, for measurement and distillation only (nothing at test time reads simulator state).

The target is each candidate's 0/1 branched outcome, or with ``targets="soft"`` the rows'
``soft_success``, its mean outcome over several draws of the base policy's noise.

The measure is the within-decision AUC on held-out decisions that split
(:func:`~torchrl_dalir.branching.candidate_outcomes.within_decision_auc`), with the held-out
decisions taken from whole episodes the scorer never saw.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.branching.candidate_outcomes import within_decision_auc
from torchrl_dalir.branching.outcomes import RESET_SEED, SUCCESS, BranchedOutcomes
from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.data.storage import TrajectoryDataset
from torchrl_dalir.data.windows import TrajectoryWindows
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.modules.world_model import TaskCompletionScorer
from torchrl_dalir.objectives.distance_hinge import CONDITION, EXECUTED, PERTURBED, DistanceHingeLoss
from torchrl_dalir.objectives.within_state_ranking import CANDIDATE_FEATURES, WithinStateRankingLoss, split_decisions
from torchrl_dalir.reranking.candidates import candidate_generator
from torchrl_dalir.reranking.config import RerankingConfig

INPUTS = ("state_chunk", "imagined", "privileged_chunk")
TARGETS = ("outcome", "soft")
POLICY_CONDITION = "policy_condition"  # [B, C] the policy's condition of a decision, precomputed (optional)
SOFT_SUCCESS = "soft_success"  # [B, K] float, each candidate's mean outcome over noise draws
TARGET = "target"  # the loss's target in the training table: SUCCESS or SOFT_SUCCESS


@dataclass
class RankingTrainingConfig:
    """Args:
    input: what the scorer reads of a candidate (``INPUTS``).
    hidden: the scorer MLP's width.
    steps, batch_size, lr, weight_decay: AdamW on batches of decisions.
    outcome_weight: the terminal-label loss beside the ranking loss (:class:`WithinStateRankingLoss`).
    ranking: with ``False``, the terminal-label loss alone (the ablation: outcomes, no ranking).
    targets: ``outcome`` (the stored 0/1 outcome) or ``soft`` (the rows' ``soft_success``); the measure is
        always the 0/1 outcome.
    held_out_fraction: the share of episodes (the last ones) held out for the measure.
    seed: initialisation and batch order.
    """

    input: str = "state_chunk"
    hidden: int = 128
    steps: int = 1500
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-3
    outcome_weight: float = 0.5
    ranking: bool = True
    targets: str = "outcome"
    held_out_fraction: float = 0.3
    seed: int = 0

    def __post_init__(self):
        check_choice("input", self.input, INPUTS)
        check_choice("targets", self.targets, TARGETS)
        for name in ("steps", "batch_size", "hidden"):
            check_at_least(name, getattr(self, name), 1)
        if not 0 < self.held_out_fraction < 1:
            raise ValueError(f"held_out_fraction must lie in (0, 1), got {self.held_out_fraction}")


@torch.no_grad()
def candidate_features(
    rows: TensorDict,
    policy,
    input: str = "state_chunk",
    critic: ChunkCritic | None = None,
    encoder=None,
    world_model=None,
) -> torch.Tensor:
    """What the scorer reads of each candidate of branched decisions ``rows``: ``[B, K, F]`` (``state_chunk``:
    ``critic``'s features of the policy's condition and the executed actions; ``privileged_chunk``: of the rows'
    ``privileged_state`` and the executed actions; ``imagined``: the imagined latent)."""
    executed = _executed(rows, policy)
    if input == "privileged_chunk":
        return critic.features(rows[keys.PRIVILEGED_STATE], executed)
    if input == "state_chunk":
        return critic.features(policy_conditions(rows, policy), executed)
    cloud, agent_pos = rows[keys.POINT_CLOUD], rows[keys.AGENT_POS]
    if encoder is None or world_model is None:
        raise ValueError("input=imagined needs the world model and its latent encoder")
    latent = encoder(cloud[:, -1], agent_pos[:, -1]).unsqueeze(1).expand(-1, executed.shape[1], -1)
    return world_model.imagine(latent, executed)


def policy_conditions(rows: TensorDict, policy) -> torch.Tensor:
    """The policy's conditions ``[B, C]`` of branched decisions: the rows' ``policy_condition`` if they hold it
    (a benchmark without the policy's weights), else the policy's encoding of their observation histories."""
    if POLICY_CONDITION in rows.keys():
        return rows[POLICY_CONDITION]
    return policy.encode(rows[keys.POINT_CLOUD], rows[keys.AGENT_POS])


def standardised(state: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """``state`` ``[..., S]`` standardised by the mean and spread of ``reference`` ``[B, S]`` (the training rows'
    privileged states: what a privileged teacher reads)."""
    scale = reference.std(0, unbiased=False).clamp(min=1e-3)  # constant coordinates stay at 0
    return (state - reference.mean(0)) / scale


def _standardised_state(rows: TensorDict, train: torch.Tensor) -> TensorDict:
    """The rows with ``privileged_state`` standardised by the training rows' mean and spread."""
    state = rows[keys.PRIVILEGED_STATE]
    return rows.clone(False).set(keys.PRIVILEGED_STATE, standardised(state, state[train]))


def _rows(outcomes: BranchedOutcomes | TensorDict) -> TensorDict:
    """The decisions of branched outcomes, or a table of them, in memory."""
    return outcomes.rows.to_tensordict() if hasattr(outcomes, "rows") else outcomes


def _executed(rows: TensorDict, policy) -> torch.Tensor:
    """The executed actions ``[B, K, k, A]`` of branched decisions' candidate chunks."""
    return rows[keys.ACTION_CHUNK][:, :, executed_slice(policy.obs_steps, policy.action_steps)]


def _held_out(rows: TensorDict, fraction: float) -> torch.Tensor:
    """Which decisions belong to the held-out episodes: the last ``fraction`` of the episodes by reset seed."""
    seeds = rows[RESET_SEED].unique(sorted=True)
    cut = seeds[len(seeds) - max(1, round(fraction * len(seeds)))]
    return rows[RESET_SEED] >= cut


def train_ranking_scorer(
    outcomes: BranchedOutcomes,
    policy,
    cfg: RankingTrainingConfig,
    encoder=None,
    world_model=None,
    progress_every: int = 0,
    device="cpu",
    held_out: torch.Tensor | None = None,
) -> tuple[nn.Module, dict]:
    """Trains a scorer on the training episodes of ``outcomes`` and measures it on the held-out ones
    (``held_out``, a mask over the decisions; by default the last ``cfg.held_out_fraction`` of the episodes).
    Returns the scorer and its metrics: the losses at the start and end, the within-decision AUC on the
    training and the held-out decisions that split (with their counts), and the held-out logits."""
    torch.manual_seed(cfg.seed)
    rows = _rows(outcomes).to(device)
    executed = _executed(rows, policy)
    held_out = (_held_out(rows, cfg.held_out_fraction) if held_out is None else held_out).to(device)
    critic = None
    if cfg.input == "privileged_chunk":
        rows = _standardised_state(rows, ~held_out)
    if cfg.input in ("state_chunk", "privileged_chunk"):
        first = rows[:1]
        cond = first[keys.PRIVILEGED_STATE] if cfg.input == "privileged_chunk" else policy_conditions(first, policy)
        critic = ChunkCritic(cond.shape[-1], policy.action_dim, policy.action_steps, hidden=cfg.hidden).to(device)
        critic.action_normalizer.fit(executed[~held_out])  # the training episodes' actions only
    features = candidate_features(rows, policy, cfg.input, critic, encoder, world_model)
    target = rows[SOFT_SUCCESS] if cfg.targets == "soft" else rows[SUCCESS]
    table = TensorDict({CANDIDATE_FEATURES: features, SUCCESS: rows[SUCCESS], TARGET: target}, [len(rows)])
    train, test = table[~held_out], table[held_out]
    scorer = (
        critic.scorer if critic is not None else TaskCompletionScorer(features.shape[-1], hidden=cfg.hidden).to(device)
    )
    loss_module = WithinStateRankingLoss(scorer, cfg.outcome_weight if cfg.ranking else 1.0)
    loss_module.set_keys(success=TARGET)  # the outcome or its mean over draws; the measure reads SUCCESS
    optimizer = torch.optim.AdamW(scorer.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    generator = torch.Generator().manual_seed(cfg.seed)

    def total(losses: TensorDict) -> torch.Tensor:
        return losses["loss_outcome"] + (losses["loss_ranking"] if cfg.ranking else 0)

    with torch.no_grad():
        first = {k: float(v) for k, v in loss_module(train).items()}
    for step in range(cfg.steps):
        batch = train[torch.randint(len(train), (min(cfg.batch_size, len(train)),), generator=generator)]
        loss = total(loss_module(batch))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if progress_every and step % progress_every == 0:
            print(f"step {step}: {float(loss):.4f}", flush=True)
    scorer.eval()
    with torch.no_grad():
        last = {k: float(v) for k, v in loss_module(train).items()}

        def auc(part: TensorDict) -> float:
            return within_decision_auc(scorer(part[CANDIDATE_FEATURES]).cpu().tolist(), part[SUCCESS].cpu().tolist())

        def splits(part: TensorDict) -> int:
            return int(split_decisions(part[SUCCESS]).sum())

        metrics = {
            "config": asdict(cfg),
            "loss_start": first,
            "loss_end": last,
            "train_decisions": len(train),
            "train_split_decisions": splits(train),
            "train_auc": auc(train),
            "held_out_decisions": len(test),
            "held_out_split_decisions": splits(test),
            "held_out_auc": auc(test),
            "held_out_logits": scorer(test[CANDIDATE_FEATURES]).cpu().tolist(),
        }
    return (critic if critic is not None else scorer).eval(), metrics


def cross_validated_auc(
    outcomes: BranchedOutcomes,
    policy,
    cfg: RankingTrainingConfig,
    folds: int = 0,
    judge: torch.Tensor | None = None,
    train=None,
    pool: TensorDict | None = None,
    **kwargs,
) -> dict:
    """The out-of-fold within-decision AUC: the episodes fall into ``folds`` groups (0: one per episode), and the
    decisions of each group are scored by a scorer trained on the others' (:func:`train_ranking_scorer`, with
    ``kwargs``). Every decision that splits is then judged by a scorer that never saw its episode, which uses all
    of them where a single held-out share leaves few. Groups without a split decision are not trained on.
    Also the branches' success rate when each decision executes the clean candidate, the scorer's out-of-fold
    arg-max, or a winner where one exists: an offline estimate, on data seeds, of what the arg-max would gain.
    With ``judge`` ``[D, K]`` (e.g. each candidate's mean outcome over several noise draws), the clean and the
    picked candidates are judged by it instead of the stored outcome. ``train`` replaces
    :func:`train_ranking_scorer` (same arguments and returns; e.g.
    :func:`~torchrl_dalir.training.distillation.train_student`). ``pool``: more decisions (rows with the same keys,
    e.g. other runs of the task) added to every fold's training and never scored: does more labelled data help?"""
    train = train if train is not None else train_ranking_scorer
    rows = _rows(outcomes)
    success = rows[SUCCESS]
    split = split_decisions(success)
    seeds = rows[RESET_SEED].unique(sorted=True)
    logits = torch.full(success.shape, float("nan"))
    trained_on = rows if pool is None else torch.cat([rows, pool])
    never_held_out = torch.zeros(len(trained_on) - len(rows), dtype=torch.bool)  # the pool's decisions
    for group in seeds.tensor_split(folds or len(seeds)):
        fold = torch.isin(rows[RESET_SEED], group)
        if (split & fold).any() and not fold.all():  # a single episode has nothing to train on out of fold
            held_out = torch.cat([fold, never_held_out])
            _, metrics = train(trained_on, policy, cfg, held_out=held_out, **kwargs)
            logits[fold] = torch.tensor(metrics["held_out_logits"])
    scored = split & ~logits.isnan().any(-1)
    # the stored outcome: where the candidates do not split, any pick does as the clean one; a judge (the
    # chance over draws) tells apart the candidates of every decision, so the scorer picks at all it scored
    asked = scored if judge is None else ~logits.isnan().any(-1)
    judge = (success if judge is None else judge).float()
    picked = judge[:, 0].clone()
    picked[asked] = judge[asked].gather(-1, logits[asked].argmax(-1, keepdim=True)).squeeze(-1)
    return {
        "folds": min(folds, len(seeds)) if folds else len(seeds),
        "split_decisions": int(split.sum()),
        "auc": within_decision_auc(logits[scored].tolist(), success[scored].tolist()),
        # the branches' success rate under three choices: the clean candidate, the scorer's arg-max (out of
        # fold), and a winner wherever there is one (the oracle)
        "clean_success": judge[:, 0].mean().item(),
        "pick_success": picked.float().mean().item(),
        "oracle_success": success.any(-1).float().mean().item(),
    }


# The chunk critic's two losses on branched outcomes: the terminal-label loss alone, or the listwise loss beside it.
CRITIC_VARIANTS = {"outcome": {"ranking": False}, "ranking": {"ranking": True}}


def fit_critic(
    outcomes: BranchedOutcomes,
    policy,
    cfg: RankingTrainingConfig | None = None,
    variants: tuple[str, ...] = tuple(CRITIC_VARIANTS),
    folds: int = 10,
    device="cpu",
) -> tuple[ChunkCritic, dict]:
    """A chunk critic for reranking: the variant of ``variants`` (:data:`CRITIC_VARIANTS`) with the higher
    out-of-fold within-decision AUC (``folds`` groups of episodes; the first listed on a tie or where no decision
    splits), then trained on every decision. Returns it and its metrics (``variant``, every variant's
    ``out_of_fold`` AUC, the losses and the training AUC)."""
    cfg = cfg if cfg is not None else RankingTrainingConfig()
    for variant in variants:
        check_choice("critic variant", variant, CRITIC_VARIANTS)
    aucs = {
        v: cross_validated_auc(outcomes, policy, replace(cfg, **CRITIC_VARIANTS[v]), folds=folds, device=device)
        for v in variants
    }
    best = max(variants, key=lambda v: (np.nan_to_num(aucs[v]["auc"], nan=-1.0), -variants.index(v)))
    everything = torch.zeros(len(outcomes), dtype=torch.bool)
    critic, metrics = train_ranking_scorer(
        outcomes, policy, replace(cfg, **CRITIC_VARIANTS[best]), held_out=everything, device=device
    )
    for unmeasured in ("held_out_logits", "held_out_auc", "held_out_decisions", "held_out_split_decisions"):
        metrics.pop(unmeasured)
    return critic, {"variant": best, "out_of_fold": aucs, **metrics}


NEGATIVES = ("noise", "policy")


@dataclass
class MixedCriticConfig:
    """The no-simulator route: a chunk critic on mixed data's recorded decisions (:class:`DistanceHingeLoss`).

    Args:
        negatives: the perturbed chunks of each recorded state: ``noise`` (Gaussian noise of ``noise_std``
            normalised action units on the executed chunk, VGAS's) or ``policy`` (the policy's own point-dropout
            candidates there, the chunks the reranker will rank).
        num_negatives: ``M``, perturbed chunks per state.
        noise_std: the ``noise`` negatives' standard deviation, in normalised action units ([-1, 1] range).
        dropout: the ``policy`` negatives' point-dropout probability.
        scale, hinge_weight: the hinge's margin per unit of distance (logits) and its weight (0: labels only).
        decisions: at most this many recorded decisions (states at every ``action_steps``-th step), drawn at random.
        hidden, steps, batch_size, lr, weight_decay: the critic MLP and AdamW.
        seed: the decisions drawn, the negatives, initialisation and batch order.
    """

    negatives: str = "noise"
    num_negatives: int = 7
    noise_std: float = 0.1
    dropout: float = RerankingConfig.dropout
    scale: float = 1.0
    hinge_weight: float = 1.0
    decisions: int = 4000
    hidden: int = 128
    steps: int = 1500
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-3
    seed: int = 0

    def __post_init__(self):
        check_choice("negatives", self.negatives, NEGATIVES)
        for name in ("num_negatives", "decisions", "hidden", "steps", "batch_size"):
            check_at_least(name, getattr(self, name), 1)


@torch.no_grad()
def recorded_decisions(
    dataset: TrajectoryDataset, policy, cfg: MixedCriticConfig, critic: ChunkCritic, device="cpu"
) -> TensorDict:
    """The decisions of ``dataset`` that :class:`DistanceHingeLoss` reads: each state's condition, executed
    chunk, perturbed chunks and terminal label (at most ``cfg.decisions`` states, one every ``action_steps``)."""
    windows = TrajectoryWindows(dataset, policy.obs_steps, policy.horizon, policy.action_steps)
    generator = torch.Generator().manual_seed(cfg.seed)
    at_decision = torch.nonzero(windows.steps % policy.action_steps == 0).squeeze(-1)
    chosen = at_decision[torch.randperm(len(at_decision), generator=generator)[: cfg.decisions]]
    executed_part = executed_slice(policy.obs_steps, policy.action_steps)
    dropout = candidate_generator(RerankingConfig(num_candidates=cfg.num_negatives + 1, dropout=cfg.dropout))
    parts = []
    for index in chosen.split(256):
        batch = windows[index].to(device)
        cloud, agent_pos = batch[keys.POINT_CLOUD], batch[keys.AGENT_POS]
        executed = batch[keys.ACTION_CHUNK][:, executed_part]
        if cfg.negatives == "policy":
            cond = dropout.conditions(policy, cloud, agent_pos, cfg.num_negatives + 1, generator)
            perturbed = policy.sample(cond[:, 1:], generator)[:, :, executed_part]
        else:
            normalize = critic.action_normalizer
            noise = torch.randn((len(index), cfg.num_negatives, *executed.shape[1:]), generator=generator)
            perturbed = normalize.unnormalize(normalize(executed).unsqueeze(1) + cfg.noise_std * noise.to(device))
        parts.append(
            TensorDict(
                {
                    CONDITION: policy.encode(cloud, agent_pos),
                    EXECUTED: executed,
                    PERTURBED: perturbed,
                    keys.TERMINAL_LABEL: batch[keys.TERMINAL_LABEL].reshape(-1),
                },
                [len(index)],
            )
        )
    return torch.cat(parts)


def train_mixed_critic(
    dataset: TrajectoryDataset, policy, cfg: MixedCriticConfig, device="cpu"
) -> tuple[ChunkCritic, dict]:
    """A chunk critic trained on ``dataset``'s recorded decisions with :class:`DistanceHingeLoss`: no branched
    outcome, no simulator. Returns it and the losses at the start and the end."""
    torch.manual_seed(cfg.seed)
    windows = TrajectoryWindows(dataset, policy.obs_steps, policy.horizon, policy.action_steps)
    first = windows[[0]].to(device)
    cond_dim = policy.encode(first[keys.POINT_CLOUD], first[keys.AGENT_POS]).shape[-1]
    critic = ChunkCritic(cond_dim, policy.action_dim, policy.action_steps, hidden=cfg.hidden).to(device)
    critic.action_normalizer.fit(dataset.rows[keys.ACTION].to(device))
    table = recorded_decisions(dataset, policy, cfg, critic, device)
    loss_module = DistanceHingeLoss(critic, cfg.scale, cfg.hinge_weight)
    optimizer = torch.optim.AdamW(critic.scorer.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    generator = torch.Generator().manual_seed(cfg.seed)
    with torch.no_grad():
        first = {k: float(v) for k, v in loss_module(table).items()}
    for _ in range(cfg.steps):
        batch = table[torch.randint(len(table), (min(cfg.batch_size, len(table)),), generator=generator).to(device)]
        loss = sum(loss_module(batch).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    critic.eval()
    with torch.no_grad():
        last = {k: float(v) for k, v in loss_module(table).items()}
    metrics = {"config": asdict(cfg), "decisions": len(table), "loss_start": first, "loss_end": last}
    return critic, metrics


@torch.no_grad()
def critic_auc(critic: ChunkCritic, outcomes: BranchedOutcomes, policy) -> dict:
    """The within-decision AUC of a trained ``critic`` on every branched decision that splits (none of which it
    was trained on, for a critic of the mixed data)."""
    rows = _rows(outcomes).to(next(critic.parameters()).device)
    logits = critic(policy.encode(rows[keys.POINT_CLOUD], rows[keys.AGENT_POS]), _executed(rows, policy))
    return {
        "split_decisions": int(split_decisions(rows[SUCCESS]).sum()),
        "auc": within_decision_auc(logits.tolist(), rows[SUCCESS].tolist()),
    }
