"""The committed Adroit Pen expert: loading, shapes, input checks and one recorded rollout."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_dalir import keys
from torchrl_dalir.experts.adroit_pen import DEFAULT_WEIGHTS, PenExpertPolicy

# Measured with the committed weights: make_env("pen", seed=ROLLOUT_SEED, render=False) succeeds
# (and so terminates) after ROLLOUT_STEPS steps under the expert's deterministic action.
ROLLOUT_SEED = 1
ROLLOUT_STEPS = 13


@pytest.fixture(scope="module")
def expert():
    return PenExpertPolicy.load()


def test_committed_weights_exist():
    assert DEFAULT_WEIGHTS.exists()


def test_expert_maps_states_to_bounded_actions(expert):
    state = torch.randn(7, 105) * 3.0
    action = expert(state)
    assert action.shape == (7, 24) and action.dtype == torch.float32
    assert action.abs().max() <= 1.0
    assert torch.equal(action, expert(state))  # deterministic: the mean action


def test_expert_reads_privileged_state_in_a_tensordict(expert):
    module = TensorDictModule(expert, in_keys=expert.in_keys, out_keys=[keys.ACTION])
    td = module(TensorDict({keys.PRIVILEGED_STATE: torch.zeros(3, 105)}, [3]))
    assert td[keys.ACTION].shape == (3, 24)


@pytest.mark.parametrize("size", [45, 104, 106])
def test_wrong_state_size_is_a_clear_error(expert, size):
    with pytest.raises(ValueError, match="105"):
        expert(torch.zeros(2, size))


def test_recorded_rollout_is_reproduced(expert, one_thread):
    from torchrl_dalir.envs import make_env

    env = make_env("pen", seed=ROLLOUT_SEED, render=False)
    module = TensorDictModule(expert, in_keys=expert.in_keys, out_keys=[keys.ACTION])
    with torch.no_grad():
        rollout = env.rollout(200, module, break_when_any_done=True)
    env.close()
    assert bool(rollout["next", keys.SUCCESS][-1]) and not bool(rollout["next", keys.SUCCESS][:-1].any())
    assert rollout.shape[-1] == ROLLOUT_STEPS
