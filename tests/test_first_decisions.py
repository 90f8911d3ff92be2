"""Reranking with a chunk critic alone (no world model) and at an episode's first decisions only."""

import dataclasses
import shutil

import pytest
import torch
from conftest import SHORT_REACH, untrained_reach_policy
from tensordict import TensorDict
from torchrl.envs import StepCounter

from torchrl_dalir import RerankingActor, keys, make_env, receding_horizon
from torchrl_dalir.modules import ChunkCritic, LatentEncoder, LatentWorldModel, TaskCompletionScorer
from torchrl_dalir.reranking import CANDIDATE_SCORES, CHOSEN_CANDIDATE, RerankingConfig, SelectionConfig

POINTS = 40


def _critic(policy):
    torch.manual_seed(1)
    critic = ChunkCritic(policy.encode(torch.rand(1, 2, POINTS, 3), torch.rand(1, 2, 4)).shape[-1], 4, 8, hidden=16)
    critic.action_normalizer.fit(torch.rand(20, 4) * 2 - 1)
    return critic


def _observation(batch=3):
    torch.manual_seed(2)
    return TensorDict(
        point_cloud=torch.rand(batch, 2, POINTS, 3), agent_pos=torch.rand(batch, 2, 4), batch_size=[batch]
    )


def test_a_critic_alone_reranks_as_it_does_beside_a_world_model_and_bad_combinations_are_refused():
    policy = untrained_reach_policy()
    critic = _critic(policy)
    encoder = LatentEncoder.from_policy(policy)
    parts = (
        encoder,
        LatentWorldModel(encoder.latent_dim, 4, 8, hidden=16, layers=1, heads=2),
        TaskCompletionScorer(encoder.latent_dim, hidden=16),
    )
    alone = RerankingActor(policy, critic=critic, num_candidates=6, seed=4)
    assert alone.selection == SelectionConfig(scorer="critic")  # the only scorer there is
    beside = RerankingActor(
        policy, *parts, critic=critic, num_candidates=6, seed=4, selection=SelectionConfig("argmax", "critic")
    )
    a, b = alone(_observation()), beside(_observation())
    assert torch.equal(a[keys.ACTION_CHUNK], b[keys.ACTION_CHUNK])
    assert torch.equal(a[CANDIDATE_SCORES], b[CANDIDATE_SCORES]) and torch.equal(
        a[CHOSEN_CANDIDATE], b[CHOSEN_CANDIDATE]
    )
    with pytest.raises(ValueError, match="needs the latent encoder, world model and scorer"):
        RerankingActor(policy)
    with pytest.raises(ValueError, match="together, or none"):
        RerankingActor(policy, parts[0], parts[1], critic=critic)
    with pytest.raises(ValueError, match="scores imagined latents"):
        RerankingActor(policy, critic=critic, selection=SelectionConfig("argmax", "state"))
    with pytest.raises(ValueError, match="decisions"):
        RerankingConfig(decisions=-1)


def _reach(step_counter: bool):
    env = make_env(dataclasses.replace(SHORT_REACH, max_steps=40), num_points=POINTS, history=2)
    return env.append_transform(StepCounter()) if step_counter else env


def _rollout(actor, step_counter=False, seed=0):
    env = _reach(step_counter)
    torch.manual_seed(seed)
    td = env.reset(seed=7)
    rollout = env.rollout(40, receding_horizon(actor), auto_reset=False, tensordict=td)
    env.close()
    return rollout


@pytest.mark.parametrize("step_counter", [False, True])
def test_only_the_first_decisions_are_reranked_and_the_rest_is_the_base_policy_own_sampling(step_counter):
    policy = untrained_reach_policy()
    critic = _critic(policy)
    first = 2 if step_counter else 1  # without a StepCounter, only the first decision can be told apart
    config = RerankingConfig(num_candidates=6, common_noise=True, decisions=first)
    rollout = _rollout(RerankingActor(policy, critic=critic, config=config, seed=4), step_counter)
    decisions = rollout[::8]  # 5 decisions of 8 steps
    scores = decisions[CANDIDATE_SCORES]
    assert scores[:first].isfinite().all() and scores[first:].isnan().all()
    assert (decisions[CHOSEN_CANDIDATE][first:] == 0).all()
    # keeping the clean candidate at the reranked decisions replays the base policy, action for action
    keep = dataclasses.replace(config, selection=SelectionConfig("margin", "critic", margin=1.0))
    kept = _rollout(RerankingActor(policy, critic=critic, config=keep, seed=4), step_counter)
    base = _rollout(policy, step_counter)
    assert torch.equal(kept[keys.ACTION], base[keys.ACTION])
    assert decisions[CHOSEN_CANDIDATE][0] != 0  # this critic switches at the first decision ...
    assert not torch.equal(rollout[keys.ACTION][:8], base[keys.ACTION][:8])  # ... which changes the episode


def test_a_batch_reranked_in_part_replays_the_base_policy_batch_call_when_it_keeps_the_clean_candidates():
    policy = untrained_reach_policy()
    keep = SelectionConfig("margin", "critic", margin=1.0)
    config = RerankingConfig(num_candidates=4, common_noise=True, decisions=1, selection=keep)
    dalir = RerankingActor(policy, critic=_critic(policy), config=config, seed=2)
    observation = _observation().set(keys.STEP_COUNT, torch.tensor([[0], [16], [0]]))  # rows 0 and 2 rerank
    torch.manual_seed(5)
    base = policy.sample(policy.encode(observation["point_cloud"], observation["agent_pos"]))
    torch.manual_seed(5)
    decision = dalir(observation)
    assert torch.equal(decision[keys.ACTION_CHUNK], base)  # one call of the base policy for the whole batch
    scores = decision[CANDIDATE_SCORES]
    assert scores[[0, 2]].isfinite().all() and scores[1].isnan().all()
    after_actor = torch.randn(1)
    torch.manual_seed(5)
    policy.sample(policy.encode(observation["point_cloud"], observation["agent_pos"]))
    assert torch.equal(after_actor, torch.randn(1))  # the global stream moved as by one base-policy call


def test_counting_decisions_past_the_first_needs_a_step_counter():
    policy = untrained_reach_policy()
    config = RerankingConfig(num_candidates=4, decisions=2)
    with pytest.raises(KeyError, match="StepCounter"):
        _rollout(RerankingActor(policy, critic=_critic(policy), config=config), step_counter=False)


def _saved_critic(policy, path):
    from torchrl_dalir.checkpoints import save_chunk_critic

    cloud = torch.rand(1, policy.obs_steps, policy.num_points, 3)
    cond = policy.encode(cloud, torch.rand(1, policy.obs_steps, policy.state_dim))
    critic = ChunkCritic(cond.shape[-1], policy.action_dim, policy.action_steps, hidden=16)
    critic.action_normalizer.fit(torch.rand(20, policy.action_dim) * 2 - 1)
    save_chunk_critic(path, critic, policy, {})
    return path


def test_evaluation_and_calibration_take_a_critic_and_rerank_the_first_decisions_only(trained_world_model, tmp_path):
    from torchrl_dalir.checkpoints import load_policy, store_selection
    from torchrl_dalir.evaluation.calibration import GRIDS, calibrate
    from torchrl_dalir.evaluation.compare import evaluate_checkpoints
    from torchrl_dalir.pipeline.config import PipelineConfig

    _, world_model, policy_path = trained_world_model
    critic = _saved_critic(load_policy(policy_path), tmp_path / "critic.pt")
    reranking = RerankingConfig(num_candidates=3, decisions=2, common_noise=True)  # 2 > 1: a StepCounter counts
    common = dict(episodes=1, seed=1, progress=False, reranking=reranking)
    with pytest.raises(ValueError, match="or a critic"):
        evaluate_checkpoints(policy_path, None, methods=["dalir"], **common)
    with pytest.raises(ValueError, match="needs a world_model_path"):
        evaluate_checkpoints(policy_path, None, methods=["argmax"], critic=critic, **common)
    rows = evaluate_checkpoints(policy_path, None, critic=critic, methods=["base", "dalir", "random"], **common)
    assert rows["DALI-R"]["selection"] == "argmax(critic)"  # no world model: the critic alone
    for method in ("DALI-R", "random candidate"):
        assert all(r["details"]["decisions"] == min(2, -(-r["steps"] // 8)) for r in rows[method]["records"])
    with pytest.raises(ValueError, match="pass critic="):
        calibrate(policy_path, world_model, grid=GRIDS["critic"], write=False, **common)
    record = calibrate(policy_path, world_model, grid=GRIDS["critic"], write=False, critic=critic, **common)
    assert [e["name"] for e in record["entries"]] == ["margin(ensemble, k=1, margin=1)", "argmax(critic)"]
    calibrated = tmp_path / "world_model.pt"  # a world model whose stored rule is the critic's
    shutil.copy(world_model, calibrated)
    store_selection(calibrated, SelectionConfig("argmax", "critic"), {"chosen": "argmax(critic)"})
    with pytest.raises(ValueError, match="stores the rule argmax\\(critic\\)"):
        evaluate_checkpoints(policy_path, calibrated, methods=["base", "dalir"], **common)
    with pytest.raises(ValueError, match="branched_episodes >= 2"):
        PipelineConfig(task="reach", calibration_grid="critic")
    assert PipelineConfig(task="reach", rerank_decisions=1).reranking().decisions == 1
