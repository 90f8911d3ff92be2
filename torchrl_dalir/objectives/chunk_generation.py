"""The skeleton the base policies' generative objectives share, as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_dalir import keys
from torchrl_dalir.modules.policies import ChunkPolicy3D
from torchrl_dalir.objectives.common import KeyedLossModule


class ChunkGenerationLoss(KeyedLossModule):
    """A policy learns to turn noise into the demo chunk of a training window.

    :meth:`forward` reads a training window (see :class:`torchrl_dalir.data.windows.TrajectoryWindows`),
    encodes its observation history into the policy's condition, normalises the demo chunk,
    draws one standard-normal noise chunk of its shape and passes the three to
    :meth:`chunk_loss`; the scalar it returns is written under the loss's single ``out_keys``
    entry. A subclass sets ``out_keys = ["loss_<name>"]`` and implements :meth:`chunk_loss`,
    which draws whatever else the objective needs (a diffusion step, a path time) after the
    noise: the random draws keep that order.

    Args:
        policy: the :class:`~torchrl_dalir.modules.ChunkPolicy3D` being trained.

    Keys (``set_keys``): ``point_cloud`` ``[B, To, N, 3]`` and ``agent_pos`` ``[B, To, D]``, the
    observation history; ``action_chunk`` ``[B, H, A]``, the demo chunk in the env's units.

    Example:
        >>> from torchrl_dalir.modules import FlowMatchingPolicy3D, PolicyConfig
        >>> class DenoisingLoss(ChunkGenerationLoss):  # one Euler step from pure noise
        ...     out_keys = ["loss_denoising"]
        ...     def chunk_loss(self, cond, chunk, noise):
        ...         zero = torch.zeros(chunk.shape[0])
        ...         return torch.nn.functional.mse_loss(noise + self.policy.velocity(noise, zero, cond), chunk)
        >>> loss = DenoisingLoss(FlowMatchingPolicy3D(PolicyConfig(down_dims=[32, 64, 128]), 4, 4))
        >>> loss.set_keys(action_chunk=("demo", "chunk"))
        >>> window = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                      "demo": {"chunk": torch.rand(8, 16, 4)}}, [8])
        >>> loss(window)["loss_denoising"].shape
        torch.Size([])
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a training window holds.

        Attributes:
            point_cloud: the point-cloud history ``[B, To, N, 3]``. Defaults to ``"point_cloud"``.
            agent_pos: the proprioception history ``[B, To, D]``. Defaults to ``"agent_pos"``.
            action_chunk: the demo chunk ``[B, H, A]``. Defaults to ``"action_chunk"``.
        """

        point_cloud: NestedKey = keys.POINT_CLOUD
        agent_pos: NestedKey = keys.AGENT_POS
        action_chunk: NestedKey = keys.ACTION_CHUNK

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, policy: ChunkPolicy3D):
        super().__init__()
        self.policy = policy

    def chunk_loss(self, cond: torch.Tensor, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The scalar loss of normalised demo chunks ``chunk`` ``[B, H, A]`` under the condition
        ``cond`` ``[B, C]``, given the noise ``noise`` (same shape as ``chunk``) drawn for them."""
        raise NotImplementedError

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        cond = self.policy.encode(tensordict[self.tensor_keys.point_cloud], tensordict[self.tensor_keys.agent_pos])
        chunk = self.policy.action_normalizer(tensordict[self.tensor_keys.action_chunk])
        loss = self.chunk_loss(cond, chunk, torch.randn_like(chunk))
        return TensorDict({self.out_keys_source[0]: loss}, [])
