"""FlowPolicy's consistency flow matching objective as a TorchRL ``LossModule``.

Straight paths ``x_t = t * a + (1 - t) * z`` are cut into ``segments``; within a segment the
network's prediction of the segment's end point, ``f(x_t, t) = x_t + (end - t) * v(x_t, t)``,
must agree with its own (gradient-free) prediction from a slightly later time ``r = t + delta``,
and at the data end (``r = 1``) with the chunk itself. Self-consistent velocities make a single
Euler step (NFE = 1) land on the data.
"""

from __future__ import annotations

import torch

from torchrl_dalir.modules.policies import FlowMatchingPolicy3D
from torchrl_dalir.objectives.chunk_generation import ChunkGenerationLoss
from torchrl_dalir.objectives.flow_matching import straight_path


class ConsistencyFlowMatchingLoss(ChunkGenerationLoss):
    """End-point consistency plus ``alpha`` times velocity consistency (away from segment ends).

    Reads the same training windows, under the same keys, as
    :class:`~torchrl_dalir.objectives.FlowMatchingLoss`.

    Args:
        policy: the :class:`~torchrl_dalir.modules.FlowMatchingPolicy3D` being trained.
        delta: the time gap between the two predictions (FlowPolicy: 0.01).
        segments: number of path segments (FlowPolicy: 2).
        alpha: weight of the velocity-consistency term.
        eps: the smallest sampled time.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import FlowMatchingPolicy3D, PolicyConfig
        >>> policy = FlowMatchingPolicy3D(PolicyConfig(down_dims=[32, 64, 128]), 4, 4)
        >>> loss = ConsistencyFlowMatchingLoss(policy, segments=2)
        >>> loss.in_keys
        ['point_cloud', 'agent_pos', 'action_chunk']
        >>> batch = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                     "action_chunk": torch.rand(8, 16, 4)}, [8])
        >>> loss(batch)["loss_consistency"].shape
        torch.Size([])
    """

    out_keys = ["loss_consistency"]
    policy: FlowMatchingPolicy3D

    def __init__(
        self,
        policy: FlowMatchingPolicy3D,
        delta: float = 0.01,
        segments: int = 2,
        alpha: float = 1e-5,
        eps: float = 1e-3,
    ):
        super().__init__(policy)
        self.delta, self.segments, self.alpha, self.eps = delta, segments, alpha, eps

    def chunk_loss(self, cond: torch.Tensor, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        n = chunk.shape[0]
        t = self.eps + (1 - self.eps) * torch.rand(n, device=chunk.device)
        r = (t + self.delta).clamp(max=1.0)
        boundaries = torch.linspace(0, 1, self.segments + 1, device=chunk.device)
        end = boundaries[torch.searchsorted(boundaries, t).clamp(min=1)]

        def end_point(x, s, v):
            return x + (end - s)[:, None, None] * v

        x_t, x_r = straight_path(t, chunk, noise), straight_path(r, chunk, noise)
        v_t = self.policy.velocity(x_t, t, cond)
        with torch.no_grad():
            v_r = self.policy.velocity(x_r, r, cond)
            target = torch.where((r < 1)[:, None, None], end_point(x_r, r, v_r), straight_path(end, chunk, noise))
        loss_end = ((end_point(x_t, t, v_t) - target) ** 2).mean()
        far_from_end = ((end - t) > 1.01 * self.delta).float()[:, None, None]
        loss_velocity = (far_from_end * (v_t - v_r) ** 2).mean()
        return loss_end + self.alpha * loss_velocity
