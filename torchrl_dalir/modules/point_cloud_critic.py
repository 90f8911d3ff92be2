"""``PointCloudCritic``: a chunk critic that reads the point cloud through an encoder of its own.

The :class:`~torchrl_dalir.modules.ChunkCritic` reads the frozen policy's condition, trained on 10 demos for
imitation: what it does not show of the state, no critic on top of it can rank by. This critic owns a copy of
the policy's observation encoders (DP3's point MLP and robot-state MLP, with their normalisers), initialised
from the policy's weights and then trained for scoring, so it can learn what the ranking needs. It is the
student of a privileged teacher (:mod:`~torchrl_dalir.training.distillation`), and it scores candidates for
:class:`~torchrl_dalir.reranking.RerankingActor` through the same rules as the chunk critic
(``SelectionConfig(scorer="critic")``).
"""

from __future__ import annotations

import copy

import torch

from torchrl_dalir import keys
from torchrl_dalir.modules.chunk_critic import ChunkCritic
from torchrl_dalir.modules.encoders import PointCloudEncoder, StateEncoder
from torchrl_dalir.modules.normalizer import MinMaxNormalizer
from torchrl_dalir.modules.world_model import _TensorModule

POOLED_POINTS = "pooled_points"  # [B, To, C] the point MLP's max-pooled features of a cloud history
EXECUTED_ACTIONS = "executed_actions"  # [B, K, k, A] each candidate's executed actions (env units)
CANDIDATE_LOGITS = "candidate_logits"  # [B, K] a scorer's logits of a decision's candidates
#: The parts of a policy this critic copies (a ChunkPolicy3D's attribute names).
ENCODER_PARTS = ("point_normalizer", "state_normalizer", "point_encoder", "state_encoder")


class PointCloudCritic(ChunkCritic):
    """Logits ``[B, K]`` of eventual success for chunks' executed actions ``[B, K, k, A]`` from observation
    histories (``[B, To, N, 3]`` clouds, ``[B, To, D]`` robot states), through its own encoders.

    Args:
        obs_steps: ``To``, the history it reads.
        state_dim: ``D``, the size of ``agent_pos``.
        action_dim, action_steps: ``A`` and ``k``, the executed actions' shape.
        point_hidden, point_out, state_out: the encoders' sizes (DP3's: 64, 128, 256; 64; 64).
        hidden: the scoring MLP's width.

    Example:
        >>> critic = PointCloudCritic(obs_steps=2, state_dim=4, action_dim=4, action_steps=8,
        ...                           point_hidden=(8, 16), point_out=8, state_out=8, hidden=16)
        >>> cloud, agent_pos = torch.rand(3, 2, 64, 3), torch.rand(3, 2, 4)
        >>> critic.scores(cloud, agent_pos, torch.rand(3, 5, 8, 4)).shape  # 3 decisions, 5 candidates each
        torch.Size([3, 5])
        >>> critic.condition(None, cloud, agent_pos).shape  # its own condition: no policy needed
        torch.Size([3, 32])
    """

    def __init__(
        self,
        obs_steps: int,
        state_dim: int,
        action_dim: int,
        action_steps: int,
        point_hidden: tuple[int, ...] = (64, 128, 256),
        point_out: int = 64,
        state_out: int = 64,
        hidden: int = 128,
    ):
        super().__init__(obs_steps * (point_out + state_out), action_dim, action_steps, hidden)
        self.obs_steps, self.state_dim = obs_steps, state_dim
        self.point_hidden, self.point_out, self.state_out = tuple(point_hidden), point_out, state_out
        self.point_normalizer = MinMaxNormalizer(3)
        self.state_normalizer = MinMaxNormalizer(state_dim)
        self.point_encoder = PointCloudEncoder(self.point_hidden, point_out)
        self.state_encoder = StateEncoder(state_dim, out_dim=state_out)

    @classmethod
    def from_encoders(cls, encoders: dict, action_dim: int, action_steps: int, hidden: int = 128) -> PointCloudCritic:
        """A critic whose encoders start as ``encoders`` (:func:`policy_encoders`: sizes and weights)."""
        critic = cls(action_dim=action_dim, action_steps=action_steps, hidden=hidden, **encoders["sizes"])
        for part in ENCODER_PARTS:
            getattr(critic, part).load_state_dict(encoders["weights"][part])
        return critic

    @classmethod
    def from_policy(cls, policy, hidden: int = 128) -> PointCloudCritic:
        """A critic whose encoders start as a copy of ``policy``'s (a DP3 or flow-matching policy)."""
        return cls.from_encoders(policy_encoders(policy), policy.action_dim, policy.action_steps, hidden)

    def architecture(self) -> dict:
        return {
            "obs_steps": self.obs_steps,
            "state_dim": self.state_dim,
            "action_dim": self.action_dim,
            "action_steps": self.action_steps,
            "point_hidden": list(self.point_hidden),
            "point_out": self.point_out,
            "state_out": self.state_out,
            "hidden": self.hidden,
        }

    def encode(self, cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """Its own condition ``[B, To * (point_out + state_out)]`` of observation histories (differentiable)."""
        if cloud.shape[-3:-2] != (self.obs_steps,) or agent_pos.shape[-2:] != (self.obs_steps, self.state_dim):
            raise ValueError(
                f"expected clouds [B, {self.obs_steps}, N, 3] and robot states [B, {self.obs_steps}, "
                f"{self.state_dim}], got {tuple(cloud.shape)} and {tuple(agent_pos.shape)}"
            )
        return self.encode_pooled(self.pooled_points(cloud), agent_pos)

    def pooled_points(self, cloud: torch.Tensor) -> torch.Tensor:
        """The point MLP's features of clouds ``[B, To, N, 3]``, max-pooled over the points: ``[B, To, C]``
        (what a training that keeps the point MLP frozen computes once)."""
        return self.point_encoder.point_features(self.point_normalizer(cloud)).max(dim=-2).values

    def encode_pooled(self, pooled: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """:meth:`encode` from :meth:`pooled_points`: the projection and the robot-state encoder."""
        state = self.state_encoder(self.state_normalizer(agent_pos))
        return torch.cat([self.point_encoder.projection(pooled), state], dim=-1).flatten(-2)

    def scores_pooled(self, pooled: torch.Tensor, agent_pos: torch.Tensor, executed: torch.Tensor) -> torch.Tensor:
        """:meth:`scores` from :meth:`pooled_points`."""
        return self(self.encode_pooled(pooled, agent_pos), executed)

    def condition(self, policy, cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """Its own encoding of the observations; ``policy`` is not read."""
        return self.encode(cloud, agent_pos)

    def scores(self, cloud: torch.Tensor, agent_pos: torch.Tensor, executed: torch.Tensor) -> torch.Tensor:
        """Logits ``[B, K]`` of executed actions ``[B, K, k, A]`` at observation histories."""
        return self(self.encode(cloud, agent_pos), executed)


def policy_encoders(policy) -> dict:
    """A copy of ``policy``'s observation encoders and their normalisers (``sizes`` and ``weights``): what a
    :class:`PointCloudCritic` starts from, small enough to ship with a scorer benchmark."""
    missing = [part for part in ENCODER_PARTS if not hasattr(policy, part)]
    if missing:
        raise TypeError(
            f"{type(policy).__name__} has no {missing}: a PointCloudCritic starts from a DP3 or flow-matching "
            "policy's encoders (torchrl_dalir.modules.ChunkPolicy3D); build one with PointCloudCritic(...) instead"
        )
    config = policy.config
    return {
        "sizes": {
            "obs_steps": policy.obs_steps,
            "state_dim": policy.state_dim,
            "point_hidden": list(config.point_hidden),
            "point_out": config.point_out,
            "state_out": config.state_out,
        },
        "weights": {part: copy.deepcopy(getattr(policy, part).state_dict()) for part in ENCODER_PARTS},
    }


class PointCloudCriticModule(_TensorModule):
    """:class:`PointCloudCritic` as a TensorDict module: the logits of a decision's candidates.

    Args:
        critic: the critic (shared, not copied).
        in_keys: the observation history and the candidates' executed actions (default ``point_cloud``,
            ``agent_pos``, ``executed_actions``).
        out_keys: the logits ``[B, K]`` (default ``candidate_logits``).

    Example:
        >>> from tensordict import TensorDict
        >>> critic = PointCloudCritic(2, 4, 4, 8, point_hidden=(8,), point_out=8, state_out=8, hidden=16)
        >>> decisions = TensorDict(point_cloud=torch.rand(3, 2, 64, 3), agent_pos=torch.rand(3, 2, 4),
        ...                        executed_actions=torch.rand(3, 5, 8, 4), batch_size=[3])
        >>> PointCloudCriticModule(critic)(decisions)["candidate_logits"].shape
        torch.Size([3, 5])
    """

    DEFAULT_IN_KEYS = (keys.POINT_CLOUD, keys.AGENT_POS, EXECUTED_ACTIONS)
    DEFAULT_OUT_KEYS = (CANDIDATE_LOGITS,)
    METHOD = "scores"
