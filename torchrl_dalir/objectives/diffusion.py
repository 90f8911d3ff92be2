"""DP3's denoising objective as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch

from torchrl_dalir.modules.policies import DiffusionPolicy3D
from torchrl_dalir.objectives.chunk_generation import ChunkGenerationLoss


class DiffusionLoss(ChunkGenerationLoss):
    """Noises the demo chunk to a random DDPM step and regresses the clean chunk (MSE).

    Reads a training window (see :class:`torchrl_dalir.data.windows.TrajectoryWindows`); its keys
    are :class:`~torchrl_dalir.objectives.ChunkGenerationLoss`'s: ``point_cloud``
    ``[B, To, N, 3]``, ``agent_pos`` ``[B, To, D]`` and ``action_chunk`` ``[B, H, A]``, each
    renamed with ``set_keys``.

    Args:
        policy: the :class:`~torchrl_dalir.modules.DiffusionPolicy3D` being trained.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import DiffusionPolicy3D, PolicyConfig
        >>> policy = DiffusionPolicy3D(PolicyConfig(kind="dp", down_dims=[32, 64, 128]), 4, 4)
        >>> loss = DiffusionLoss(policy)
        >>> batch = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                     "action_chunk": torch.rand(8, 16, 4)}, [8])
        >>> loss(batch)["loss_diffusion"].shape
        torch.Size([])
    """

    out_keys = ["loss_diffusion"]
    policy: DiffusionPolicy3D

    def chunk_loss(self, cond: torch.Tensor, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        policy = self.policy
        steps = torch.randint(0, policy.config.train_timesteps, (chunk.shape[0],), device=chunk.device)
        noisy = policy.scheduler.add_noise(chunk, noise, steps)
        return torch.nn.functional.mse_loss(policy.unet(noisy, steps, cond), chunk)
