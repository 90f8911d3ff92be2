"""FlowPolicy's consistency flow matching objective as a TorchRL ``LossModule``.

Straight paths ``x_t = t * a + (1 - t) * z`` are cut into ``segments``; within a segment the
network's prediction of the segment's end point, ``f(x_t, t) = x_t + (end - t) * v(x_t, t)``,
must agree with its own (gradient-free) prediction from a slightly later time ``r = t + delta``,
and at the data end (``r = 1``) with the chunk itself. Self-consistent velocities make a single
Euler step (NFE = 1) land on the data.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from torchrl_dalir.modules.policies import FlowMatchingPolicy3D


class ConsistencyFlowMatchingLoss(LossModule):
    """End-point consistency plus ``alpha`` times velocity consistency (away from segment ends).

    Args:
        policy: the :class:`FlowMatchingPolicy3D` being trained.
        delta: the time gap between the two predictions (FlowPolicy: 0.01).
        segments: number of path segments (FlowPolicy: 2).
        alpha: weight of the velocity-consistency term.
        eps: the smallest sampled time.

    Example:
        >>> from torchrl_dalir.modules import FlowMatchingPolicy3D, PolicyConfig
        >>> policy = FlowMatchingPolicy3D(PolicyConfig(down_dims=[32, 64, 128]), 4, 4)
        >>> batch = TensorDict({"point_cloud": torch.rand(8, 2, 64, 3), "agent_pos": torch.rand(8, 2, 4),
        ...                     "action_chunk": torch.rand(8, 16, 4)}, [8])
        >>> ConsistencyFlowMatchingLoss(policy)(batch)["loss_consistency"].shape
        torch.Size([])
    """

    def __init__(self, policy: FlowMatchingPolicy3D, delta: float = 0.01, segments: int = 2, alpha: float = 1e-5, eps: float = 1e-3):
        super().__init__()
        self.policy, self.delta, self.segments, self.alpha, self.eps = policy, delta, segments, alpha, eps

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        policy = self.policy
        cond, data = policy.training_pair(tensordict)
        noise = torch.randn_like(data)
        n = data.shape[0]
        t = self.eps + (1 - self.eps) * torch.rand(n, device=data.device)
        r = (t + self.delta).clamp(max=1.0)
        boundaries = torch.linspace(0, 1, self.segments + 1, device=data.device)
        end = boundaries[torch.searchsorted(boundaries, t).clamp(min=1)]

        def path(s):
            s = s[:, None, None]
            return s * data + (1 - s) * noise

        def end_point(x, s, v):
            return x + (end - s)[:, None, None] * v

        x_t, x_r = path(t), path(r)
        v_t = policy.velocity(x_t, t, cond)
        with torch.no_grad():
            v_r = policy.velocity(x_r, r, cond)
            target = torch.where((r < 1)[:, None, None], end_point(x_r, r, v_r), path(end))
        loss_end = ((end_point(x_t, t, v_t) - target) ** 2).mean()
        far_from_end = ((end - t) > 1.01 * self.delta).float()[:, None, None]
        loss_velocity = (far_from_end * (v_t - v_r) ** 2).mean()
        return TensorDict({"loss_consistency": loss_end + self.alpha * loss_velocity}, [])
