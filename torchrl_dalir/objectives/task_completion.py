"""The task-completion scorer's objective as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_dalir import keys
from torchrl_dalir.modules.world_model import LatentEncoder, TaskCompletionScorer


class TaskCompletionLoss(LossModule):
    """Binary cross-entropy between ``sigmoid(C(s_t))`` and a soft completion target.

    By default the target is ``completion_target`` = ``gamma^(T-t) * y_T`` from sparse terminal
    labels; ``target_key`` names another one (the dense-reward oracle of the ablation). The
    latent encoder is fine-tuned through this loss; with ``encoder=None`` the scorer reads
    precomputed latents from ``latent`` (a frozen encoder: many epochs cost little).

    Args:
        encoder: the latent encoder (trainable), or ``None`` to read ``latent``.
        scorer: the scorer.
        target_key: the entry holding targets in [0, 1].

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64]), 4, 4)
        >>> encoder = LatentEncoder.from_policy(policy)
        >>> loss = TaskCompletionLoss(encoder, TaskCompletionScorer(encoder.latent_dim))
        >>> rows = TensorDict({"point_cloud": torch.rand(6, 64, 3), "agent_pos": torch.rand(6, 4),
        ...                    "completion_target": torch.rand(6)}, [6])
        >>> loss(rows)["loss_task_completion"].shape
        torch.Size([])
    """

    def __init__(self, encoder: LatentEncoder | None, scorer: TaskCompletionScorer, target_key: str = keys.COMPLETION_TARGET):
        super().__init__()
        self.encoder, self.scorer, self.target_key = encoder, scorer, target_key

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        if self.encoder is None:
            latent = tensordict.get(keys.LATENT)
        else:
            latent = self.encoder(tensordict.get(keys.POINT_CLOUD), tensordict.get(keys.AGENT_POS))
        logits = self.scorer(latent)
        target = tensordict.get(self.target_key).to(logits.dtype)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target)
        return TensorDict({"loss_task_completion": loss}, [])
