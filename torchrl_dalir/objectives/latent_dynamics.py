"""The latent world model's objective as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_dalir import keys
from torchrl_dalir.modules.world_model import LatentWorldModel

LATENT = keys.LATENT  # s_t, precomputed by the frozen latent encoder
FUTURE_LATENT = (keys.FUTURE, keys.LATENT)  # s_{t+k}


class LatentDynamicsLoss(LossModule):
    """MSE between the imagined ``s_t + W(s_t, a_{t:t+k})`` and the encoded ``s_{t+k}``.

    The latents come from the latent encoder *frozen* after the scorer stage, so the targets
    cannot move to make the loss trivial (no collapse); they are precomputed once, which also
    makes this stage cheap. Reads ``latent`` ``[B, L]``, ``("future", "latent")`` ``[B, L]`` and
    ``action_chunk`` ``[B, k, A]`` (the executed actions ``a_t .. a_{t+k-1}``).

    Args:
        world_model: the model being trained.

    Example:
        >>> wm = LatentWorldModel(16, 4, hidden=32, layers=1, heads=2)
        >>> batch = TensorDict({"latent": torch.randn(5, 16), "future": {"latent": torch.randn(5, 16)},
        ...                     "action_chunk": torch.randn(5, 8, 4)}, [5])
        >>> LatentDynamicsLoss(wm)(batch)["loss_latent_dynamics"].shape
        torch.Size([])
    """

    def __init__(self, world_model: LatentWorldModel):
        super().__init__()
        self.world_model = world_model

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        predicted = self.world_model.imagine(tensordict.get(LATENT), tensordict.get(keys.ACTION_CHUNK))
        loss = torch.nn.functional.mse_loss(predicted, tensordict.get(FUTURE_LATENT))
        return TensorDict({"loss_latent_dynamics": loss}, [])
