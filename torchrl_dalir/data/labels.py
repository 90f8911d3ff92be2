"""Terminal labels, discounted Monte-Carlo completion targets and quality tags.

A trajectory that took ``T`` actions is stored as ``T + 1`` rows, one per observation
``s_0 .. s_T``; row ``T`` holds the final observation (no action follows it). Its terminal label
is ``y_T = 1`` if the success flag was set (the episode then terminated), ``0`` if it timed out,
and row ``t`` carries the scorer's target ``y_t = gamma^(T - t) * y_T``.

:class:`TerminalLabelTransform` computes these labels on TorchRL rollouts (a collector's
``postproc`` or a replay buffer's transform); :func:`trajectory_rows` uses it to build the
stored rows.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase, Transform
from torchrl.objectives.value.functional import reward2go

from torchrl_dalir import keys

# Observation entries copied from the env into every stored row.
OBSERVATION_KEYS = (keys.POINT_CLOUD, keys.AGENT_POS, keys.PRIVILEGED_STATE)


def _check_gamma(gamma: float) -> float:
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
    return float(gamma)


def _discounted(actions_to_go: torch.Tensor, terminal_label: float | torch.Tensor, gamma: float) -> torch.Tensor:
    """``gamma^(T - t) * y_T`` as float32, computed in float64: the one implementation of the target."""
    return (gamma ** actions_to_go.to(torch.float64) * terminal_label).to(torch.float32)


def completion_targets(num_actions: int, terminal_label: float, gamma: float) -> torch.Tensor:
    """``[T + 1]`` float32 targets ``gamma^(T - t) * y_T`` for ``t = 0 .. T``."""
    return _discounted(torch.arange(num_actions, -1, -1), terminal_label, _check_gamma(gamma))


def dense_reward_targets(rows: TensorDictBase, gamma: float) -> torch.Tensor:
    """The dense-reward oracle's targets (the paper's ablation): each row's discounted reward-to-go
    within its trajectory, mapped linearly onto [0, 1] (the smallest to 0, the largest to 1). The
    final rows' reward-to-go is 0, so with non-negative rewards (MetaWorld) this divides by the
    largest; Adroit Pen's shaped reward is partly negative, and the order is kept all the same.

    ``rows`` are stored rows (``reward`` of the action taken at the row, ``is_final`` at ``s_T``).
    Uses the simulator's shaped reward, which the method itself never sees.
    """
    reward = rows[keys.REWARD].float().unsqueeze(-1)
    to_go = reward2go(reward, rows[keys.IS_FINAL].unsqueeze(-1), gamma, time_dim=-2).squeeze(-1)
    low = to_go.min()
    return (to_go - low) / (to_go.max() - low).clamp_min(1e-8)


def quality_tag(success: bool, expert_source: bool) -> int:
    """Index into :data:`keys.QUALITY_TAGS <torchrl_dalir.keys.QUALITY_TAGS>`: a clean expert's success is
    ``expert``, any other success ``imperfect_success``, and every failure ``failed``."""
    if not success:
        return keys.QUALITY_TAGS.index("failed")
    return keys.QUALITY_TAGS.index("expert" if expert_source else "imperfect_success")


class TerminalLabelTransform(Transform):
    """Labels each step of complete trajectories with the trajectory's terminal label ``y_T``, the
    completion target ``gamma^(T - t) * y_T`` of the step's observation and its quality tag.

    The labels depend on how a trajectory ends, so, like TorchRL's ``Reward2GoTransform``, this is
    an inverse transform: :meth:`inv` labels, and it is what ``ReplayBuffer.extend`` runs on the data
    it stores and what a collector runs with ``postproc=labels.inv``; :meth:`forward` passes labeled
    data (a replay buffer's samples) through. It cannot be part of an env.

    Input is TorchRL's rollout layout ``[..., T]`` (time last). ``("next", "done")`` ends a
    trajectory, so a batch may hold several; ``y_T`` is 1 if ``("next", "success")`` was set at any
    step of the trajectory. A batch whose last trajectory is still running is refused, as its label is
    unknown: a collector's fixed-frame batches qualify only when they end at episode ends, and with
    ``trajs_per_batch`` and a replay buffer the collector writes whole trajectories, labeled on
    ``extend``. Zero-padded batches (``trajs_per_batch`` with ``traj_format="padded"``) are read
    through their ``("collector", "mask")``; padded steps get zeros, like the rest of the padding.

    Args:
        gamma: discount of the completion targets, in (0, 1].
        expert_source: whether the trajectories come from the clean expert: a success is then tagged
            ``expert``, otherwise ``imperfect_success`` (see :func:`quality_tag`).
        success_key, done_key, mask_key: where the success flag, the done flag and the optional
            mask of valid steps are read.

    Writes, each of shape ``[..., T]``: ``"completion_target"`` (float32), ``"terminal_label"``
    (float32) and ``"quality"`` (int64, an index into :data:`keys.QUALITY_TAGS <torchrl_dalir.keys.QUALITY_TAGS>`).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> # a success after 3 actions, then a time-out after 2
        >>> done = torch.tensor([[0], [0], [1], [0], [1]], dtype=torch.bool)
        >>> success = torch.tensor([[0], [0], [1], [0], [0]], dtype=torch.bool)
        >>> rollout = TensorDict({"next": {"done": done, "success": success}}, batch_size=[5])
        >>> labels = TerminalLabelTransform(gamma=0.5, expert_source=True)
        >>> labels.inv(rollout)["completion_target"]
        tensor([0.1250, 0.2500, 0.5000, 0.0000, 0.0000])
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(10), transform=labels, batch_size=2)
        >>> _ = buffer.extend(rollout)  # labeled on the way in
        >>> buffer[:]["quality"]  # expert, then failed
        tensor([0, 0, 0, 2, 2])
    """

    ENV_ERR = (
        "TerminalLabelTransform labels complete trajectories: use it as a replay buffer's transform or "
        "as a collector's postproc=labels.inv, not in an env"
    )

    def __init__(
        self,
        gamma: float,
        *,
        expert_source: bool = False,
        success_key: NestedKey = ("next", keys.SUCCESS),
        done_key: NestedKey = ("next", keys.DONE),
        mask_key: NestedKey = ("collector", "mask"),
    ):
        super().__init__(
            in_keys=[],
            in_keys_inv=[done_key, success_key],
            out_keys_inv=[keys.COMPLETION_TARGET, keys.TERMINAL_LABEL, keys.QUALITY],
        )
        self.gamma = _check_gamma(gamma)
        self.expert_source = expert_source
        self.done_key, self.success_key, self.mask_key = done_key, success_key, mask_key

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.shape
        if not shape or shape[-1] == 0:
            raise ValueError(
                "TerminalLabelTransform needs complete trajectories along a last (time) dim, "
                f"got a batch of shape {shape}"
            )
        done = tensordict.get(self.done_key).reshape(shape)
        success = tensordict.get(self.success_key).reshape(shape)
        valid = tensordict.get(self.mask_key, None)
        valid = torch.ones_like(done) if valid is None else valid.reshape(shape)
        last_valid = valid & ~torch.cat([valid[..., 1:], torch.zeros_like(valid[..., :1])], -1)
        if (last_valid & ~done).any():
            raise ValueError(
                "the batch ends with an incomplete trajectory (its last step is not done), so its terminal label is "
                "unknown: TerminalLabelTransform labels complete trajectories only"
            )
        ends = done | ~valid  # a padded step is a trajectory of its own, without success

        time = torch.arange(shape[-1], device=done.device).expand(shape)
        starts = torch.cat([torch.ones_like(ends[..., :1]), ends[..., :-1]], -1)
        first = torch.where(starts, time, 0).cummax(-1).values  # the trajectory's first step
        last = torch.where(ends, time, shape[-1] - 1).flip(-1).cummin(-1).values.flip(-1)  # and its done step
        successes = (success & valid).long().cumsum(-1)
        before = torch.where(first > 0, successes.gather(-1, (first - 1).clamp_min(0)), 0)
        succeeded = successes.gather(-1, last) > before

        quality = torch.where(succeeded, quality_tag(True, self.expert_source), quality_tag(False, self.expert_source))
        target_key, label_key, quality_key = self.out_keys_inv
        tensordict.set(target_key, _discounted(last - time + 1, succeeded.to(torch.float64), self.gamma))
        tensordict.set(label_key, succeeded.to(torch.float32))
        tensordict.set(quality_key, torch.where(valid, quality, 0))
        return tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Passes labeled data through (labels are written by :meth:`inv`, e.g. on ``ReplayBuffer.extend``)."""
        missing = [key for key in self.out_keys_inv if key not in tensordict.keys(include_nested=True)]
        if missing:
            raise KeyError(
                f"{missing} not found: TerminalLabelTransform labels in inv(), e.g. a collector's postproc=labels.inv"
            )
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise ValueError(self.ENV_ERR)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(gamma={self.gamma}, expert_source={self.expert_source})"

    def set_container(self, container) -> None:
        if isinstance(container, EnvBase) or container.parent is not None:
            raise ValueError(self.ENV_ERR)
        super().set_container(container)


def trajectory_rows(
    trajectory: TensorDictBase,
    *,
    trajectory_id: int,
    source: int,
    noise_scale: float,
    expert_source: bool,
    gamma: float,
) -> TensorDict:
    """Turns one collected trajectory (TorchRL layout, ``[T]`` steps with ``"next"``) into the
    ``T + 1`` labeled rows that the dataset stores; the labels come from :class:`TerminalLabelTransform`."""
    num_actions = trajectory.shape[0]
    labeled = TerminalLabelTransform(gamma, expert_source=expert_source).inv(trajectory)  # refuses incomplete ones
    label, quality = labeled[keys.TERMINAL_LABEL], labeled[keys.QUALITY]

    final = trajectory[-1]["next"]
    observations = {
        key: torch.cat([trajectory[key], final[key].unsqueeze(0)])
        for key in OBSERVATION_KEYS
        if key in trajectory.keys()
    }
    action = trajectory[keys.ACTION]
    n = num_actions + 1
    rows = TensorDict(
        {
            **observations,
            keys.ACTION: torch.cat([action, torch.zeros_like(action[:1])]),
            keys.REWARD: torch.cat([trajectory["next", keys.REWARD].reshape(num_actions), torch.zeros(1)]),
            keys.SUCCESS: torch.cat(
                [torch.zeros(1, dtype=torch.bool), trajectory["next", keys.SUCCESS].reshape(num_actions)]
            ),
            # s_T, after the last action, has T - t = 0 actions to go: its target is y_T itself
            keys.COMPLETION_TARGET: torch.cat([labeled[keys.COMPLETION_TARGET], label[-1:]]),
            keys.TERMINAL_LABEL: torch.cat([label, label[-1:]]),
            keys.TRAJECTORY_ID: torch.full((n,), trajectory_id, dtype=torch.int64),
            keys.STEP: torch.arange(n, dtype=torch.int64),
            keys.IS_FINAL: torch.arange(n) == num_actions,
            keys.QUALITY: torch.cat([quality, quality[-1:]]),
            keys.SOURCE: torch.full((n,), source, dtype=torch.int64),
            keys.NOISE_SCALE: torch.full((n,), noise_scale, dtype=torch.float32),
        },
        batch_size=[n],
    )
    return rows
