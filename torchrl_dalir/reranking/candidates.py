"""Candidate generators: how DALI-R perturbs the policy's input to get diverse action chunks.

Each generator returns the policy's conditions for ``K`` candidates per observation, the first
always from the clean observation.
"""

from __future__ import annotations

import warnings

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_dalir import keys
from torchrl_dalir.config import check_probability
from torchrl_dalir.modules.policies import check_point_cloud
from torchrl_dalir.modules.policy_interface import has_point_features, read_observation
from torchrl_dalir.reranking.config import RerankingConfig


class PointDropout(TensorDictModuleBase):
    """Stochastic point dropout: every candidate keeps each point with probability ``1 - dropout``.

    With DP3's max-pooled point encoder, dropping points is a mask on the pooling, so for a policy
    with per-point features (``point_features`` and ``condition``, as
    :class:`~torchrl_dalir.modules.ChunkPolicy3D` has) :meth:`conditions` computes them once and
    pools them once per candidate (the same result as re-encoding each dropped cloud, at a fraction
    of the cost). For any other :class:`~torchrl_dalir.modules.ChunkPolicy` it encodes every dropped
    cloud with the policy's ``encode`` (the same conditions, slower: on the ``cpu`` preset's
    architecture, 32 candidates of 512-point clouds and one thread, the conditions took about 30x
    as long, 140 against 5 ms a decision, and with the sampling of the chunks 4.4x for FM with one
    Euler step, 180 against 40 ms, and 1.4x for DP with 10 DDIM steps, 550 against 380 ms;
    ``examples/benchmarks/benchmark_point_dropout.py``).
    Called on a tensordict, it is an ordinary module/transform: dropped points are replaced by a
    kept point of the same cloud, so the cloud keeps its shape and dtype and a max-pooled encoder
    sees the kept set; a cloud with no points or with NaN or infinite values is refused.

    Args:
        dropout: the probability of dropping a point (``p`` before version 0.3, still accepted by keyword).
        seed: seeds the module's own generator (for use as a standalone module).

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"point_cloud": torch.rand(4, 512, 3)}, [4])
        >>> PointDropout(0.2)(td)["point_cloud"].shape
        torch.Size([4, 512, 3])
    """

    in_keys = [keys.POINT_CLOUD]
    out_keys = [keys.POINT_CLOUD]

    def __init__(self, dropout: float = RerankingConfig.dropout, seed: int = 0, *, p: float | None = None):
        super().__init__()
        if p is not None:
            warnings.warn(
                "PointDropout(p=...) is now PointDropout(dropout=...), the name the configurations use",
                DeprecationWarning,
                stacklevel=2,
            )
            dropout = p
        check_probability("dropout probability", dropout)
        self.dropout = dropout
        self.generator = torch.Generator().manual_seed(seed)

    @property
    def p(self) -> float:
        """The dropout probability under its former name."""
        return self.dropout

    def keep_masks(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> torch.Tensor:
        """A bool mask of ``shape`` (``[..., N]``), keeping at least one point per cloud."""
        keep = torch.rand(shape, generator=generator if generator is not None else self.generator) >= self.dropout
        keep[..., 0] |= ~keep.any(-1)
        return keep

    @staticmethod
    def drop(cloud: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """Clouds ``[..., N, 3]`` with the points not in ``keep`` ``[..., N]`` replaced by a kept point of the
        same cloud: the same shape, and the kept set for a max-pooled encoder."""
        first_kept = keep.float().argmax(-1, keepdim=True)  # index of a kept point per cloud
        replacement = torch.gather(cloud, -2, first_kept.unsqueeze(-1).expand(*first_kept.shape, 3))
        return torch.where(keep.unsqueeze(-1), cloud, replacement)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cloud = tensordict.get(keys.POINT_CLOUD)
        check_point_cloud(cloud, keys.POINT_CLOUD)
        keep = self.keep_masks(cloud.shape[:-1]).to(cloud.device)
        return tensordict.set(keys.POINT_CLOUD, self.drop(cloud, keep))

    @staticmethod
    def encode(policy, cloud: torch.Tensor, agent_pos: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """The policy's conditions ``[*batch, C]`` of clouds ``[*batch, To, N, 3]`` (or ``[B, 1, To, N, 3]``, shared
        by the masks) seen through keep masks ``[*batch, To, N]``, with states ``[*batch, To, D]``: by pooling
        per-point features under the masks if the policy has them, else by encoding each dropped cloud."""
        if has_point_features(policy):
            return policy.condition(policy.point_features(cloud), agent_pos, keep)
        batch = keep.shape[:-2]
        dropped = PointDropout.drop(cloud.expand(*batch, *cloud.shape[-3:]), keep)
        cond = policy.encode(dropped.reshape(-1, *dropped.shape[-3:]), agent_pos.reshape(-1, *agent_pos.shape[-2:]))
        return cond.reshape(*batch, cond.shape[-1])

    def conditions(self, policy, cloud, agent_pos, num_candidates: int, generator: torch.Generator) -> torch.Tensor:
        """Conditions ``[B, K, C]`` for clouds ``[B, To, N, 3]``: one feature pass and ``K`` poolings (the fast
        path), or ``K - 1`` dropped clouds encoded anew and the clean one."""
        keep = self.keep_masks((cloud.shape[0], num_candidates, *cloud.shape[1:3]), generator).to(cloud.device)
        keep[:, 0] = True  # candidate 0 sees the clean observation
        states = agent_pos.unsqueeze(1).expand(-1, num_candidates, -1, -1)
        if has_point_features(policy):
            features = policy.point_features(cloud).unsqueeze(1)  # [B, 1, To, N, C], shared by the K masks
            return policy.condition(features, states, keep)
        return self.encode(policy, cloud.unsqueeze(1), states, keep)


class GaussianObservationNoise:
    """The paper's "standard observation noise" baseline: i.i.d. Gaussian jitter of every point
    (``std`` in metres); every candidate's cloud is encoded anew.

    Args:
        std: the noise's standard deviation, in world units (metres).

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> cloud, agent_pos = torch.rand(2, 2, 64, 3), torch.rand(2, 2, 4)  # 2 observations, a 2-step history each
        >>> generator = torch.Generator().manual_seed(0)
        >>> conditions = GaussianObservationNoise(0.01).conditions(policy, cloud, agent_pos, 8, generator)
        >>> conditions.shape  # [B, K, C]: the policy's condition for each of 8 candidates
        torch.Size([2, 8, 256])
        >>> torch.allclose(conditions[:, 0], policy.encode(cloud, agent_pos), atol=1e-6)  # candidate 0 is clean
        True
    """

    def __init__(self, std: float = RerankingConfig.noise_std):
        if std < 0:
            raise ValueError(f"noise std must be non-negative, got {std}")
        self.std = std

    def conditions(self, policy, cloud, agent_pos, num_candidates: int, generator: torch.Generator) -> torch.Tensor:
        batch = cloud.shape[0]
        noise = torch.randn((batch, num_candidates, *cloud.shape[1:]), generator=generator).to(cloud.device) * self.std
        noise[:, 0] = 0  # candidate 0 sees the clean observation
        noisy = cloud.unsqueeze(1) + noise
        states = agent_pos.unsqueeze(1).expand(-1, num_candidates, -1, -1)
        return policy.encode(noisy.flatten(0, 1), states.flatten(0, 1)).reshape(batch, num_candidates, -1)


class CleanObservation:
    """No input perturbation: every candidate is sampled from the clean observation and they differ
    only by the policy's sampling noise (repeated queries of the frozen policy). The seeds of an
    action-space search (:mod:`~torchrl_dalir.reranking.search`); the observation is encoded once.

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> conditions = CleanObservation().conditions(policy, torch.rand(1, 2, 64, 3), torch.rand(1, 2, 4), 8, None)
        >>> conditions.shape, bool((conditions == conditions[:, :1]).all())  # 8 copies of the clean condition
        (torch.Size([1, 8, 256]), True)
    """

    def conditions(self, policy, cloud, agent_pos, num_candidates: int, generator: torch.Generator) -> torch.Tensor:
        return policy.encode(cloud, agent_pos).unsqueeze(1).expand(-1, num_candidates, -1)


class DropoutPolicy(TensorDictModuleBase):
    """A policy that acts on a point-dropout view of its observation: each decision is one of
    DALI-R's perturbed candidates, taken at random. Its rollouts are exploration data that covers
    the candidates a reranker chooses among (the stored observations stay clean).

    Args:
        policy: the frozen base policy (a :class:`~torchrl_dalir.modules.ChunkPolicy`).
        dropout: the point-dropout probability (DALI-R's).
        seed: seeds the dropout masks and the policy's sampling noise (one generator for both).
    """

    in_keys = [keys.POINT_CLOUD, keys.AGENT_POS]
    out_keys = [keys.ACTION_CHUNK]

    def __init__(self, policy, dropout: float = RerankingConfig.dropout, seed: int = 0):
        super().__init__()
        self.policy, self.dropout, self.seed = policy, PointDropout(dropout, seed), seed

    def reset(self, seed: int | None = None) -> None:
        """Restarts masks and noise from ``seed`` (by default the last one), so the same episodes replay."""
        if seed is not None:
            self.seed = seed
        self.dropout.generator.manual_seed(self.seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cloud, agent_pos = read_observation(self.policy, tensordict, self.in_keys)
        keep = self.dropout.keep_masks(cloud.shape[:-1]).to(cloud.device)
        cond = PointDropout.encode(self.policy, cloud, agent_pos, keep)  # checked by read_observation
        return tensordict.set(self.out_keys[0], self.policy.sample(cond, self.dropout.generator))


def candidate_generator(config: RerankingConfig):
    """The candidate generator that ``config`` names, with its setting (``dropout`` or ``noise_std``).

    Example:
        >>> (candidate_generator(RerankingConfig()).dropout,
        ...  type(candidate_generator(RerankingConfig(candidates="clean"))).__name__)
        (0.2, 'CleanObservation')
    """
    if config.candidates == "dropout":
        return PointDropout(config.dropout)
    if config.candidates == "noise":
        return GaussianObservationNoise(config.noise_std)
    return CleanObservation()
