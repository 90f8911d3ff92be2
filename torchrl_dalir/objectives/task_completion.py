"""The task-completion scorer's objective as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_dalir import keys
from torchrl_dalir.modules.world_model import LatentEncoder, TaskCompletionScorer
from torchrl_dalir.objectives.common import KeyedLossModule


class TaskCompletionLoss(KeyedLossModule):
    """Binary cross-entropy between ``sigmoid(C(s_t))`` and a soft completion target.

    By default the target is ``completion_target`` = ``gamma^(T-t) * y_T`` from sparse terminal
    labels; ``set_keys(target=...)`` (or ``target_key``) names another one (the dense-reward
    oracle of the ablation). The latent encoder is fine-tuned through this loss; with
    ``encoder=None`` the scorer reads precomputed latents from ``latent`` (a frozen encoder:
    many epochs cost little).

    Args:
        encoder: the latent encoder (trainable), or ``None`` to read ``latent``.
        scorer: the scorer.
        target_key: a shorthand for ``set_keys(target=target_key)``; ``None`` keeps the default.

    Keys (``set_keys``): ``point_cloud`` ``[B, N, 3]`` and ``agent_pos`` ``[B, D]`` (one
    observation, read with an encoder), ``latent`` ``[B, L]`` (read without one) and ``target``
    ``[B]``.

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64]), 4, 4)
        >>> encoder = LatentEncoder.from_policy(policy)
        >>> loss = TaskCompletionLoss(encoder, TaskCompletionScorer(encoder.latent_dim))
        >>> rows = TensorDict({"point_cloud": torch.rand(6, 64, 3), "agent_pos": torch.rand(6, 4),
        ...                    "completion_target": torch.rand(6)}, [6])
        >>> loss(rows)["loss_task_completion"].shape
        torch.Size([])
        >>> frozen = TaskCompletionLoss(None, TaskCompletionScorer(encoder.latent_dim),
        ...                             target_key="dense_reward_target")
        >>> frozen.in_keys
        ['latent', 'dense_reward_target']
        >>> table = TensorDict({"latent": encoder(rows["point_cloud"], rows["agent_pos"]).detach(),
        ...                     "dense_reward_target": torch.rand(6)}, [6])
        >>> frozen(table)["loss_task_completion"].shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a row holds.

        Attributes:
            point_cloud: one observation's point cloud ``[B, N, 3]``. Defaults to ``"point_cloud"``.
            agent_pos: its proprioception ``[B, D]``. Defaults to ``"agent_pos"``.
            latent: its precomputed latent ``[B, L]`` (read when there is no encoder). Defaults to ``"latent"``.
            target: the target in [0, 1] ``[B]``. Defaults to ``"completion_target"``.
        """

        point_cloud: NestedKey = keys.POINT_CLOUD
        agent_pos: NestedKey = keys.AGENT_POS
        latent: NestedKey = keys.LATENT
        target: NestedKey = keys.COMPLETION_TARGET

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_task_completion"]

    def __init__(
        self, encoder: LatentEncoder | None, scorer: TaskCompletionScorer, target_key: NestedKey | None = None
    ):
        super().__init__()
        self.encoder, self.scorer = encoder, scorer
        if target_key is not None:
            self.set_keys(target=target_key)

    def _read_key_names(self) -> tuple[str, ...]:
        observation = ("latent",) if self.encoder is None else ("point_cloud", "agent_pos")
        return (*observation, "target")

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        if self.encoder is None:
            latent = tensordict[self.tensor_keys.latent]
        else:
            latent = self.encoder(tensordict[self.tensor_keys.point_cloud], tensordict[self.tensor_keys.agent_pos])
        logits = self.scorer(latent)
        target = tensordict[self.tensor_keys.target].to(logits.dtype)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target)
        return TensorDict({"loss_task_completion": loss}, [])
