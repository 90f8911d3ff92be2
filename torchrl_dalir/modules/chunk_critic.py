"""``ChunkCritic``: the chance that a candidate chunk, executed now, leads to success (a Q-function).

It reads the policy's own condition of the observation history (``policy.encode``) and the
chunk's executed actions, min-max normalised, so it never passes through the world model, whose
error on a decision's candidates can exceed their spread. Trained on branched outcomes
(:mod:`~torchrl_dalir.training.ranking`), it scores candidates for
:class:`~torchrl_dalir.reranking.RerankingActor` with ``SelectionConfig(scorer="critic")``.
"""

from __future__ import annotations

import torch
from torch import nn

from torchrl_dalir.modules.normalizer import MinMaxNormalizer
from torchrl_dalir.modules.world_model import TaskCompletionScorer


class ChunkCritic(nn.Module):
    """Logits ``[B, K]`` of eventual success for chunks' executed actions ``[B, K, k, A]`` from conditions ``[B, C]``.

    Args:
        cond_dim: ``C``, the size of the policy's condition.
        action_dim, action_steps: ``A`` and ``k``, the executed actions' shape.
        hidden: the MLP's width.

    Example:
        >>> critic = ChunkCritic(cond_dim=6, action_dim=4, action_steps=8, hidden=16)
        >>> critic(torch.randn(2, 6), torch.rand(2, 5, 8, 4)).shape  # 2 decisions, 5 candidates each
        torch.Size([2, 5])
    """

    def __init__(self, cond_dim: int, action_dim: int, action_steps: int, hidden: int = 128):
        super().__init__()
        self.cond_dim, self.action_dim, self.action_steps, self.hidden = cond_dim, action_dim, action_steps, hidden
        self.action_normalizer = MinMaxNormalizer(action_dim)
        self.scorer = TaskCompletionScorer(cond_dim + action_steps * action_dim, hidden)

    def architecture(self) -> dict:
        return {
            "cond_dim": self.cond_dim,
            "action_dim": self.action_dim,
            "action_steps": self.action_steps,
            "hidden": self.hidden,
        }

    def condition(self, policy, cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """The condition ``[B, C]`` it reads of observation histories: ``policy``'s own encoding (a critic with
        encoders of its own, :class:`~torchrl_dalir.modules.PointCloudCritic`, overrides this)."""
        return policy.encode(cloud, agent_pos)

    def features(self, cond: torch.Tensor, executed: torch.Tensor) -> torch.Tensor:
        """What the MLP reads of each candidate: ``[B, K, C + k * A]``."""
        if cond.shape[-1] != self.cond_dim or executed.shape[-2:] != (self.action_steps, self.action_dim):
            raise ValueError(
                f"expected conditions [B, {self.cond_dim}] and executed actions [B, K, {self.action_steps}, "
                f"{self.action_dim}], got {tuple(cond.shape)} and {tuple(executed.shape)}"
            )
        state = cond.unsqueeze(-2).expand(*executed.shape[:-2], -1)
        return torch.cat([state, self.action_normalizer(executed).flatten(-2)], dim=-1)

    def forward(self, cond: torch.Tensor, executed: torch.Tensor) -> torch.Tensor:
        return self.scorer(self.features(cond, executed))
