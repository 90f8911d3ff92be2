"""What DALI-R needs of a base policy: :class:`ChunkPolicy`, a small ``typing.Protocol``.

:class:`~torchrl_dalir.reranking.RerankingActor` wraps any object with these members, not only
this library's :class:`~torchrl_dalir.modules.ChunkPolicy3D` (which has them all):

- ``encode(point_cloud, agent_pos) -> cond``: an observation history, ``[B, To, N, 3]`` and
  ``[B, To, D]``, to the condition ``[B, C]`` that a chunk is sampled from;
- ``sample(cond, generator=None, noise=None) -> chunk``: chunks ``[..., H, A]`` (env units) from
  conditions ``[..., C]``, many at once; the noise ``[..., H, A]`` comes from ``generator`` or is
  given (DALI-R's common random numbers give the clean candidate the policy's own noise);
- ``obs_steps`` (``To``), ``horizon`` (``H``), ``action_steps`` (actions executed per decision,
  from chunk entry ``To - 1`` on) and ``action_dim`` (``A``).

Optional members, used when present:

- ``point_features(point_cloud) -> [..., To, N, F]`` and ``condition(features, agent_pos, keep)``:
  the fast path of point dropout (:class:`~torchrl_dalir.reranking.PointDropout`): per-point
  features computed once and pooled under each candidate's keep mask ``[..., To, N]``. It must
  give what ``encode`` gives on the kept points. Without it, every dropped cloud is encoded anew
  (its dropped points replaced by a kept point of the same cloud).
- ``read_observation(tensordict, in_keys) -> (point_cloud, agent_pos)``: reads and checks an
  observation; without it, :func:`read_observation` checks the shapes and values.
- ``action_normalizer``: a :class:`~torchrl_dalir.modules.MinMaxNormalizer` of the policy's
  actions, the space an action-space search works in; without it the search uses the world
  model's (fitted on the world model's data).
- ``task``, ``num_points``, ``state_dim``: what it was trained on (an env or observation of another
  is refused); ``reset(seed)``: restarts its own noise stream.

The world model's latent encoder is a copy of the policy's encoders when it has DP3's
(``point_normalizer``, ``point_encoder``, ``state_normalizer``, ``state_encoder``), else a new
encoder of the same architecture trained with the scorer (see
:func:`~torchrl_dalir.training.train_world_model`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch
from tensordict import NestedKey, TensorDictBase

from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.modules.policies import check_point_cloud, check_values
from torchrl_dalir.utils import require_keys

REQUIRED = ("encode", "sample", "obs_steps", "horizon", "action_steps", "action_dim")
FAST_PATH = ("point_features", "condition")


@runtime_checkable
class ChunkPolicy(Protocol):
    """A policy that DALI-R can rerank: it encodes an observation history to a condition and
    samples action chunks from conditions with given noise (see the module's description).

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> config = PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64])
        >>> policy = make_policy(config, action_dim=4, state_dim=4)
        >>> isinstance(policy, ChunkPolicy), (policy.obs_steps, policy.horizon, policy.action_steps, policy.action_dim)
        (True, (2, 16, 8, 4))
        >>> cond = policy.encode(torch.rand(3, 2, 64, 3), torch.rand(3, 2, 4))  # [B, To, N, 3], [B, To, D] -> [B, C]
        >>> policy.sample(cond.unsqueeze(1).expand(-1, 5, -1)).shape  # 5 chunks per condition: [B, 5, H, A]
        torch.Size([3, 5, 16, 4])
    """

    obs_steps: int
    horizon: int
    action_steps: int
    action_dim: int

    def encode(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """Conditions ``[B, C]`` of observation histories ``[B, To, N, 3]`` and ``[B, To, D]``."""
        ...

    def sample(
        self, cond: torch.Tensor, generator: torch.Generator | None = None, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Chunks ``[..., H, A]`` in env units from conditions ``[..., C]``; the noise ``[..., H, A]`` is
        drawn from ``generator`` (by default the policy's own stream) unless given."""
        ...


def missing_members(policy) -> list[str]:
    """The members of :class:`ChunkPolicy` that ``policy`` lacks (methods that are not callable count as missing)."""
    missing = [name for name in REQUIRED if not hasattr(policy, name)]
    return missing + [
        name for name in ("encode", "sample") if name not in missing and not callable(getattr(policy, name))
    ]


def check_chunk_policy(policy, user: str = "RerankingActor") -> None:
    """Refuses an object that is not a :class:`ChunkPolicy`, naming what it lacks, or whose chunk sizes
    do not fit together (the executed actions must lie in the chunk)."""
    missing = missing_members(policy)
    if missing:
        raise TypeError(
            f"{user} needs a chunk policy (torchrl_dalir.modules.ChunkPolicy): {type(policy).__name__} has no "
            f"{', '.join(map(repr, missing))}. It must expose encode(point_cloud, agent_pos) -> cond, "
            "sample(cond, generator=None, noise=None) -> chunk, and obs_steps, horizon, action_steps, action_dim"
        )
    sizes = {name: getattr(policy, name) for name in ("obs_steps", "horizon", "action_steps", "action_dim")}
    if any(not isinstance(value, int) or value < 1 for value in sizes.values()):
        raise ValueError(f"{type(policy).__name__}'s chunk sizes must be positive integers, got {sizes}")
    if sizes["obs_steps"] - 1 + sizes["action_steps"] > sizes["horizon"]:
        raise ValueError(
            f"{type(policy).__name__} executes chunk entries obs_steps - 1 .. obs_steps - 2 + action_steps, "
            f"beyond its horizon: {sizes}"
        )


def has_point_features(policy) -> bool:
    """Whether ``policy`` offers point dropout's fast path (``point_features`` and ``condition``)."""
    return all(callable(getattr(policy, name, None)) for name in FAST_PATH)


def executed(policy: ChunkPolicy) -> slice:
    """The chunk entries a decision executes: ``action_steps`` of them from entry ``obs_steps - 1`` on."""
    return executed_slice(policy.obs_steps, policy.action_steps)


def _name(key: NestedKey) -> str:
    return key if isinstance(key, str) else str(tuple(key))


def read_observation(
    policy: ChunkPolicy, tensordict: TensorDictBase, in_keys: Sequence[NestedKey]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The point cloud and robot state at ``in_keys`` of ``tensordict``, checked: by the policy's own
    ``read_observation`` if it has one, otherwise here: a history of ``obs_steps`` frames for every
    batch entry, ``[*batch, To, N, 3]`` and ``[*batch, To, D]``, finite floating-point values, and the
    ``state_dim`` and ``num_points`` the policy names, if it names them.

    Example:
        >>> from tensordict import TensorDict
        >>> class Sizes:  # enough of a policy for reading
        ...     obs_steps = 2
        >>> td = TensorDict(point_cloud=torch.rand(3, 2, 64, 3), agent_pos=torch.rand(3, 2, 4), batch_size=[3])
        >>> [x.shape for x in read_observation(Sizes(), td, ["point_cloud", "agent_pos"])]
        [torch.Size([3, 2, 64, 3]), torch.Size([3, 2, 4])]
    """
    reader = getattr(policy, "read_observation", None)
    if callable(reader):
        return reader(tensordict, in_keys)
    cloud_key, state_key = list(in_keys)[:2]
    require_keys(tensordict, [cloud_key, state_key], f"{type(policy).__name__}'s actor")
    cloud, agent_pos = tensordict.get(cloud_key), tensordict.get(state_key)
    to = policy.obs_steps
    if cloud.dim() < 3 or cloud.shape[-3] != to or cloud.shape[-1] != 3:
        raise ValueError(
            f"{_name(cloud_key)} must be [..., {to}, N, 3] (a {to}-step history; stack it with "
            f"torchrl_dalir.envs.make_env(..., history={to})), got {tuple(cloud.shape)}"
        )
    state_dim = getattr(policy, "state_dim", None)
    if (
        agent_pos.dim() < 2
        or agent_pos.shape[-2] != to
        or agent_pos.shape[:-2] != cloud.shape[:-3]
        or (state_dim is not None and agent_pos.shape[-1] != state_dim)
    ):
        size = state_dim if state_dim is not None else "D"
        raise ValueError(
            f"{_name(state_key)} must be [..., {to}, {size}] (a {to}-step history of the robot state, with the "
            f"cloud's batch {list(cloud.shape[:-3])}), got {tuple(agent_pos.shape)}"
        )
    if cloud.dim() - 3 < tensordict.batch_dims:
        raise ValueError(
            f"{_name(cloud_key)} is {tuple(cloud.shape)} in a tensordict of batch size {list(tensordict.batch_size)}: "
            f"it must be [*batch, {to}, N, 3], a {to}-step history (torchrl_dalir.envs.make_env(..., history={to}))"
        )
    if cloud.shape[:-3].numel() == 0:
        raise ValueError(f"no observation to act on: {_name(cloud_key)} is {tuple(cloud.shape)}, an empty batch")
    num_points = getattr(policy, "num_points", None)
    if num_points is not None and cloud.shape[-2] != num_points:
        raise ValueError(
            f"the policy was trained on {num_points}-point clouds; the observation has {cloud.shape[-2]} points "
            f"(torchrl_dalir.envs.make_env(..., num_points={num_points}))"
        )
    check_point_cloud(cloud, cloud_key)
    check_values(agent_pos, state_key)
    return cloud, agent_pos
