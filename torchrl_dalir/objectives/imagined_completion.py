"""The scorer ensemble's objective on imagined latents, as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_dalir import keys
from torchrl_dalir.modules.world_model import ScorerEnsemble
from torchrl_dalir.objectives.common import KeyedLossModule

IMAGINED_LATENT = keys.IMAGINED_LATENT  # s_hat_{t+k} = s_t + W(s_t, a_{t:t+k}) of a recorded chunk


class ImaginedCompletionLoss(KeyedLossModule):
    """Binary cross-entropy of every ensemble member on its own batch of imagined latents.

    Each member sees a different random batch of the training windows (and starts from its own
    initialisation), as in deep ensembles; there is no bootstrap resampling. The targets are the
    completion targets of the observation the chunk leads to, ``y_{t+k}``: the scorer learns the
    value of a state and a chunk from the inputs it will see at inference.

    Args:
        ensemble: the scorer ensemble being trained.

    Keys (``set_keys``): ``imagined_latent`` ``[E, B, L]`` and ``target`` ``[E, B]`` (by default
    the future observation's ``completion_target``).

    Example:
        >>> ensemble = ScorerEnsemble(16, hidden=32, members=3)
        >>> loss = ImaginedCompletionLoss(ensemble)
        >>> batch = TensorDict({"imagined_latent": torch.randn(3, 8, 16),
        ...                     "future": {"completion_target": torch.rand(3, 8)}}, [3, 8])
        >>> loss(batch)["loss_imagined_completion"].shape
        torch.Size([])
        >>> loss.set_keys(target=("future", "dense_reward_target"))
        >>> loss.in_keys
        ['imagined_latent', ('future', 'dense_reward_target')]
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a batch of imagined windows holds.

        Attributes:
            imagined_latent: the imagined ``s_hat_{t+k}`` ``[E, B, L]``. Defaults to ``"imagined_latent"``.
            target: the target at ``t + k`` ``[E, B]``. Defaults to ``("future", "completion_target")``.
        """

        imagined_latent: NestedKey = keys.IMAGINED_LATENT
        target: NestedKey = (keys.FUTURE, keys.COMPLETION_TARGET)

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_imagined_completion"]

    def __init__(self, ensemble: ScorerEnsemble):
        super().__init__()
        self.ensemble = ensemble

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        logits = self.ensemble(tensordict[self.tensor_keys.imagined_latent], per_member=True)
        target = tensordict[self.tensor_keys.target].to(logits.dtype)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target)
        return TensorDict({"loss_imagined_completion": loss}, [])
