"""A 1D temporal U-Net over action chunks, conditioned by FiLM on the time step and the observation.

The denoiser of Diffusion Policy and DP3 (and the velocity field of the flow-matching policy):
residual Conv1d blocks with GroupNorm and Mish, whose features are scaled and shifted by a
linear map of ``[step embedding, observation feature]``.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEmbedding(nn.Module):
    """Embeds a scalar step ``[B]`` as ``[B, dim]`` sines and cosines of geometric frequencies."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, step: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=step.device) / (half - 1))
        angles = step.float()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class ConvBlock(nn.Sequential):
    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, groups: int):
        super().__init__(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(groups, out_channels),
            nn.Mish(),
        )


class FiLMResidualBlock(nn.Module):
    """Two conv blocks; the first one's output is scaled and shifted by the condition."""

    def __init__(self, in_channels: int, out_channels: int, cond_dim: int, kernel_size: int, groups: int):
        super().__init__()
        self.first = ConvBlock(in_channels, out_channels, kernel_size, groups)
        self.second = ConvBlock(out_channels, out_channels, kernel_size, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out_channels))
        self.skip = nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        h = self.first(x) * scale + shift
        return self.second(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """U-Net over ``[B, H, A]`` chunks, conditioned on a step ``[B]`` and a feature ``[B, C]``.

    Args:
        action_dim: ``A``.
        cond_dim: size of the observation feature.
        down_dims: channel widths per level (DP3: 512, 1024, 2048; the chunk length must be
            divisible by ``2 ** (len(down_dims) - 1)``).
        kernel_size: temporal kernel (DP3: 5).
        groups: GroupNorm groups (DP3: 8).
        step_embed_dim: size of the step embedding (DP3: 128).

    Example:
        >>> net = ConditionalUnet1D(4, cond_dim=256, down_dims=(32, 64, 128))
        >>> net(torch.randn(2, 16, 4), torch.tensor([3, 7]), torch.randn(2, 256)).shape
        torch.Size([2, 16, 4])
    """

    def __init__(
        self,
        action_dim: int,
        cond_dim: int,
        down_dims: tuple[int, ...] = (512, 1024, 2048),
        kernel_size: int = 5,
        groups: int = 8,
        step_embed_dim: int = 128,
    ):
        super().__init__()
        self.step_encoder = nn.Sequential(
            SinusoidalEmbedding(step_embed_dim),
            nn.Linear(step_embed_dim, 4 * step_embed_dim),
            nn.Mish(),
            nn.Linear(4 * step_embed_dim, step_embed_dim),
        )
        film_dim = step_embed_dim + cond_dim
        widths = [action_dim, *down_dims]
        levels = list(zip(widths[:-1], widths[1:]))

        def block(n_in, n_out):
            return FiLMResidualBlock(n_in, n_out, film_dim, kernel_size, groups)

        self.down = nn.ModuleList()
        for i, (n_in, n_out) in enumerate(levels):
            last = i == len(levels) - 1
            resample = nn.Identity() if last else nn.Conv1d(n_out, n_out, 3, stride=2, padding=1)
            self.down.append(nn.ModuleList([block(n_in, n_out), block(n_out, n_out), resample]))
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]), block(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList()
        for n_in, n_out in reversed(levels[1:]):  # every up level undoes one downsampling
            upsample = nn.ConvTranspose1d(n_in, n_in, 4, stride=2, padding=1)
            self.up.append(nn.ModuleList([block(2 * n_out, n_in), block(n_in, n_in), upsample]))
        self.head = nn.Sequential(
            ConvBlock(down_dims[0], down_dims[0], kernel_size, groups), nn.Conv1d(down_dims[0], action_dim, 1)
        )
        self.min_length = 2 ** (len(down_dims) - 1)

    def forward(self, chunk: torch.Tensor, step: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        if chunk.shape[-2] % self.min_length:
            raise ValueError(f"chunk length {chunk.shape[-2]} must be divisible by {self.min_length}")
        film = torch.cat([self.step_encoder(step.expand(chunk.shape[0])), cond], dim=-1)
        x = chunk.transpose(1, 2)
        skips = []
        for first, second, downsample in self.down:
            x = second(first(x, film), film)
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, film)
        for first, second, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(second(first(x, film), film))
        return self.head(x).transpose(1, 2)
