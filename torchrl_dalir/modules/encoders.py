"""DP3's observation encoders: a per-point MLP with max-pooling, and a robot-state MLP.

The point encoder keeps per-point features and pooling apart: point dropout is a mask on the
pooling, so many dropout masks can share one pass of the per-point MLP (the reranker's trick).
"""

from __future__ import annotations

import torch
from torch import nn


def _mlp(sizes: list[int], layer_norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        layers.append(nn.Linear(n_in, n_out))
        if layer_norm:
            layers.append(nn.LayerNorm(n_out))
        layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def masked_max(features: torch.Tensor, keep: torch.Tensor, top: int = 8) -> torch.Tensor:
    """``max`` over the points where ``keep`` is set: ``features`` ``[..., N, C]`` and ``keep``
    ``[..., N]`` broadcast over the leading dimensions; returns ``[..., C]``.

    Bit-identical to ``features.masked_fill(~keep[..., None], -inf).max(-2)`` without
    materialising the broadcast features: per channel, the largest value over the kept points is
    the first kept one among the channel's ``top`` largest values (found once for all masks);
    only channels with none of those kept (rare under light dropout) take the full masked max.
    """
    points, channels = features.shape[-2:]
    batch = torch.broadcast_shapes(features.shape[:-2], keep.shape[:-1])
    top = min(top, points)
    values, index = features.topk(top, dim=-2)  # [..., top, C], largest first
    # [..., C, top]: whether the point of each of a channel's top values is kept, the top values
    # contiguous (a reduction over a strided dimension of 8 was the slowest step here)
    kept = (
        keep.unsqueeze(-2)
        .expand(*batch, channels, points)
        .gather(-1, index.transpose(-1, -2).expand(*batch, channels, top))
    )
    first = kept.to(torch.uint8).argmax(-1, keepdim=True)  # the first kept one (argmax returns the first maximum)
    out = values.transpose(-1, -2).expand(*batch, channels, top).gather(-1, first).squeeze(-1)
    missing = ~kept.any(-1)  # [..., C]: none of the top values is kept
    if missing.any():
        rows = missing.any(-1)
        masked = features.expand(*batch, points, channels)[rows].masked_fill(
            ~keep.expand(*batch, points)[rows].unsqueeze(-1), float("-inf")
        )
        out[rows] = torch.where(missing[rows], masked.max(-2).values, out[rows])
    return out


class PointCloudEncoder(nn.Module):
    """Per-point MLP (Linear, LayerNorm, ReLU per layer), max over points, projection.

    Args:
        hidden: per-point layer widths (DP3: 64, 128, 256).
        out_dim: size of the pooled, projected feature (DP3: 64).

    Example:
        >>> encoder = PointCloudEncoder(hidden=(16, 32), out_dim=8)
        >>> cloud = torch.rand(2, 100, 3)
        >>> encoder(cloud).shape
        torch.Size([2, 8])
        >>> keep = torch.arange(100) < 60  # point dropout is a mask on the pooling: the same as dropping the points
        >>> torch.allclose(encoder(cloud, keep), encoder(cloud[:, :60]))
        True
    """

    def __init__(self, hidden: tuple[int, ...] = (64, 128, 256), out_dim: int = 64):
        super().__init__()
        self.point_mlp = _mlp([3, *hidden], layer_norm=True)
        self.projection = nn.Sequential(nn.Linear(hidden[-1], out_dim), nn.LayerNorm(out_dim))
        self.hidden, self.out_dim = tuple(hidden), out_dim

    def point_features(self, cloud: torch.Tensor) -> torch.Tensor:
        """``[..., N, 3]`` -> ``[..., N, C]``."""
        if cloud.shape[-1] != 3:
            raise ValueError(f"point clouds must be [..., N, 3], got {tuple(cloud.shape)}")
        return self.point_mlp(cloud)

    def pool(self, features: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """Max over points, only over the points where ``keep`` (``[..., N]`` bool) is set, then
        projects. ``features`` ``[..., N, C]`` broadcast against ``keep``: one feature pass can
        serve many masks (``features`` ``[B, 1, To, N, C]``, ``keep`` ``[B, K, To, N]``)."""
        pooled = features.max(dim=-2).values if keep is None else masked_max(features, keep)
        return self.projection(pooled)

    def forward(self, cloud: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        return self.pool(self.point_features(cloud), keep)


class StateEncoder(nn.Module):
    """Robot-state MLP: D -> 64 -> ReLU -> 64 (DP3).

    Example:
        >>> StateEncoder(state_dim=4)(torch.rand(5, 2, 4)).shape  # any leading shape, e.g. a 2-step history
        torch.Size([5, 2, 64])
    """

    def __init__(self, state_dim: int, hidden: int = 64, out_dim: int = 64):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(state_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))
        self.state_dim, self.hidden, self.out_dim = state_dim, hidden, out_dim

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if state.shape[-1] != self.state_dim:
            raise ValueError(f"agent_pos must have {self.state_dim} entries, got {tuple(state.shape)}")
        return self.net(state)
