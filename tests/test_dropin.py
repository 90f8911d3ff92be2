"""The actors as drop-in TorchRL policies: any env layout, their own settings, clear refusals (issue 16)."""

import dataclasses
from functools import partial

import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict
from test_reranking import _observation, _parts
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.utils import step_mdp

from torchrl_dalir import RerankingActor, keys, make_env, receding_horizon
from torchrl_dalir.envs import env_task
from torchrl_dalir.modules import PolicyConfig, make_policy
from torchrl_dalir.modules.receding_horizon import ACTION_PLAN
from torchrl_dalir.reranking import CANDIDATE_SCORES, CHOSEN_CANDIDATE

POINTS = 40


def _dalir(seed=3, **kwargs):
    parts = _parts(task="reach", num_points=POINTS)  # as load_policy builds it
    return RerankingActor(*parts, num_candidates=4, seed=seed, **kwargs)


def _reach(max_steps=80, **kwargs):
    return make_env(dataclasses.replace(SHORT_REACH, max_steps=max_steps), num_points=POINTS, history=2, **kwargs)


@pytest.fixture(scope="module")
def env():
    env = _reach(seed=0)
    yield env
    env.close()


def check_receding_horizon(rollout):
    """Every batch entry replans at its own episode starts and every 8 steps, and only then: each
    step executes its plan's next action and carries its decision's scores and choice."""
    rollout = rollout.reshape(-1, rollout.shape[-1])  # [envs, steps]
    counter, is_init = rollout["counter"].squeeze(-1), rollout[keys.IS_INIT].squeeze(-1)
    assert (counter[:, 0] == 1).all()
    replan = is_init[:, 1:] | (counter[:, :-1] == 8)
    torch.testing.assert_close(counter[:, 1:], torch.where(replan, 1, counter[:, :-1] + 1))
    plan = rollout[ACTION_PLAN]
    index = (counter - 1).long()[..., None, None].expand(*counter.shape, 1, plan.shape[-1])
    assert torch.equal(rollout[keys.ACTION], plan.gather(2, index).squeeze(2))
    kept = ~replan
    assert torch.equal(plan[:, 1:][kept], plan[:, :-1][kept])
    assert torch.equal(rollout[CHOSEN_CANDIDATE][:, 1:][kept], rollout[CHOSEN_CANDIDATE][:, :-1][kept])
    assert torch.equal(rollout[CHOSEN_CANDIDATE], rollout[CANDIDATE_SCORES].argmax(-1))


def test_unbatched_env_runs_the_policy_and_dalir_directly_in_rollouts_and_in_a_collector(env):
    dalir = _dalir()
    observation = env.reset()
    assert dalir(observation.clone())[keys.ACTION_CHUNK].shape == (16, 4)  # no batch dimension needed
    assert dalir.policy(observation.clone())[keys.ACTION_CHUNK].shape == (16, 4)
    rollout = env.rollout(20, receding_horizon(dalir), break_when_any_done=False)
    assert rollout[keys.ACTION].shape == (20, 4) and rollout[CANDIDATE_SCORES].shape == (20, 4)
    check_receding_horizon(rollout)
    assert env.rollout(9, receding_horizon(dalir.policy))[keys.ACTION].shape == (9, 4)
    collector = Collector(env, receding_horizon(dalir), frames_per_batch=12, total_frames=12)
    batch = next(iter(collector))
    collector.shutdown(close_env=False)
    assert batch[keys.ACTION].shape == (12, 4)
    check_receding_horizon(batch)


def test_an_actor_goes_on_with_the_plan_its_tensordict_carries(env):
    actor = receding_horizon(_dalir())
    start = env.rollout(4, actor, break_when_any_done=False)
    other = _reach(seed=1)
    other.rollout(3, actor)  # the same actor object acts elsewhere in between
    other.close()
    carried = step_mdp(start[-1], keep_other=True)
    rest = env.rollout(6, actor, auto_reset=False, tensordict=carried, break_when_any_done=False)
    assert rest["counter"].squeeze(-1).tolist() == [5, 6, 7, 8, 1, 2]
    assert torch.equal(rest[ACTION_PLAN][:4], start[ACTION_PLAN][-1:].expand(4, 8, 4))


@pytest.fixture(scope="module", params=[SerialEnv, ParallelEnv])
def batched_env(request):
    # episodes of 5 and 11 steps: resets in one env fall in the middle of the other's plans
    tasks = [dataclasses.replace(SHORT_REACH, max_steps=steps) for steps in (5, 11)]
    env = request.param(2, [partial(make_env, task, num_points=POINTS, history=2) for task in tasks])
    yield env
    if not env.is_closed:
        env.close()


def test_batched_env_reset_seeds_every_worker_alike_unless_told_apart(batched_env):
    goal = lambda td: td[keys.PRIVILEGED_STATE][:, -3:]  # noqa: E731
    same = goal(batched_env.reset(seed=7))  # TorchRL passes reset keywords to every worker
    assert torch.equal(same[0], same[1])
    apart = goal(batched_env.reset(list_of_kwargs=[{"seed": 7}, {"seed": 8}]))
    assert torch.equal(apart[0], same[0]) and not torch.equal(apart[0], apart[1])
    batched_env.set_seed(7)
    seeded = goal(batched_env.reset())
    assert not torch.equal(seeded[0], seeded[1])


def test_batched_envs_replan_each_entry_at_its_own_reset_in_rollouts_and_collectors(batched_env):
    actor = receding_horizon(_dalir(), env=batched_env)
    rollout = batched_env.rollout(30, actor, break_when_any_done=False)
    assert rollout[keys.IS_INIT][0].sum() == 6 and rollout[keys.IS_INIT][1].sum() == 3
    check_receding_horizon(rollout)
    collector = Collector(batched_env, actor, frames_per_batch=40, total_frames=40)
    check_receding_horizon(next(iter(collector)))
    collector.shutdown()  # closes the env


def test_reset_replays_the_same_actor_object(env):
    actor = receding_horizon(_dalir())

    def run(actor=actor):
        return env.rollout(16, actor, auto_reset=False, tensordict=env.reset(seed=5), break_when_any_done=False)[
            keys.ACTION
        ]

    first, second = run(), run()
    assert not torch.equal(first, second)  # its generator went on
    actor.reset()
    assert torch.equal(run(), first)
    actor.reset(seed=4)
    assert not torch.equal(run(), first)
    base = receding_horizon(actor.chunk_actor.policy)  # a base policy seeded this way draws from its own generator
    base.reset(seed=0)
    torch.manual_seed(1)
    first = run(base)
    base.reset()
    torch.manual_seed(2)
    assert torch.equal(run(base), first)


def test_decision_outputs_are_kept_by_default(env):
    rollout = env.rollout(3, receding_horizon(_dalir()))
    assert rollout[CANDIDATE_SCORES].shape == (3, 4) and rollout[CHOSEN_CANDIDATE].shape == (3,)
    assert CANDIDATE_SCORES not in env.rollout(3, receding_horizon(_dalir(), decision_keys=())).keys(True)


def test_horizon_settings_come_from_the_policy_and_others_are_refused():
    dalir = _dalir()
    actor = receding_horizon(dalir)
    assert (actor.obs_steps, actor.action_steps) == (2, 8) and actor.n_steps == 8
    assert receding_horizon(dalir, 2, 8).action_steps == 8
    with pytest.raises(ValueError, match="obs_steps=1, but the policy was trained with obs_steps=2"):
        receding_horizon(dalir, 1, 8)
    with pytest.raises(ValueError, match="action_steps=4"):
        receding_horizon(dalir.policy, action_steps=4)
    from tensordict.nn import TensorDictModule

    with pytest.raises(ValueError, match="pass obs_steps and action_steps"):
        receding_horizon(TensorDictModule(lambda cloud: cloud, [keys.POINT_CLOUD], [keys.ACTION_CHUNK]))


def test_an_env_the_policy_was_not_trained_for_is_refused_with_a_clear_message(env):
    dalir = _dalir()
    dense_env = make_env(SHORT_REACH, num_points=512, history=2)
    with pytest.raises(ValueError, match="trained on 40-point clouds; the observation has 512 points"):
        receding_horizon(dalir, env=dense_env)  # refused when wrapped for the env ...
    with pytest.raises(ValueError, match="40-point"):
        dense_env.rollout(2, receding_horizon(dalir))  # ... and at the first decision without it
    dense_env.close()
    hammer = _dalir()
    hammer.policy.task = "hammer"
    assert env_task(env) == "reach"
    with pytest.raises(ValueError, match="trained on task 'hammer'; the env runs 'reach'"):
        receding_horizon(hammer, env=env)
    door = _dalir()
    door.policy.state_dim = 28
    with pytest.raises(ValueError, match="agent_pos must be"):
        env.rollout(2, receding_horizon(door))
    no_history = make_env(SHORT_REACH, num_points=POINTS)
    with pytest.raises(ValueError, match="2-step history"):
        receding_horizon(dalir, env=no_history)
    no_history.close()
    batch_without_history = TensorDict(
        {keys.POINT_CLOUD: torch.rand(2, POINTS, 3), keys.AGENT_POS: torch.rand(2, 4)}, [2]
    )
    with pytest.raises(ValueError, match=r"batch size \[2\]: it must be \[\*batch, 2, N, 3\]"):
        dalir(batch_without_history)


def test_keys_come_from_arguments():
    torch.manual_seed(0)
    config = PolicyConfig(
        kind="fm", down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, euler_steps=2
    )
    policy = make_policy(config, 4, 4, in_keys=["cloud", ("robot", "pos")], out_keys=["plan_chunk"])
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, 4) * 2 - 1)
    obs = _observation()
    td = TensorDict(
        {
            "cloud": obs[keys.POINT_CLOUD],
            ("robot", "pos"): obs[keys.AGENT_POS],
            "start": torch.ones(3, 1, dtype=torch.bool),
        },
        [3],
    )
    actor = receding_horizon(policy, chunk_key="plan_chunk", action_key="move", init_key="start")
    out = actor(td.clone())
    assert out["move"].shape == (3, 4) and out["counter"].shape == (3, 1)
    dalir = RerankingActor(
        policy,
        *_parts()[1:],
        num_candidates=4,
        seed=3,
        in_keys=["cloud", ("robot", "pos")],
        out_keys=["plan_chunk", "scores", "choice"],
    )
    out = receding_horizon(dalir, chunk_key="plan_chunk", action_key="move", init_key="start")(td.clone())
    assert out["scores"].shape == (3, 4) and out["choice"].shape == (3,)
    default = RerankingActor(policy, *_parts()[1:], num_candidates=4, seed=3)
    expected = default(obs.clone())
    assert torch.equal(out["scores"], expected[CANDIDATE_SCORES]) and torch.equal(
        out["choice"], expected[CHOSEN_CANDIDATE]
    )
