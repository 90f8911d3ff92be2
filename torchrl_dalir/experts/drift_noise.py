"""Temporally correlated action noise that turns any policy into an imperfect one."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from torchrl_dalir import keys


class DriftNoise(TensorDictModuleBase):
    """Adds stationary AR(1) noise to ``action`` and clips it to the action bounds.

    ``n_t = rho * n_{t-1} + sqrt(1 - rho^2) * scale * eps_t`` with ``eps_t ~ N(0, I)``, started
    from its stationary law at every episode start (``is_init``, from TorchRL's ``InitTracker``),
    so every step's noise has standard deviation ``scale`` and lag-1 correlation ``rho``: the
    arm drifts off course for several steps instead of jittering. The noise state lives in the
    module, one row per env of the batch; the generator is seeded, so a collection is repeatable.

    Args:
        scale: noise standard deviation, a float or one value per action dimension.
        correlation: ``rho``, the lag-1 autocorrelation (0 gives white noise).
        seed: seeds the module's own generator.
        low, high: action bounds the noisy action is clipped to.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> noise = DriftNoise(scale=0.1, correlation=0.9, seed=0)
        >>> td = TensorDict({"action": torch.zeros(4), "is_init": torch.ones(1, dtype=torch.bool)})
        >>> noise(td)["action"].shape
        torch.Size([4])
    """

    in_keys = [keys.ACTION, keys.IS_INIT]
    out_keys = [keys.ACTION]

    def __init__(
        self,
        scale: float | torch.Tensor,
        correlation: float = 0.9,
        seed: int = 0,
        low: float | torch.Tensor = -1.0,
        high: float | torch.Tensor = 1.0,
    ):
        super().__init__()
        if not 0.0 <= correlation < 1.0:
            raise ValueError(f"correlation must lie in [0, 1), got {correlation}")
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32))
        if (self.scale < 0).any():
            raise ValueError(f"noise scale must be non-negative, got {scale}")
        self.correlation = float(correlation)
        self.low, self.high = low, high
        self.generator = torch.Generator().manual_seed(seed)
        self._noise: torch.Tensor | None = None

    def reset(self, seed: int) -> None:
        """Restarts the noise from its stationary law, the generator seeded with ``seed`` (at an episode start,
        so that the episode's noise depends on ``seed`` only)."""
        self.generator.manual_seed(seed)
        self._noise = None

    def _sample(self, like: torch.Tensor) -> torch.Tensor:
        eps = torch.randn(like.shape, generator=self.generator, dtype=torch.float32)
        return eps.to(like.device) * self.scale.to(like.device)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION)
        is_init = tensordict.get(keys.IS_INIT, None)
        fresh = self._sample(action)
        if self._noise is None or self._noise.shape != action.shape:
            noise = fresh
        else:
            rho = self.correlation
            noise = rho * self._noise + (1 - rho**2) ** 0.5 * fresh
            if is_init is not None:
                restart = is_init.reshape(*action.shape[:-1], 1)
                noise = torch.where(restart, fresh, noise)
        self._noise = noise
        noisy = (action + noise).clamp(self.low, self.high)
        return tensordict.set(keys.ACTION, noisy)


def add_drift_noise(policy, scale: float, correlation: float = 0.9, seed: int = 0) -> TensorDictSequential:
    """``policy`` followed by :class:`DriftNoise`: an imperfect version of any TorchRL policy."""
    return TensorDictSequential(policy, DriftNoise(scale, correlation=correlation, seed=seed))
