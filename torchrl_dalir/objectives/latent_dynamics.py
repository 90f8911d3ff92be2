"""The latent world model's objective as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_dalir import keys
from torchrl_dalir.modules.world_model import LatentWorldModel
from torchrl_dalir.objectives.common import KeyedLossModule

LATENT = keys.LATENT  # s_t, precomputed by the frozen latent encoder
FUTURE_LATENT = (keys.FUTURE, keys.LATENT)  # s_{t+k}


class LatentDynamicsLoss(KeyedLossModule):
    """MSE between the imagined ``s_t + W(s_t, a_{t:t+k})`` and the encoded ``s_{t+k}``.

    The latents come from the latent encoder *frozen* after the scorer stage, so the targets
    cannot move to make the loss trivial (no collapse); they are precomputed once, which also
    makes this stage cheap.

    Args:
        world_model: the model being trained.

    Keys (``set_keys``): ``latent`` ``[B, L]``, ``future_latent`` ``[B, L]`` (by default
    ``("future", "latent")``) and ``action_chunk`` ``[B, k, A]`` (the executed actions
    ``a_t .. a_{t+k-1}``).

    Example:
        >>> wm = LatentWorldModel(16, 4, hidden=32, layers=1, heads=2)
        >>> loss = LatentDynamicsLoss(wm)
        >>> batch = TensorDict({"latent": torch.randn(5, 16), "future": {"latent": torch.randn(5, 16)},
        ...                     "action_chunk": torch.randn(5, 8, 4)}, [5])
        >>> loss(batch)["loss_latent_dynamics"].shape
        torch.Size([])
        >>> loss.set_keys(action_chunk="action")
        >>> loss.in_keys
        ['latent', ('future', 'latent'), 'action']
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a world-model window holds.

        Attributes:
            latent: ``s_t`` ``[B, L]``. Defaults to ``"latent"``.
            future_latent: ``s_{t+k}`` ``[B, L]``. Defaults to ``("future", "latent")``.
            action_chunk: the executed actions ``[B, k, A]``. Defaults to ``"action_chunk"``.
        """

        latent: NestedKey = LATENT
        future_latent: NestedKey = FUTURE_LATENT
        action_chunk: NestedKey = keys.ACTION_CHUNK

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_latent_dynamics"]

    def __init__(self, world_model: LatentWorldModel):
        super().__init__()
        self.world_model = world_model

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        latent, actions = tensordict[self.tensor_keys.latent], tensordict[self.tensor_keys.action_chunk]
        loss = torch.nn.functional.mse_loss(
            self.world_model.imagine(latent, actions), tensordict[self.tensor_keys.future_latent]
        )
        return TensorDict({"loss_latent_dynamics": loss}, [])
