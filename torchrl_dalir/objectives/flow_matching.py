"""Linear-path (optimal-transport) conditional flow matching as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_dalir.modules.policies import FlowMatchingPolicy3D


class FlowMatchingLoss(LossModule):
    """Regresses the velocity ``a - z`` at ``x_t = t * a + (1 - t) * z``, ``t ~ U[0, 1]`` (MSE).

    Reads the same training windows as :class:`~torchrl_dalir.objectives.DiffusionLoss`.

    Args:
        policy: the :class:`FlowMatchingPolicy3D` being trained.

    Example:
        >>> from torchrl_dalir.modules import FlowMatchingPolicy3D, PolicyConfig
        >>> policy = FlowMatchingPolicy3D(PolicyConfig(down_dims=[32, 64, 128]), 4, 4)
        >>> batch = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                     "action_chunk": torch.rand(8, 16, 4)}, [8])
        >>> FlowMatchingLoss(policy)(batch)["loss_flow_matching"].shape
        torch.Size([])
    """

    def __init__(self, policy: FlowMatchingPolicy3D):
        super().__init__()
        self.policy = policy

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        policy = self.policy
        cond, target = policy.training_pair(tensordict)
        noise = torch.randn_like(target)
        t = torch.rand(target.shape[0], device=target.device)
        x_t = t[:, None, None] * target + (1 - t[:, None, None]) * noise
        loss = torch.nn.functional.mse_loss(policy.velocity(x_t, t, cond), target - noise)
        return TensorDict({"loss_flow_matching": loss}, [])
