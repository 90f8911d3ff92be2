"""The scripted Adroit Door expert: shapes, input checks, statelessness and a recorded rollout."""

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from torchrl_dalir import keys
from torchrl_dalir.envs import get_task, make_env
from torchrl_dalir.envs.gym_env import make_simulator
from torchrl_dalir.experts.adroit_door import ACTION_DIM, STATE_DIM, DoorScriptedPolicy

# Measured on this repository's pinned simulator: with make_env("door", seed=0) the expert's
# first success comes at this step (the episode then terminates).
SEED_0_SUCCESS_STEP = 86


def _as_module(expert: DoorScriptedPolicy) -> TensorDictModule:
    return TensorDictModule(expert, in_keys=expert.in_keys, out_keys=[keys.ACTION])


@pytest.fixture(scope="module")
def door_states() -> torch.Tensor:
    """Real privileged states along the first 60 steps of an expert episode (approach and grasp)."""
    env = make_env("door", seed=1, render=False)
    rollout = env.rollout(60, _as_module(DoorScriptedPolicy()), break_when_any_done=True)
    return rollout[keys.PRIVILEGED_STATE]


def test_expert_maps_a_batch_of_states_to_bounded_actions(door_states):
    expert = DoorScriptedPolicy()
    assert door_states.shape[-1] == STATE_DIM
    actions = expert(door_states)
    assert actions.shape == (*door_states.shape[:-1], ACTION_DIM)
    assert actions.dtype == torch.float32 and actions.device == door_states.device
    assert actions.abs().max() <= 1.0
    nested = expert(door_states[:6].reshape(2, 3, STATE_DIM))
    assert nested.shape == (2, 3, ACTION_DIM)


def test_expert_is_stateless(door_states):
    """An action depends on its own state only: batch order and call history do not matter."""
    expert = DoorScriptedPolicy()
    batch = expert(door_states)
    reversed_batch = DoorScriptedPolicy()(door_states.flip(0)).flip(0)
    one_by_one = torch.stack([expert(s) for s in door_states])
    assert torch.equal(batch, reversed_batch)
    assert torch.equal(batch, one_by_one)


@pytest.mark.parametrize("shape", [(4, STATE_DIM - 1), (STATE_DIM + 1,), (2, 39)])
def test_expert_rejects_a_wrong_state_size(shape):
    with pytest.raises(ValueError, match="privileged_state"):
        DoorScriptedPolicy()(torch.zeros(shape))


def test_coast_speed_falls_to_zero_at_the_target():
    expert = DoorScriptedPolicy()
    speeds = [expert.coast_speed(a) for a in (0.0, 0.5, 1.0, expert.gains.coast_target, 1.6)]
    assert all(a > b for a, b in zip(speeds[:3], speeds[1:4]))
    assert speeds[3] == speeds[4] == 0.0


def test_expert_rollout_reproduces_the_recorded_success_step():
    env = make_env("door", seed=0, render=False)
    rollout = env.rollout(200, _as_module(DoorScriptedPolicy()), break_when_any_done=True)
    success = rollout["next", keys.SUCCESS].squeeze(-1)
    assert bool(success[-1]) and not bool(success[:-1].any())
    assert rollout.shape[-1] == SEED_0_SUCCESS_STEP


def test_expert_grasps_again_when_the_door_stopped_short():
    """A door left half open with the hand pulled back: the expert re-grasps and yanks again."""
    task = get_task("door")
    env = make_simulator(task)
    raw = env.unwrapped
    env.reset(seed=0)
    qpos, qvel = raw.data.qpos.copy(), np.zeros_like(raw.data.qvel)
    qpos[[0, 3, 28, 29]] = -0.2, 1.4, 0.3, 1.5  # forearm slid back and rolled, door at 0.3 rad, latch turned
    raw.set_state(qpos, qvel)
    expert = DoorScriptedPolicy()
    for step in range(1, 121):
        state = torch.as_tensor(task.privileged_state(raw, raw._get_obs()), dtype=torch.float32)
        _, _, _, _, info = env.step(expert(state).numpy())
        if info["success"]:
            break
    assert info["success"] and step < 100  # measured: 69 steps
