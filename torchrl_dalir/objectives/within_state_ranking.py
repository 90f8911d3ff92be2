"""The candidate scorer's objective on branched outcomes, as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from torchrl_dalir.objectives.common import KeyedLossModule

CANDIDATE_FEATURES = "candidate_features"  # [B, K, F] what the scorer reads of each candidate of a decision
SUCCESS = "success"  # [B, K] bool, whether each candidate's branch went on to succeed


def split_decisions(success: torch.Tensor) -> torch.Tensor:
    """Which decisions ``[..., K]`` of candidates' outcomes split: some, not all, succeeded."""
    wins = success.sum(-1)
    return (wins > 0) & (wins < success.shape[-1])


class WithinStateRankingLoss(KeyedLossModule):
    """Ranks candidates of the same decision: a listwise softmax cross-entropy beside a terminal-label loss.

    At a decision whose candidates split (some branches succeed, some fail), the target puts equal
    mass on the winners and the loss is the cross-entropy of ``softmax(logits)`` over the decision's
    ``K`` candidates against it (ListNet's top-one form): it moves scores only *relative to the
    other candidates of the same state*, which a loss on labels across states never asks for.
    Decisions that do not split carry no ranking signal; every candidate, split or not, also enters
    the binary cross-entropy against its own outcome (``outcome_weight``), which keeps the logits
    calibrated as success probabilities.

    Args:
        scorer: maps candidate features ``[B, K, F]`` to logits ``[B, K]`` (e.g. a
            :class:`~torchrl_dalir.modules.world_model.TaskCompletionScorer` of input size ``F``), or a TensorDict
            module that reads what it needs of the batch and writes the logits at its ``out_keys[0]`` (e.g. a
            :class:`~torchrl_dalir.modules.PointCloudCriticModule`, which reads the observations); the
            ``features`` key is then not read.
        outcome_weight: the weight of the binary cross-entropy (0: ranking only).

    Keys (``set_keys``): ``features`` ``[B, K, F]`` and ``success`` ``[B, K]``.

    Example:
        >>> import torch
        >>> from torchrl_dalir.modules import TaskCompletionScorer
        >>> loss = WithinStateRankingLoss(TaskCompletionScorer(6, hidden=16))
        >>> decisions = TensorDict({"candidate_features": torch.randn(4, 8, 6),
        ...                         "success": torch.rand(4, 8) > 0.5}, [4])
        >>> sorted(loss(decisions).keys())
        ['loss_outcome', 'loss_ranking']
        >>> loss.set_keys(features="imagined_latent")
        >>> loss.in_keys
        ['imagined_latent', 'success']
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a batch of decisions holds.

        Attributes:
            features: what the scorer reads of each candidate ``[B, K, F]``. Defaults to ``"candidate_features"``.
            success: each candidate's branched outcome ``[B, K]``. Defaults to ``"success"``.
        """

        features: NestedKey = CANDIDATE_FEATURES
        success: NestedKey = SUCCESS

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_ranking", "loss_outcome"]

    def __init__(self, scorer: nn.Module, outcome_weight: float = 0.5):
        super().__init__()
        if outcome_weight < 0:
            raise ValueError(f"outcome_weight must be non-negative, got {outcome_weight}")
        self.scorer, self.outcome_weight = scorer, outcome_weight

    def _read_key_names(self) -> tuple[str, ...]:
        return ("success",) if isinstance(self.scorer, TensorDictModuleBase) else ("features", "success")

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        if isinstance(self.scorer, TensorDictModuleBase):
            logits = self.scorer(tensordict.copy())[self.scorer.out_keys[0]]
        else:
            logits = self.scorer(tensordict[self.tensor_keys.features])
        success = tensordict[self.tensor_keys.success].to(logits.dtype)
        split = split_decisions(success)
        target = success / success.sum(-1, keepdim=True).clamp(min=1)
        listwise = -(target * logits.log_softmax(-1)).sum(-1)
        ranking = (listwise * split).sum() / split.sum().clamp(min=1)  # 0 without a split decision in the batch
        outcome = nn.functional.binary_cross_entropy_with_logits(logits, success)
        return TensorDict({"loss_ranking": ranking, "loss_outcome": self.outcome_weight * outcome}, [])
