"""Terminal labels, discounted Monte-Carlo completion targets and quality tags.

A trajectory that took ``T`` actions is stored as ``T + 1`` rows, one per observation
``s_0 .. s_T``; row ``T`` holds the final observation (no action follows it). Its terminal label
is ``y_T = 1`` if the success flag was set (the episode then terminated), ``0`` if it timed out,
and row ``t`` carries the scorer's target ``y_t = gamma^(T - t) * y_T``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives.value.functional import reward2go

from torchrl_dalir import keys

# Observation entries copied from the env into every stored row.
OBSERVATION_KEYS = (keys.POINT_CLOUD, keys.AGENT_POS, keys.PRIVILEGED_STATE)


def completion_targets(num_actions: int, terminal_label: float, gamma: float) -> torch.Tensor:
    """``[T + 1]`` float32 targets ``gamma^(T - t) * y_T`` for ``t = 0 .. T``."""
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
    exponents = torch.arange(num_actions, -1, -1, dtype=torch.float64)
    return (gamma**exponents * terminal_label).to(torch.float32)


def dense_reward_targets(rows: TensorDictBase, gamma: float) -> torch.Tensor:
    """The dense-reward oracle's targets (the paper's ablation): each row's discounted reward-to-go
    within its trajectory, divided by the largest one so that targets lie in [0, 1].

    ``rows`` are stored rows (``reward`` of the action taken at the row, ``is_final`` at ``s_T``).
    Uses the simulator's shaped reward, which the method itself never sees.
    """
    reward = rows[keys.REWARD].float().unsqueeze(-1)
    to_go = reward2go(reward, rows[keys.IS_FINAL].unsqueeze(-1), gamma, time_dim=-2).squeeze(-1)
    if (to_go < 0).any():
        raise ValueError("the dense-reward oracle expects non-negative rewards")
    return to_go / to_go.max().clamp_min(1e-8)


def quality_tag(success: bool, expert_source: bool) -> int:
    """Index into :data:`keys.QUALITY_TAGS`: a clean expert's success is ``expert``, any other
    success ``imperfect_success``, and every failure ``failed``."""
    if not success:
        return keys.QUALITY_TAGS.index("failed")
    return keys.QUALITY_TAGS.index("expert" if expert_source else "imperfect_success")


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
    ``T + 1`` labeled rows that the dataset stores."""
    num_actions = trajectory.shape[0]
    if num_actions == 0 or not bool(trajectory["next", keys.DONE][-1].all()):
        raise ValueError("a stored trajectory must be complete: its last step must be done")
    success_flags = trajectory["next", keys.SUCCESS].reshape(num_actions)
    success = bool(success_flags.any())
    label = float(success)

    final = trajectory[-1]["next"]
    observations = {
        key: torch.cat([trajectory[key], final[key].unsqueeze(0)]) for key in OBSERVATION_KEYS if key in trajectory.keys()
    }
    action = trajectory[keys.ACTION]
    n = num_actions + 1
    rows = TensorDict(
        {
            **observations,
            keys.ACTION: torch.cat([action, torch.zeros_like(action[:1])]),
            keys.REWARD: torch.cat([trajectory["next", keys.REWARD].reshape(num_actions), torch.zeros(1)]),
            keys.SUCCESS: torch.cat([torch.zeros(1, dtype=torch.bool), success_flags]),
            keys.COMPLETION_TARGET: completion_targets(num_actions, label, gamma),
            keys.TERMINAL_LABEL: torch.full((n,), label),
            keys.TRAJECTORY_ID: torch.full((n,), trajectory_id, dtype=torch.int64),
            keys.STEP: torch.arange(n, dtype=torch.int64),
            keys.IS_FINAL: torch.arange(n) == num_actions,
            keys.QUALITY: torch.full((n,), quality_tag(success, expert_source), dtype=torch.int64),
            keys.SOURCE: torch.full((n,), source, dtype=torch.int64),
            keys.NOISE_SCALE: torch.full((n,), noise_scale, dtype=torch.float32),
        },
        batch_size=[n],
    )
    return rows
