"""DP3's denoising objective as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_dalir.modules.policies import DiffusionPolicy3D


class DiffusionLoss(LossModule):
    """Noises the demo chunk to a random DDPM step and regresses the clean chunk (MSE).

    Reads a training window (see :class:`torchrl_dalir.data.windows.TrajectoryWindows`):
    ``point_cloud`` ``[B, To, N, 3]``, ``agent_pos`` ``[B, To, D]``, ``action_chunk`` ``[B, H, A]``.

    Args:
        policy: the :class:`DiffusionPolicy3D` being trained.

    Example:
        >>> from torchrl_dalir.modules import DiffusionPolicy3D, PolicyConfig
        >>> policy = DiffusionPolicy3D(PolicyConfig(kind="dp", down_dims=[32, 64, 128]), 4, 4)
        >>> batch = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                     "action_chunk": torch.rand(8, 16, 4)}, [8])
        >>> DiffusionLoss(policy)(batch)["loss_diffusion"].shape
        torch.Size([])
    """

    def __init__(self, policy: DiffusionPolicy3D):
        super().__init__()
        self.policy = policy

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        policy = self.policy
        cond, target = policy.training_pair(tensordict)
        noise = torch.randn_like(target)
        steps = torch.randint(0, policy.config.train_timesteps, (target.shape[0],), device=target.device)
        noisy = policy.scheduler.add_noise(target, noise, steps)
        loss = torch.nn.functional.mse_loss(policy.unet(noisy, steps, cond), target)
        return TensorDict({"loss_diffusion": loss}, [])
