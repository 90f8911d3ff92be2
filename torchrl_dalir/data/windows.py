"""Training windows: observation history, action chunk and the observation ``k`` steps ahead.

Every step at which an action was taken anchors one window, the last steps of every episode
included. With ``obs_steps = 2`` and ``horizon = 16`` (DP3's setting), the window of step ``t``
holds observations ``t-1, t``, actions ``t-1 .. t+14`` and the observation ``t + 8``:

- before the episode start, observations and actions repeat the first ones (DP3's padding; the
  observations by the rule of :mod:`torchrl_dalir.envs.history`, the env's);
- past the last action, actions repeat the last one; ``action_is_pad`` marks every padded
  chunk step, so a loss can ignore them;
- past the final observation ``s_T``, the future is ``s_T`` itself and ``future_is_pad`` is set.

(TorchRL's ``SliceSampler`` does not pad episode ends reliably in 0.14.1, hence this class.)
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.data.storage import TrajectoryDataset
from torchrl_dalir.envs.history import history_steps


class TrajectoryWindows:
    """Indexable training windows over a :class:`TrajectoryDataset`.

    Args:
        dataset: the labeled trajectories.
        obs_steps: observation-history length ``To``.
        horizon: action-chunk length ``H``.
        future_offset: ``k``, how far ahead the world model's target observation lies.
        observation_keys: the observation entries to gather (never the privileged state).

    Example:
        >>> from pathlib import Path
        >>> from torchrl_dalir.data import DatasetMeta, trajectory_rows
        >>> T, success = 20, torch.arange(20)[:, None] == 19  # 20 actions, then a success; agent_pos is the step
        >>> episode = TensorDict({"agent_pos": torch.arange(T * 1.0)[:, None], "action": torch.rand(T, 4), "next": {
        ...     "agent_pos": torch.arange(1.0, T + 1)[:, None], "reward": torch.zeros(T, 1),
        ...     "success": success, "done": success}}, [T])
        >>> rows = trajectory_rows(episode, trajectory_id=0, source=0, noise_scale=0.0, expert_source=True, gamma=0.9)
        >>> meta = DatasetMeta("synthetic", 8, 0.9, 0, [])
        >>> windows = TrajectoryWindows(TrajectoryDataset(Path("in-memory"), meta, rows))
        >>> batch = windows[[0, 5]]  # the windows of steps 0 and 5
        >>> batch["agent_pos"].squeeze(-1).tolist(), batch["obs_is_pad"].tolist()  # step 0's history repeats it
        ([[0.0, 0.0], [4.0, 5.0]], [[True, False], [False, False]])
        >>> batch["action_chunk"].shape, batch["future", "agent_pos"].squeeze(-1).tolist()  # 16 actions; 8 steps ahead
        (torch.Size([2, 16, 4]), [8.0, 13.0])
        >>> windows.sample(64, generator=torch.Generator().manual_seed(0))["agent_pos"].shape
        torch.Size([64, 2, 1])
    """

    def __init__(
        self,
        dataset: TrajectoryDataset,
        obs_steps: int = 2,
        horizon: int = 16,
        future_offset: int = 8,
        observation_keys: tuple[str, ...] = (keys.POINT_CLOUD, keys.AGENT_POS),
    ):
        if obs_steps < 1 or horizon < obs_steps or future_offset < 1:
            raise ValueError(
                f"need 1 <= obs_steps <= horizon and future_offset >= 1; got {obs_steps}, {horizon}, {future_offset}"
            )
        self.dataset = dataset
        self.obs_steps, self.horizon, self.future_offset = obs_steps, horizon, future_offset
        self.observation_keys = tuple(k for k in observation_keys if k in dataset.rows.keys())
        rows = dataset.rows
        self.anchors = torch.nonzero(~rows[keys.IS_FINAL]).squeeze(-1)
        trajectory = rows[keys.TRAJECTORY_ID][self.anchors]
        self._start = dataset.starts[trajectory]
        self._num_actions = dataset.lengths[trajectory] - 1  # T
        self._t = self.anchors - self._start

    def __len__(self) -> int:
        return len(self.anchors)

    @property
    def steps(self) -> torch.Tensor:
        """The step ``t`` that anchors each window (its index in its trajectory)."""
        return self._t

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> TensorDict:
        return self[torch.randint(len(self), (batch_size,), generator=generator)]

    def __getitem__(self, index) -> TensorDict:
        index = torch.as_tensor(index).reshape(-1)
        start, num_actions, t = self._start[index, None], self._num_actions[index, None], self._t[index, None]
        rows = self.dataset.rows

        obs_t, obs_is_pad = history_steps(t.squeeze(-1), self.obs_steps)
        obs_rows = start + obs_t
        act_t = t - (self.obs_steps - 1) + torch.arange(self.horizon)
        act_rows = start + act_t.clamp(min=0).minimum(num_actions - 1)
        future_t = t.squeeze(-1) + self.future_offset
        future_rows = start.squeeze(-1) + future_t.minimum(num_actions.squeeze(-1))

        def gather(key, idx):
            return rows[key][idx.reshape(-1)].reshape(*idx.shape, *rows[key].shape[1:])

        anchor_rows = self.anchors[index]
        batch = len(index)
        return TensorDict(
            {
                **{key: gather(key, obs_rows) for key in self.observation_keys},
                keys.OBS_MASK: obs_is_pad,
                keys.ACTION_CHUNK: gather(keys.ACTION, act_rows),
                keys.ACTION_MASK: (act_t < 0) | (act_t >= num_actions),
                keys.FUTURE: TensorDict(
                    {
                        **{key: gather(key, future_rows) for key in self.observation_keys},
                        keys.COMPLETION_TARGET: gather(keys.COMPLETION_TARGET, future_rows),
                    },
                    batch_size=[batch],
                ),
                keys.FUTURE_MASK: future_t > num_actions.squeeze(-1),
                **{
                    key: gather(key, anchor_rows)
                    for key in (
                        keys.COMPLETION_TARGET,
                        keys.TERMINAL_LABEL,
                        keys.TRAJECTORY_ID,
                        keys.STEP,
                        keys.QUALITY,
                    )
                },
            },
            batch_size=[batch],
        )
