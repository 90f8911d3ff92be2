"""Per-dimension min-max normalisation to [-1, 1], fitted on the demos and saved with the model."""

from __future__ import annotations

import torch
from torch import nn


class MinMaxNormalizer(nn.Module):
    """Maps each feature dimension from its fitted ``[min, max]`` to ``[-1, 1]`` and back.

    Dimensions that never vary (``max - min`` below ``eps``) are only centred, as DP3 does, so
    a constant gripper command or coordinate does not divide by zero.

    Args:
        dim: feature size (the last dimension of the tensors it will see).
        eps: the smallest range treated as varying.

    Example:
        >>> normalizer = MinMaxNormalizer(3).fit(torch.rand(100, 3))
        >>> x = torch.rand(5, 3)
        >>> torch.allclose(normalizer.unnormalize(normalizer(x)), x, atol=1e-6)
        True
    """

    def __init__(self, dim: int, eps: float = 1e-4):
        super().__init__()
        self.eps = eps
        self.register_buffer("low", torch.full((dim,), -1.0))
        self.register_buffer("high", torch.full((dim,), 1.0))
        self.register_buffer("fitted", torch.tensor(False))

    @torch.no_grad()
    def fit(self, data: torch.Tensor) -> MinMaxNormalizer:
        """Fits on ``data`` ``[..., dim]`` (every leading dimension is a sample)."""
        flat = data.reshape(-1, data.shape[-1]).float()
        if flat.shape[-1] != self.low.shape[0]:
            raise ValueError(f"normalizer of size {self.low.shape[0]} cannot fit data of size {flat.shape[-1]}")
        if not torch.isfinite(flat).all():
            raise ValueError("cannot fit a normalizer on data with NaN or infinite values")
        self.low.copy_(flat.min(0).values)
        self.high.copy_(flat.max(0).values)
        self.fitted.fill_(True)
        return self

    def _scale_offset(self):
        span = self.high - self.low
        varying = span > self.eps
        scale = torch.where(varying, 2.0 / span.clamp_min(self.eps), torch.ones_like(span))
        offset = torch.where(varying, -1.0 - self.low * scale, -(self.high + self.low) / 2)
        return scale, offset

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale, offset = self._scale_offset()
        return x * scale + offset

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        scale, offset = self._scale_offset()
        return (y - offset) / scale
