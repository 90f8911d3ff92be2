"""Same-state negatives without a simulator: a chunk critic trained on mixed data with a distance hinge."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import nn

from torchrl_dalir import keys
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.objectives.common import KeyedLossModule

CONDITION = "condition"  # [B, C] the policy's condition of the observation history
EXECUTED = "executed_actions"  # [B, k, A] the chunk the data executed from there
PERTURBED = "perturbed_actions"  # [B, M, k, A] other chunks from the same state, never executed


class DistanceHingeLoss(KeyedLossModule):
    """A :class:`~torchrl_dalir.modules.ChunkCritic` on recorded decisions: the terminal label of the executed
    chunk, and a hinge that puts every perturbed chunk of the same state below it by a margin that grows with its
    distance from it (VGAS's idea; without a simulator, no outcome of the perturbed chunk is known).

    The binary cross-entropy fits ``Q(s, a)`` to the trajectory's terminal label; the hinge asks
    ``Q(s, a') <= Q(s, a) - scale * d(a, a')`` (logits), with ``d`` the root-mean-square distance in the
    critic's normalised action units. The hinge moves the gap between the two values and the cross-entropy
    pins their level. Gradients flow through both sides of the hinge: were ``Q(s, a)`` detached there, the hinge
    would push every value of a state down, the executed chunk's with it, without end. Mixed data
    record one chunk per state; the hinge is the only signal here that compares chunks of the same state,
    which a critic trained on labels alone is never asked to do.

    Args:
        critic: the chunk critic to train.
        scale: the margin per unit of distance, in logits.
        hinge_weight: the hinge's weight beside the cross-entropy (0: labels only).

    Keys (``set_keys``): ``condition`` ``[B, C]``, ``executed`` ``[B, k, A]``, ``perturbed`` ``[B, M, k, A]``
    and ``label`` ``[B]`` (the terminal label, 1 success, 0 time-out).

    Example:
        >>> critic = ChunkCritic(cond_dim=6, action_dim=4, action_steps=8, hidden=16)
        >>> loss = DistanceHingeLoss(critic)
        >>> batch = TensorDict({"condition": torch.randn(5, 6), "executed_actions": torch.rand(5, 8, 4),
        ...                     "perturbed_actions": torch.rand(5, 3, 8, 4), "terminal_label": torch.ones(5)}, [5])
        >>> sorted(loss(batch).keys())
        ['loss_hinge', 'loss_outcome']
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a batch of recorded decisions holds.

        Attributes:
            condition: the policy's condition ``[B, C]``. Defaults to ``"condition"``.
            executed: the executed chunk's actions ``[B, k, A]``. Defaults to ``"executed_actions"``.
            perturbed: other chunks from the same state ``[B, M, k, A]``. Defaults to ``"perturbed_actions"``.
            label: the trajectory's terminal label ``[B]``. Defaults to ``"terminal_label"``.
        """

        condition: NestedKey = CONDITION
        executed: NestedKey = EXECUTED
        perturbed: NestedKey = PERTURBED
        label: NestedKey = keys.TERMINAL_LABEL

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_outcome", "loss_hinge"]

    def __init__(self, critic: ChunkCritic, scale: float = 1.0, hinge_weight: float = 1.0):
        super().__init__()
        if scale < 0 or hinge_weight < 0:
            raise ValueError(f"scale and hinge_weight must be non-negative, got {scale} and {hinge_weight}")
        self.critic, self.scale, self.hinge_weight = critic, scale, hinge_weight

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        cond = tensordict[self.tensor_keys.condition]
        executed, perturbed = tensordict[self.tensor_keys.executed], tensordict[self.tensor_keys.perturbed]
        label = tensordict[self.tensor_keys.label].reshape(-1).to(cond.dtype)
        logits = self.critic(cond, torch.cat([executed.unsqueeze(1), perturbed], dim=1))  # [B, 1 + M]
        outcome = nn.functional.binary_cross_entropy_with_logits(logits[:, 0], label)
        normalize = self.critic.action_normalizer
        distance = (normalize(perturbed) - normalize(executed).unsqueeze(1)).pow(2).mean((-2, -1)).sqrt()  # [B, M]
        target = logits[:, :1] - self.scale * distance
        hinge = nn.functional.relu(logits[:, 1:] - target).mean()
        return TensorDict({"loss_outcome": outcome, "loss_hinge": self.hinge_weight * hinge}, [])
