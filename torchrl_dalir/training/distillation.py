"""A point-cloud critic distilled from a privileged teacher, then fine-tuned on branched outcomes.

The whole algorithm in :func:`train_student`, on one split of branched decisions into training and held-out
episodes:

1. **Teacher.** A chunk critic of the simulator's low-dimensional state at the decision and the chunk
   (``privileged_chunk``, :func:`~torchrl_dalir.training.ranking.train_ranking_scorer`), trained on the training
   decisions' branched outcomes. It ranks candidates far better than any critic of the frozen policy's condition
   (``docs/results/scorer_benchmark.json``), but it reads what no deployed policy sees.
2. **Labels.** The teacher scores the candidates of many more decision states than branching can afford
   (``distill``: states of fresh data seeds with the policy's candidates, and no continuation), and of the
   training decisions.
3. **Distillation.** A :class:`~torchrl_dalir.modules.PointCloudCritic`, its encoders initialised from the
   policy's, learns the teacher's within-decision ranking from the point cloud, the robot state and the chunk
   (:class:`~torchrl_dalir.objectives.CriticDistillationLoss`).
4. **Fine-tuning.** The student then learns the training decisions' own outcomes
   (:class:`~torchrl_dalir.objectives.WithinStateRankingLoss`), at a lower learning rate.

Nothing of the held-out decisions enters any step, and the student reads no simulator state: it is measured, and
deployed, on observations alone.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_dalir import keys
from torchrl_dalir.branching.candidate_outcomes import within_decision_auc
from torchrl_dalir.branching.outcomes import SUCCESS
from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.modules.point_cloud_critic import (
    CANDIDATE_LOGITS,
    EXECUTED_ACTIONS,
    POOLED_POINTS,
    PointCloudCritic,
    PointCloudCriticModule,
)
from torchrl_dalir.objectives.critic_distillation import TEACHER_LOGITS, CriticDistillationLoss
from torchrl_dalir.objectives.within_state_ranking import WithinStateRankingLoss, split_decisions
from torchrl_dalir.training.ranking import (
    SOFT_SUCCESS,
    TARGET,
    TARGETS,
    RankingTrainingConfig,
    _executed,
    standardised,
    train_ranking_scorer,
)


def _privileged_teacher() -> RankingTrainingConfig:
    return RankingTrainingConfig(input="privileged_chunk", targets="soft")


@dataclass
class DistillationConfig:
    """Args:
    teacher: the privileged teacher's training (its ``input`` must be ``privileged_chunk``).
    hidden: the student's scoring MLP width.
    distill_steps, finetune_steps: AdamW steps on the teacher's labels, then on the branched outcomes (0: skip).
    batch_size: decisions per step.
    lr, finetune_lr, weight_decay: AdamW's, for each phase.
    temperature, probability_weight: :class:`~torchrl_dalir.objectives.CriticDistillationLoss`'s.
    finetune_targets: ``outcome`` (0/1) or ``soft`` (the mean over draws) in fine-tuning.
    outcome_weight: :class:`~torchrl_dalir.objectives.WithinStateRankingLoss`'s, in fine-tuning.
    train_point_mlp: also train the per-point MLP (about 0.25 s a step of 32 decisions of 2 x 512 points on one
        CPU thread); by default it stays the policy's, its pooled features are computed once, and the
        projection, the robot-state encoder and the scoring MLP are trained (milliseconds a step).
    seed: initialisation and batch order.
    """

    teacher: RankingTrainingConfig = field(default_factory=_privileged_teacher)
    hidden: int = 128
    distill_steps: int = 3000
    finetune_steps: int = 200
    batch_size: int = 32
    lr: float = 1e-3
    finetune_lr: float = 1e-4
    weight_decay: float = 1e-3
    temperature: float = 1.0
    probability_weight: float = 0.5
    finetune_targets: str = "soft"
    outcome_weight: float = 0.5
    train_point_mlp: bool = False
    seed: int = 0

    def __post_init__(self):
        if self.teacher.input != "privileged_chunk":
            raise ValueError(
                f"the teacher must read the privileged state (input=privileged_chunk), not {self.teacher.input}"
            )
        check_choice("finetune_targets", self.finetune_targets, TARGETS)
        for name in ("distill_steps", "finetune_steps"):
            check_at_least(name, getattr(self, name), 0)
        check_at_least("batch_size", self.batch_size, 1)


def _fit(loss_module, table: TensorDict, parameters, steps: int, cfg: DistillationConfig, lr: float, generator):
    """``steps`` AdamW steps of ``loss_module`` (the sum of its losses) on random batches of ``table``; returns the
    mean loss over the whole table before and after."""

    def mean_loss() -> float:
        with torch.no_grad():
            return float(sum(loss_module(table).values()))

    before = mean_loss()
    optimizer = torch.optim.AdamW(parameters, lr=lr, weight_decay=cfg.weight_decay)
    for _ in range(steps):
        batch = table[torch.randint(len(table), (min(cfg.batch_size, len(table)),), generator=generator)]
        loss = sum(loss_module(batch).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return before, mean_loss()


def _student_module(student: PointCloudCritic, cfg: DistillationConfig) -> TensorDictModule:
    """The student as a TensorDict module: from the clouds, or from their pooled point features when the point
    MLP stays frozen."""
    if cfg.train_point_mlp:
        return PointCloudCriticModule(student)
    student.point_encoder.point_mlp.requires_grad_(False)
    return TensorDictModule(
        student, [POOLED_POINTS, keys.AGENT_POS, EXECUTED_ACTIONS], [CANDIDATE_LOGITS], method="scores_pooled"
    )


def _observations(rows: TensorDict, policy, student: PointCloudCritic, cfg: DistillationConfig) -> TensorDict:
    """What the student reads of decisions: the observation history (or its pooled point features) and each
    candidate's executed actions."""
    cloud = rows[keys.POINT_CLOUD].float()
    if cfg.train_point_mlp:
        points = {keys.POINT_CLOUD: cloud}
    else:
        with torch.no_grad():
            points = {POOLED_POINTS: torch.cat([student.pooled_points(part) for part in cloud.split(64)])}
    return TensorDict(
        {**points, keys.AGENT_POS: rows[keys.AGENT_POS], EXECUTED_ACTIONS: _executed(rows, policy)}, [len(rows)]
    )


def train_student(
    rows: TensorDict,
    policy,
    cfg: DistillationConfig,
    held_out: torch.Tensor | None,
    distill: TensorDict,
    encoders: dict,
) -> tuple[PointCloudCritic, dict]:
    """The student of a teacher trained on ``rows`` outside ``held_out`` (branched decisions with
    ``privileged_state``, and ``soft_success`` for soft targets), distilled on the teacher's labels of ``distill``
    (decision states: ``point_cloud``, ``agent_pos``, ``privileged_state``, ``action_chunk`` of as many candidates
    as ``rows``) and of the training rows, then fine-tuned on the training rows' outcomes. Its encoders start as
    ``encoders`` (:func:`~torchrl_dalir.modules.point_cloud_critic.policy_encoders`); ``policy`` gives the chunk
    sizes. Returns it and its metrics (the teacher's, the phases' losses, the held-out AUC and logits), as
    :func:`~torchrl_dalir.training.ranking.train_ranking_scorer` does, so that
    :func:`~torchrl_dalir.training.ranking.cross_validated_auc` can measure it out of fold (``train=train_student``).
    ``held_out=None`` trains on every row (the student to deploy) and measures nothing held out."""
    if distill[keys.ACTION_CHUNK].shape[1:] != rows[keys.ACTION_CHUNK].shape[1:]:
        raise ValueError(
            f"the distillation states' candidates {tuple(distill[keys.ACTION_CHUNK].shape[1:])} differ from the "
            f"branched decisions' {tuple(rows[keys.ACTION_CHUNK].shape[1:])}"
        )
    held_out = held_out if held_out is not None else torch.zeros(len(rows), dtype=torch.bool)
    train = ~held_out
    teacher, teacher_metrics = train_ranking_scorer(rows, policy, cfg.teacher, held_out=held_out)
    torch.manual_seed(cfg.seed)
    generator = torch.Generator().manual_seed(cfg.seed)
    student = PointCloudCritic.from_encoders(encoders, policy.action_dim, policy.action_steps, cfg.hidden)
    module = _student_module(student, cfg)
    labelled = torch.cat(
        [_observations(rows[train], policy, student, cfg), _observations(distill, policy, student, cfg)]
    )
    reference = rows[keys.PRIVILEGED_STATE][train]  # the teacher's standardisation: its training rows'
    states = torch.cat([rows[keys.PRIVILEGED_STATE][train], distill[keys.PRIVILEGED_STATE]])
    with torch.no_grad():
        labelled[TEACHER_LOGITS] = teacher(standardised(states, reference), labelled[EXECUTED_ACTIONS])

    student.action_normalizer.fit(labelled[EXECUTED_ACTIONS])
    distillation = CriticDistillationLoss(module, cfg.temperature, cfg.probability_weight)
    trained = [p for p in student.parameters() if p.requires_grad]
    distill_losses = _fit(distillation, labelled, trained, cfg.distill_steps, cfg, cfg.lr, generator)

    outcomes = _observations(rows[train], policy, student, cfg)
    outcomes[SUCCESS] = rows[SUCCESS][train]
    outcomes[TARGET] = (rows[SOFT_SUCCESS] if cfg.finetune_targets == "soft" else rows[SUCCESS])[train]
    ranking = WithinStateRankingLoss(module, cfg.outcome_weight)
    ranking.set_keys(success=TARGET)
    finetune_losses = _fit(ranking, outcomes, trained, cfg.finetune_steps, cfg, cfg.finetune_lr, generator)

    student.eval()
    metrics = {
        "config": asdict(cfg),
        "teacher": {"train_auc": teacher_metrics["train_auc"]},
        "distill_states": len(distill),
        "loss_distillation": distill_losses,
        "loss_finetune": finetune_losses,
    }
    if not held_out.any():
        return student, metrics
    with torch.no_grad():
        logits = module(_observations(rows[held_out], policy, student, cfg))[module.out_keys[0]]
    success = rows[SUCCESS][held_out]
    metrics["teacher"]["held_out_auc"] = teacher_metrics["held_out_auc"]
    metrics.update(
        held_out_decisions=int(held_out.sum()),
        held_out_split_decisions=int(split_decisions(success).sum()),
        held_out_auc=within_decision_auc(logits.tolist(), success.tolist()),
        held_out_logits=logits.tolist(),
    )
    return student, metrics
