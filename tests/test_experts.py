import pytest
import torch
from tensordict import TensorDict

from torchrl_dalir import keys, make_env
from torchrl_dalir.envs import TASKS
from torchrl_dalir.experts import DriftNoise, make_expert


def test_metaworld_expert_acts_on_privileged_state():
    expert = make_expert("disassemble")
    td = TensorDict({keys.PRIVILEGED_STATE: torch.rand(5, 39)}, [5])
    action = expert(td)[keys.ACTION]
    assert action.shape == (5, 4) and action.dtype == torch.float32
    assert action.abs().max() <= 1.0


@pytest.mark.parametrize("task", sorted(TASKS))
def test_every_benchmark_task_has_an_expert_that_acts_in_its_env(task):
    env = make_env(task, seed=0, render=False)
    td = make_expert(task)(env.reset())
    assert td[keys.ACTION].shape == env.action_spec.shape
    assert env.action_spec.is_in(td[keys.ACTION])
    env.step(td)


def _noise_sequence(noise, steps, batch, reset_at=()):
    out = []
    for t in range(steps):
        is_init = torch.full((batch, 1), t == 0 or t in reset_at)
        td = TensorDict({keys.ACTION: torch.zeros(batch, 3), keys.IS_INIT: is_init}, [batch])
        out.append(noise(td)[keys.ACTION])
    return torch.stack(out)  # [steps, batch, 3]


def test_drift_noise_statistics():
    scale, rho = 0.1, 0.9
    seq = _noise_sequence(DriftNoise(scale, correlation=rho, seed=0, low=-10, high=10), steps=60, batch=4000)
    assert seq.mean().abs() < 0.005
    assert seq.std(dim=1).mean() == pytest.approx(scale, rel=0.05)  # stationary from the first step
    lag1 = (seq[1:] * seq[:-1]).mean() / seq.var()
    assert lag1 == pytest.approx(rho, abs=0.02)


def test_drift_noise_restarts_at_episode_start_and_is_seeded():
    seq = _noise_sequence(
        DriftNoise(0.1, correlation=0.99, seed=0, low=-10, high=10), steps=40, batch=4000, reset_at={20}
    )
    assert torch.corrcoef(torch.stack([seq[19].flatten(), seq[18].flatten()]))[0, 1] > 0.95
    assert torch.corrcoef(torch.stack([seq[20].flatten(), seq[19].flatten()]))[0, 1].abs() < 0.05
    again = _noise_sequence(
        DriftNoise(0.1, correlation=0.99, seed=0, low=-10, high=10), steps=40, batch=4000, reset_at={20}
    )
    assert torch.equal(seq, again)


def test_drift_noise_clips_to_bounds():
    seq = _noise_sequence(DriftNoise(5.0, seed=1), steps=5, batch=100)
    assert seq.abs().max() <= 1.0 and (seq.abs() == 1.0).any()


def test_drift_noise_rejects_bad_arguments():
    with pytest.raises(ValueError):
        DriftNoise(0.1, correlation=1.0)
    with pytest.raises(ValueError):
        DriftNoise(-0.1)
