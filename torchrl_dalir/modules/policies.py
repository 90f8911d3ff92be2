"""The base 3D policies: DP3-style diffusion and 3D flow matching over action chunks.

Both read a 2-step history of ``point_cloud`` ``[..., To, N, 3]`` and ``agent_pos``
``[..., To, D]`` (with or without batch dimensions) and write ``action_chunk`` ``[..., H, A]``;
they differ only in how a chunk is generated from noise (:meth:`ChunkPolicy3D.generate`).
Inputs and outputs are in the env's units; min-max normalizers fitted on the demos live inside
the module and are saved with it. Chunks are clamped to the env's action bounds (set by
:func:`~torchrl_dalir.checkpoints.load_policy`), so they hold the actions the simulator executes.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_dalir import keys
from torchrl_dalir.modules.config import FLOW_PREDICTIONS, PolicyConfig
from torchrl_dalir.modules.encoders import PointCloudEncoder, StateEncoder
from torchrl_dalir.modules.normalizer import MinMaxNormalizer
from torchrl_dalir.modules.unet import ConditionalUnet1D
from torchrl_dalir.utils import require_keys

# A point further outside the policy's training clouds than this, in units of their extent (min-max
# normalised to [-1, 1]), is refused: a cloud in millimetres instead of metres lands near 1000, and
# far larger finite values overflow the network into NaN actions. (The robot state is not checked:
# a dimension that barely moved in the demos normalises to large values for ordinary states.)
MAX_NORMALIZED_MAGNITUDE = 100.0


def _name(key: NestedKey) -> str:
    return key if isinstance(key, str) else str(tuple(key))


def check_values(value: torch.Tensor, key: NestedKey) -> None:
    """Refuses an observation entry of a non-floating dtype or with NaN or infinite values, naming it."""
    if not value.is_floating_point():
        raise ValueError(f"{_name(key)} {tuple(value.shape)} is {value.dtype}: pass floating-point values (float32)")
    if not torch.isfinite(value).all():
        bad = int((~torch.isfinite(value)).sum())
        raise ValueError(
            f"{_name(key)} {tuple(value.shape)} holds {bad} NaN or infinite values: check the observation's source"
        )


def check_finite_output(value: torch.Tensor, what: str, cause: str) -> None:
    """Refuses a module's output with NaN or infinite values, naming it, its shape and the likely ``cause``:
    an env would execute NaN actions (MuJoCo resets the simulation) and a selection rule would rank NaN scores."""
    if not torch.isfinite(value).all():
        bad = int((~torch.isfinite(value)).sum())
        raise ValueError(f"{what} {tuple(value.shape)} holds {bad} NaN or infinite values: {cause}")


def check_point_cloud(cloud: torch.Tensor, key: NestedKey = keys.POINT_CLOUD) -> None:
    """Refuses a cloud that is not ``[..., N, 3]`` with ``N >= 1`` finite floating-point points, naming
    ``key`` and the shape (the policies, DALI-R's actor and :class:`PointDropout` share this check)."""
    if cloud.dim() < 2 or cloud.shape[-1] != 3:
        raise ValueError(f"{_name(key)} must be [..., N, 3] (xyz points), got {tuple(cloud.shape)}")
    if cloud.shape[-2] == 0:
        raise ValueError(f"{_name(key)} {tuple(cloud.shape)} holds no points: every cloud needs at least one")
    check_values(cloud, key)


class ChunkPolicy3D(TensorDictModuleBase):
    """Shared body: normalizers, observation encoders and the conditional U-Net.

    It has every member of :class:`~torchrl_dalir.modules.policy_interface.ChunkPolicy`, what DALI-R
    needs of a policy, and its optional ones (point dropout's per-point fast path, the action
    normaliser, the observation checks); a policy of your own needs only the protocol's.

    Args:
        config: the architecture.
        action_dim: ``A``.
        state_dim: ``D``, the size of ``agent_pos``.
        task: the task it is trained on (stored in its checkpoint; an env of another task is refused).
        num_points: the cloud size it is trained on (stored in its checkpoint; other clouds are refused).
        checkpoint: the file it was loaded from (set by :func:`~torchrl_dalir.checkpoints.load_policy`).
        in_keys: where it reads the point cloud and the robot state (default ``point_cloud``, ``agent_pos``).
        out_keys: where it writes the chunk (default ``action_chunk``).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_dalir.modules import PolicyConfig, make_policy
        >>> policy = make_policy(PolicyConfig(down_dims=[16, 32, 64], point_hidden=[16, 32, 64]),
        ...                      action_dim=4, state_dim=4)
        >>> isinstance(policy, ChunkPolicy3D), policy.in_keys, policy.out_keys
        (True, ['point_cloud', 'agent_pos'], ['action_chunk'])
        >>> policy.reset(seed=0)  # its own noise stream: the same observation, the same chunk
        >>> observation = TensorDict(point_cloud=torch.rand(3, 2, 64, 3), agent_pos=torch.rand(3, 2, 4), batch_size=[3])
        >>> chunk = policy(observation.clone())["action_chunk"]
        >>> chunk.shape
        torch.Size([3, 16, 4])
        >>> policy.reset(seed=0)
        >>> torch.equal(policy(observation.clone())["action_chunk"], chunk)
        True
    """

    def __init__(
        self,
        config: PolicyConfig,
        action_dim: int,
        state_dim: int,
        *,
        task: str | None = None,
        num_points: int | None = None,
        checkpoint: str | None = None,
        in_keys: Sequence[NestedKey] = (keys.POINT_CLOUD, keys.AGENT_POS),
        out_keys: Sequence[NestedKey] = (keys.ACTION_CHUNK,),
    ):
        super().__init__()
        if config.flow_prediction not in FLOW_PREDICTIONS:  # "task": a training configuration resolves it for its task
            raise ValueError(
                f"flow_prediction={config.flow_prediction!r} names no target; build the policy from a "
                f"resolved configuration (PolicyTrainingConfig.resolved()) or choose one of {FLOW_PREDICTIONS}"
            )
        self.in_keys, self.out_keys = list(in_keys), list(out_keys)
        self.config = config
        self.action_dim, self.state_dim = action_dim, state_dim
        self.task, self.num_points, self.checkpoint = task, num_points, checkpoint
        self.point_normalizer = MinMaxNormalizer(3)
        self.state_normalizer = MinMaxNormalizer(state_dim)
        self.action_normalizer = MinMaxNormalizer(action_dim)
        # the bounds the env clips actions to (unbounded until set_action_bounds); not saved, they are the env's
        self.register_buffer("action_low", torch.full((action_dim,), -torch.inf), persistent=False)
        self.register_buffer("action_high", torch.full((action_dim,), torch.inf), persistent=False)
        self.generator: torch.Generator | None = (
            None  # the sampling noise's own stream (see reset); None: torch's global one
        )
        self.seed: int | None = None
        self.point_encoder = PointCloudEncoder(tuple(config.point_hidden), config.point_out)
        self.state_encoder = StateEncoder(state_dim, out_dim=config.state_out)
        self.cond_dim = config.obs_steps * (config.point_out + config.state_out)
        self.unet = ConditionalUnet1D(
            action_dim, self.cond_dim, tuple(config.down_dims), config.kernel_size, config.groups, config.step_embed_dim
        )

    # -- chunk sizes (the ChunkPolicy interface, torchrl_dalir.modules.policy_interface) ------
    @property
    def obs_steps(self) -> int:
        """``To``, the observation history it reads (``config.obs_steps``)."""
        return self.config.obs_steps

    @property
    def horizon(self) -> int:
        """``H``, the chunk length (``config.horizon``)."""
        return self.config.horizon

    @property
    def action_steps(self) -> int:
        """The actions executed per decision (``config.action_steps``)."""
        return self.config.action_steps

    # -- normalisation ---------------------------------------------------------------------
    def fit_normalizers(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor, action: torch.Tensor) -> None:
        """Fits the three normalizers on demo data (any leading shape)."""
        self.point_normalizer.fit(point_cloud)
        self.state_normalizer.fit(agent_pos)
        self.action_normalizer.fit(action)

    def set_action_bounds(self, low: torch.Tensor, high: torch.Tensor) -> None:
        """The bounds ``[A]`` the env clips every action to: sampled chunks are clamped to them (in env units), so
        a chunk, and what a world model imagines from it, is what the simulator will execute."""
        low, high = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
        if low.shape != (self.action_dim,) or high.shape != (self.action_dim,) or not (low <= high).all():
            raise ValueError(
                f"action bounds must be two [{self.action_dim}] tensors with low <= high, got {low} and {high}"
            )
        self.action_low.copy_(low)
        self.action_high.copy_(high)

    def reset(self, seed: int | None = None) -> None:
        """With ``seed``, the sampling noise comes from the policy's own generator seeded with it, so the same
        observations give the same chunks whatever else draws from torch's global generator (a collection seeds
        each worker's policy this way); without, that generator restarts from its last seed (if it has none, the
        noise keeps coming from torch's global generator)."""
        if seed is not None:
            self.seed = seed
        if self.seed is not None:
            self.generator = torch.Generator().manual_seed(self.seed)

    # -- observation -> condition ------------------------------------------------------------
    def check_observation(
        self, point_cloud: torch.Tensor, agent_pos: torch.Tensor, in_keys: Sequence[NestedKey] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Refuses an observation the policy cannot act on, naming the entry (``in_keys``, by default the
        policy's) and its shape: a wrong shape, no points, non-numeric or non-finite values, or values far
        outside the range the policy was trained on. Returns both in the policy's dtype: floating-point
        observations of another precision (numpy's float64) are cast, integer or bool ones are refused."""
        cloud_key, state_key = in_keys if in_keys is not None else self.in_keys
        to = self.config.obs_steps
        if point_cloud.dim() < 3 or point_cloud.shape[-3] != to or point_cloud.shape[-1] != 3:
            raise ValueError(
                f"{_name(cloud_key)} must be [..., {to}, N, 3] (a {to}-step history; stack it with "
                f"torchrl_dalir.envs.make_env(..., history={to})), got {tuple(point_cloud.shape)}"
            )
        if agent_pos.shape[-2:] != (to, self.state_dim):
            raise ValueError(
                f"{_name(state_key)} must be [..., {to}, {self.state_dim}] "
                f"(the policy's {self.state_dim}-D robot state, a {to}-step history), got {tuple(agent_pos.shape)}"
            )
        if point_cloud.shape[:-3].numel() == 0:
            raise ValueError(
                f"no observation to act on: {_name(cloud_key)} is {tuple(point_cloud.shape)}, an empty batch"
            )
        check_point_cloud(point_cloud, cloud_key)
        check_values(agent_pos, state_key)
        dtype = self.point_normalizer.low.dtype
        point_cloud, agent_pos = point_cloud.to(dtype), agent_pos.to(dtype)
        excess = self.point_normalizer(point_cloud).abs().max().item()
        if excess > MAX_NORMALIZED_MAGNITUDE:
            low, high = self.point_normalizer.low.tolist(), self.point_normalizer.high.tolist()
            raise ValueError(
                f"{_name(cloud_key)} {tuple(point_cloud.shape)} lies far outside the points the policy was trained on: "
                f"up to {excess:.3g} where they span [-1, 1] after normalisation (xyz from {low} to {high}). "
                "Pass world-frame coordinates in metres, as make_env gives them"
            )
        return point_cloud, agent_pos

    def read_observation(
        self, tensordict: TensorDictBase, in_keys: Sequence[NestedKey] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The point cloud and robot state an actor reads from ``tensordict`` (at ``in_keys``, by default the
        policy's), refused unless they are what the policy acts on (:meth:`check_observation`): a history of
        ``obs_steps`` frames for every batch entry, and the cloud size it was trained on."""
        in_keys = list(in_keys) if in_keys is not None else self.in_keys
        require_keys(tensordict, in_keys[:2], type(self).__name__)
        cloud, agent_pos = tensordict.get(in_keys[0]), tensordict.get(in_keys[1])
        cloud, agent_pos = self.check_observation(cloud, agent_pos, in_keys)
        to = self.config.obs_steps
        if cloud.dim() - 3 < tensordict.batch_dims:
            raise ValueError(
                f"{_name(in_keys[0])} is {tuple(cloud.shape)} in a tensordict of batch size "
                f"{list(tensordict.batch_size)}: it must be [*batch, {to}, N, 3], a {to}-step history "
                f"(torchrl_dalir.envs.make_env(..., history={to}))"
            )
        if self.num_points is not None and cloud.shape[-2] != self.num_points:
            raise ValueError(
                f"the policy was trained on {self.num_points}-point clouds; "
                f"the observation has {cloud.shape[-2]} points "
                f"(torchrl_dalir.envs.make_env(..., num_points={self.num_points}))"
            )
        return cloud, agent_pos

    def point_features(self, point_cloud: torch.Tensor) -> torch.Tensor:
        """Per-point features of normalised clouds ``[..., To, N, 3]`` -> ``[..., To, N, C]``."""
        return self.point_encoder.point_features(self.point_normalizer(point_cloud))

    def condition(
        self, features: torch.Tensor, agent_pos: torch.Tensor, keep: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Pools per-point features (under an optional keep mask ``[..., To, N]``) and appends the
        state features: the U-Net's condition ``[..., To * (point_out + state_out)]``."""
        pooled = self.point_encoder.pool(features, keep)
        state = self.state_encoder(self.state_normalizer(agent_pos))
        return torch.cat([pooled, state], dim=-1).flatten(-2)

    def encode(
        self, point_cloud: torch.Tensor, agent_pos: torch.Tensor, keep: torch.Tensor | None = None
    ) -> torch.Tensor:
        point_cloud, agent_pos = self.check_observation(point_cloud, agent_pos)
        return self.condition(self.point_features(point_cloud), agent_pos, keep)

    # -- condition -> chunk --------------------------------------------------------------------
    def generate(self, cond: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Turns noise ``[B, H, A]`` into a normalised chunk, conditioned on ``cond`` ``[B, C]``."""
        raise NotImplementedError

    def sample(
        self, cond: torch.Tensor, generator: torch.Generator | None = None, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Chunks ``[..., H, A]`` in env units within the action bounds, one per condition ``[..., C]``; batch
        many conditions (e.g. 32 candidates) into one call. The noise comes from ``generator``, by default the
        policy's own (see :meth:`reset`)."""
        generator = generator if generator is not None else self.generator
        batch_shape = cond.shape[:-1]
        flat = cond.reshape(-1, cond.shape[-1])
        shape = (flat.shape[0], self.config.horizon, self.action_dim)
        if noise is None:
            noise = torch.randn(
                shape, generator=generator, device=cond.device if generator is None else generator.device
            )
            noise = noise.to(cond.device)
        elif noise.shape != (*batch_shape, *shape[1:]):
            raise ValueError(
                f"noise must be {(*batch_shape, *shape[1:])} (one chunk per condition), got {tuple(noise.shape)}"
            )
        chunk = self.generate(flat, noise.reshape(shape).to(cond.dtype))
        chunk = self.action_normalizer.unnormalize(chunk).clamp(self.action_low, self.action_high)
        if not torch.isfinite(chunk).all():
            check_finite_output(chunk, "the policy's action_chunk", self._overflow_cause())
        return chunk.reshape(*batch_shape, *shape[1:])

    def _overflow_cause(self) -> str:
        """Why sampled chunks are not finite: damaged weights, or an observation that overflowed the network."""
        if not all(value.isfinite().all() for value in self.state_dict().values() if value.is_floating_point()):
            return (
                "the policy's weights or normalizers hold NaN or infinite values "
                "(a damaged checkpoint, or a training that diverged): load another checkpoint or train it again"
            )
        return (
            "an observation far outside what the policy was trained on overflowed the network: most likely its "
            "robot state (agent_pos, whose range is not checked, unlike the cloud's), e.g. in other units than "
            "the env's; pass observations as make_env gives them"
        )

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase, generator: torch.Generator | None = None) -> TensorDictBase:
        cloud, agent_pos = self.read_observation(tensordict)
        cond = self.condition(self.point_features(cloud), agent_pos)  # ``encode`` without checking again
        return tensordict.set(self.out_keys[0], self.sample(cond, generator))


class DiffusionPolicy3D(ChunkPolicy3D):
    """DP3: DDIM over action chunks; the network predicts the clean chunk, which is clipped.

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig
        >>> policy = DiffusionPolicy3D(PolicyConfig(kind="dp", down_dims=[32, 64, 128]), action_dim=4, state_dim=4)
        >>> cond = policy.encode(torch.rand(3, 2, 64, 3), torch.rand(3, 2, 4))
        >>> policy.sample(cond).shape
        torch.Size([3, 16, 4])
    """

    def __init__(self, config: PolicyConfig, action_dim: int, state_dim: int, **kwargs):
        super().__init__(config, action_dim, state_dim, **kwargs)
        from diffusers import DDIMScheduler

        self.scheduler = DDIMScheduler(
            num_train_timesteps=config.train_timesteps,
            beta_schedule=config.beta_schedule,
            clip_sample=config.clip_sample,
            prediction_type="sample",
            set_alpha_to_one=True,
            steps_offset=0,
        )

    def generate(self, cond: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        self.scheduler.set_timesteps(self.config.ddim_steps)
        x = noise
        for t in self.scheduler.timesteps:
            step = t.to(cond.device).expand(cond.shape[0])
            x = self.scheduler.step(self.unet(x, step, cond), t, x).prev_sample
        return x


FINAL_TIME_GAP = 1e-3  # the smallest 1 - t a derived velocity divides by (Euler steps stop at t <= 1 - 1/steps)


class FlowMatchingPolicy3D(ChunkPolicy3D):
    """3D flow matching: a velocity field along the straight path from noise (t=0) to the chunk
    (t=1), integrated with ``euler_steps`` Euler steps (network evaluations). The network outputs
    the velocity or, with ``flow_prediction="sample"``, the clean chunk (:class:`PolicyConfig`).

    Example:
        >>> from torchrl_dalir.modules import PolicyConfig
        >>> policy = FlowMatchingPolicy3D(PolicyConfig(kind="fm", down_dims=[32, 64, 128], euler_steps=1), 4, 4)
        >>> policy.sample(policy.encode(torch.rand(3, 2, 64, 3), torch.rand(3, 2, 4))).shape
        torch.Size([3, 16, 4])
    """

    def network(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """The U-Net's output at path time ``t`` ``[B]`` in [0, 1] (embedded like a diffusion step): the
        velocity, or the clean chunk under ``flow_prediction="sample"``."""
        return self.unet(x, t * self.config.train_timesteps, cond)

    def network_target(self, chunk: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """What :meth:`network` regresses anywhere on the straight path from ``noise`` to ``chunk``: the
        velocity ``chunk - noise``, or the chunk itself under ``flow_prediction="sample"``."""
        return chunk if self.config.flow_prediction == "sample" else chunk - noise

    def velocity(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """The velocity at path time ``t``; a predicted clean chunk ``a`` gives ``(a - x) / (1 - t)``,
        the velocity that reaches it at ``t = 1``."""
        out = self.network(x, t, cond)
        if self.config.flow_prediction == "sample":
            return (out - x) / (1 - t)[:, None, None].clamp_min(FINAL_TIME_GAP)
        return out

    def generate(self, cond: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        steps = self.config.euler_steps
        x = noise
        for k in range(steps):
            t = torch.full((cond.shape[0],), k / steps, device=cond.device)
            x = x + self.velocity(x, t, cond) / steps
        return x


def make_policy(config: PolicyConfig, action_dim: int, state_dim: int, **kwargs) -> ChunkPolicy3D:
    """The policy class that ``config.kind`` names (``kwargs``: :class:`ChunkPolicy3D`'s keyword arguments,
    ``task``, ``num_points``, ``checkpoint``, ``in_keys``, ``out_keys``)."""
    return {"dp": DiffusionPolicy3D, "fm": FlowMatchingPolicy3D}[config.kind](config, action_dim, state_dim, **kwargs)
