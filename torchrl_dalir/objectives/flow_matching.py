"""Linear-path (optimal-transport) conditional flow matching as a TorchRL ``LossModule``."""

from __future__ import annotations

import torch

from torchrl_dalir.modules.policies import FlowMatchingPolicy3D
from torchrl_dalir.objectives.chunk_generation import ChunkGenerationLoss


def straight_path(t: torch.Tensor, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """``x_t = t * a + (1 - t) * z`` for path times ``t`` ``[B]``: noise at ``t = 0``, the chunk at ``t = 1``."""
    t = t[:, None, None]
    return t * chunk + (1 - t) * noise


class FlowMatchingLoss(ChunkGenerationLoss):
    """Regresses the velocity ``a - z`` at ``x_t = t * a + (1 - t) * z``, ``t ~ U[0, 1]`` (MSE), or
    the chunk ``a`` itself when the policy predicts samples (``flow_prediction="sample"``).

    Reads the same training windows, under the same keys, as
    :class:`~torchrl_dalir.objectives.DiffusionLoss`.

    Args:
        policy: the :class:`~torchrl_dalir.modules.FlowMatchingPolicy3D` being trained.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import FlowMatchingPolicy3D, PolicyConfig
        >>> loss = FlowMatchingLoss(FlowMatchingPolicy3D(PolicyConfig(down_dims=[32, 64, 128]), 4, 4))
        >>> loss.set_keys(action_chunk="expert_chunk")
        >>> window = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                      "expert_chunk": torch.rand(8, 16, 4)}, [8])
        >>> loss(window)["loss_flow_matching"].shape
        torch.Size([])
    """

    out_keys = ["loss_flow_matching"]
    policy: FlowMatchingPolicy3D

    def chunk_loss(self, cond: torch.Tensor, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        t = torch.rand(chunk.shape[0], device=chunk.device)
        out = self.policy.network(straight_path(t, chunk, noise), t, cond)
        return torch.nn.functional.mse_loss(out, self.policy.network_target(chunk, noise))
