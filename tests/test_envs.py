import dataclasses
from functools import partial

import numpy as np
import pytest
import torch
from conftest import SHORT_REACH
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from torchrl_dalir import TASKS, keys, make_env
from torchrl_dalir.envs import get_task
from torchrl_dalir.experts import make_expert

BENCHMARK = ["door", "pen", "disassemble", "shelf-place", "stick-pull", "pick-place-wall"]


def test_registry_holds_the_paper_tasks():
    assert sorted(TASKS) == sorted(BENCHMARK)
    assert get_task("reach-v3").env_id == "reach-v3"


def test_unknown_task_lists_known_tasks():
    with pytest.raises(KeyError, match="unknown task 'doors'.*disassemble.*reach"):
        make_env("doors")


@pytest.mark.parametrize("task", BENCHMARK)
def test_specs_and_point_clouds(task):
    spec = get_task(task)
    env = make_env(task, seed=0, num_points=256)
    check_env_specs(env)
    rollout = env.rollout(3)
    cloud = rollout[keys.POINT_CLOUD]
    assert cloud.shape == (3, 256, 3) and cloud.dtype == torch.float32
    assert torch.isfinite(cloud).all()
    assert (cloud >= torch.tensor(spec.crop_low)).all() and (cloud <= torch.tensor(spec.crop_high)).all()
    assert rollout[keys.AGENT_POS].shape == (3, spec.agent_pos_dim)
    assert rollout["next", keys.SUCCESS].dtype == torch.bool
    # the cloud is a set of distinct points spread over the workspace, not one repeated point
    assert len(torch.unique(cloud[0], dim=0)) > 100
    env.close()


@pytest.mark.parametrize("task", ["disassemble", "door"])
def test_same_seed_same_episode(task):
    def run(seed):
        env = make_env(task, seed=seed, num_points=128)
        actions = torch.linspace(-0.5, 0.5, 5)[:, None].expand(5, env.action_spec.shape[-1])
        td = env.reset()
        clouds = [td[keys.POINT_CLOUD]]
        for action in actions:
            td = env.step(td.set(keys.ACTION, action.clone()))["next"]
            clouds.append(td[keys.POINT_CLOUD])
        env.close()
        return torch.stack(clouds), td[keys.PRIVILEGED_STATE]

    first, again, other = run(3), run(3), run(4)
    assert torch.equal(first[0], again[0]) and torch.equal(first[1], again[1])
    assert not torch.equal(first[1], other[1])


def test_seed_stride_resets_every_episode_with_a_seed_of_its_own():
    """Episode i resets with seed + i * stride whatever ran before it, and says so; a reset without a step in
    between takes no new seed; the env passes TorchRL's spec check with the seed in its observations."""
    short = dataclasses.replace(SHORT_REACH, max_steps=3)
    check_env_specs(make_env(short, seed=10, seed_stride=4, num_points=16))
    env = make_env(short, seed=10, seed_stride=4, num_points=16)
    env.reset()  # then the rollout's own reset
    rollout = env.rollout(9, break_when_any_done=False)  # three episodes of three steps
    assert rollout[keys.EPISODE_SEED].flatten().tolist() == [10] * 3 + [14] * 3 + [18] * 3
    alone = make_env(short, seed=14, seed_stride=4, num_points=16).reset()
    assert torch.equal(alone[keys.PRIVILEGED_STATE], rollout[keys.PRIVILEGED_STATE][3])
    with pytest.raises(ValueError, match="seed_stride needs a seed"):
        make_env(short, seed=None, seed_stride=4)


def test_episode_terminates_at_first_success():
    env = make_env(SHORT_REACH, seed=0, render=False)
    rollout = env.rollout(SHORT_REACH.max_steps, make_expert("reach"), break_when_any_done=True)
    success = rollout["next", keys.SUCCESS].squeeze(-1)
    assert success[-1] and not success[:-1].any()
    assert rollout["next", keys.TERMINATED][-1].item() and len(rollout) < SHORT_REACH.max_steps


def test_step_limit_truncates():
    env = make_env(SHORT_REACH, seed=0, render=False)
    rollout = env.rollout(100, break_when_any_done=True)  # random actions do not reach the goal
    assert len(rollout) == SHORT_REACH.max_steps
    assert rollout["next", keys.TRUNCATED][-1].item()


def test_simulator_state_replays_an_episode_exactly():
    from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator

    env = PointCloudObservation(make_simulator(SHORT_REACH), SHORT_REACH, num_points=64)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for action in rng.uniform(-1, 1, (SHORT_REACH.max_steps - 4, 4)):
        env.step(action)
    state = env.get_state()
    actions = rng.uniform(-1, 1, (4, 4))

    def play():
        return [env.step(action) for action in actions]

    first = play()  # the last of these hits the step limit
    env.set_state(state)
    second = play()
    assert first[-1][3] and not any(step[3] for step in first[:-1])
    for a, b in zip(first, second):
        assert all(np.array_equal(a[0][key], b[0][key]) for key in a[0])
        assert a[1:4] == b[1:4]
    assert not np.array_equal(first[0][0][keys.POINT_CLOUD], first[-1][0][keys.POINT_CLOUD])
    env.close()


def test_serial_env_of_point_cloud_envs():
    env = SerialEnv(2, lambda: make_env(SHORT_REACH, seed=None, num_points=64))
    env.set_seed(0)
    rollout = env.rollout(4)
    assert rollout[keys.POINT_CLOUD].shape == (2, 4, 64, 3)
    # two workers, two different episodes
    assert not torch.equal(rollout[0, 0][keys.PRIVILEGED_STATE], rollout[1, 0][keys.PRIVILEGED_STATE])
    env.close()


def test_parallel_env_of_point_cloud_envs():
    env = ParallelEnv(2, partial(make_env, SHORT_REACH, seed=None, num_points=64))
    env.set_seed(0)
    rollout = env.rollout(3)
    assert rollout[keys.POINT_CLOUD].shape == (2, 3, 64, 3)
    assert torch.isfinite(rollout[keys.POINT_CLOUD]).all()
    env.close()


def test_history_stacks_observations():
    env = make_env(SHORT_REACH, seed=0, num_points=32, history=2)
    check_env_specs(env)
    rollout = env.rollout(3)
    assert rollout[keys.POINT_CLOUD].shape == (3, 2, 32, 3) and rollout[keys.AGENT_POS].shape == (3, 2, 4)
    # at the reset both frames are the first observation; afterwards the older one is the previous step
    assert torch.equal(rollout[keys.AGENT_POS][0, 0], rollout[keys.AGENT_POS][0, 1])
    assert torch.equal(rollout[keys.AGENT_POS][1, 0], rollout[keys.AGENT_POS][0, 1])
    assert torch.equal(rollout[keys.POINT_CLOUD][2, 0], rollout[keys.POINT_CLOUD][1, 1])


def test_decision_period_renders_only_the_clouds_decisions_read():
    actions = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, (11, 4)).astype(np.float32))

    def play(**kwargs):
        env = make_env(SHORT_REACH, seed=0, num_points=32, history=2, **kwargs)
        td = env.reset()
        steps = [td.clone()]
        for action in actions:
            td = env.step(td.set(keys.ACTION, action))
            steps.append(td["next"].clone())
            td = step_mdp(td)
        env.close()
        return steps

    every, lazy = play(), play(decision_period=4)  # the observations of steps t = 0 (the reset) .. 11
    newest = torch.stack([step[keys.POINT_CLOUD][-1] for step in lazy])
    rendered = [t for t in range(12) if torch.isfinite(newest[t]).all()]
    assert rendered == [0, 3, 4, 7, 8, 11]  # decisions at 0, 4 and 8 read steps 0, 3-4 and 7-8; step 11 is read at 12
    assert all(torch.isnan(newest[t]).all() for t in range(12) if t not in rendered)
    for t in (0, 4, 8):  # what a decision reads is what an env rendering every step gives
        assert torch.equal(lazy[t][keys.POINT_CLOUD], every[t][keys.POINT_CLOUD])
    for a, b in zip(every[1:], lazy[1:]):  # rendering leaves the episode unchanged
        assert torch.equal(a[keys.AGENT_POS], b[keys.AGENT_POS]) and torch.equal(a[keys.REWARD], b[keys.REWARD])
    # an episode's last observation is rendered wherever it ends: step 6 is read by no decision
    env = make_env(dataclasses.replace(SHORT_REACH, max_steps=6), seed=0, num_points=32, history=2, decision_period=4)
    rollout = env.rollout(10, break_when_any_done=True)
    assert rollout.shape[-1] == 6 and torch.isfinite(rollout["next", keys.POINT_CLOUD][-1, -1]).all()
    assert torch.isnan(rollout["next", keys.POINT_CLOUD][-2, -1]).all()  # step 5 is read by no decision either
    env.close()
    with pytest.raises(ValueError, match="decision_period must be at least 1"):
        make_env(SHORT_REACH, decision_period=0)
