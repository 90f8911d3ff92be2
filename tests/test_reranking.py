import dataclasses

import numpy as np
import pytest
import torch
from conftest import SHORT_REACH
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import SerialEnv

from torchrl_dalir import RerankingActor, keys, make_env, receding_horizon
from torchrl_dalir.branching.candidate_outcomes import (
    candidate_outcomes,
    success_by_score_rank,
    summarize_candidate_outcomes,
)
from torchrl_dalir.evaluation.plots import plot_candidate_outcomes
from torchrl_dalir.modules import LatentEncoder, LatentWorldModel, PolicyConfig, TaskCompletionScorer, make_policy
from torchrl_dalir.reranking import (
    CANDIDATE_SCORES,
    CHOSEN_CANDIDATE,
    GaussianObservationNoise,
    PointDropout,
    RandomCandidateActor,
)

TINY = dict(down_dims=[16, 32, 64], point_hidden=[16, 32, 64], train_timesteps=20, ddim_steps=2, euler_steps=2)


def _parts(kind="fm", action_dim=4, seed=0, **policy_fields):
    """A tiny untrained policy (``policy_fields``: e.g. its ``task`` and ``num_points``), latent encoder,
    world model and scorer."""
    torch.manual_seed(seed)
    policy = make_policy(PolicyConfig(kind=kind, **TINY), action_dim=action_dim, state_dim=4, **policy_fields)
    policy.fit_normalizers(torch.rand(50, 3), torch.rand(50, 4), torch.rand(50, action_dim) * 2 - 1)
    encoder = LatentEncoder.from_policy(policy)
    world_model = LatentWorldModel(encoder.latent_dim, action_dim, 8, hidden=32, layers=1, heads=2)
    torch.nn.init.normal_(world_model.out[-1].weight, std=0.1)  # not the zero ("no change") init
    scorer = TaskCompletionScorer(encoder.latent_dim, hidden=32)
    return policy, encoder, world_model, scorer


def _observation(batch=3, points=40):
    g = torch.Generator().manual_seed(5)
    return TensorDict(
        {
            keys.POINT_CLOUD: torch.rand(batch, 2, points, 3, generator=g),
            keys.AGENT_POS: torch.rand(batch, 2, 4, generator=g),
        },
        [batch],
    )


def test_point_dropout_module_keeps_shape_and_drops_about_p():
    cloud = torch.rand(200, 64, 3)
    dropped = PointDropout(0.3, seed=0)(TensorDict({keys.POINT_CLOUD: cloud.clone()}, [200]))[keys.POINT_CLOUD]
    assert dropped.shape == cloud.shape
    changed = (dropped != cloud).any(-1).float().mean().item()
    assert changed == pytest.approx(0.3, abs=0.03)


def test_shared_feature_dropout_equals_per_candidate_encoding():
    policy, *_ = _parts()
    obs = _observation(batch=2)
    dropout = PointDropout(0.3)
    k = 6
    cond = dropout.conditions(policy, obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], k, torch.Generator().manual_seed(1))
    keep = dropout.keep_masks((2, k, 2, 40), torch.Generator().manual_seed(1))
    keep[:, 0] = True
    for b in range(2):
        for c in range(k):
            # re-encode each dropped cloud (dropped points replaced by a kept one: same point set)
            cloud = obs[keys.POINT_CLOUD][b].clone()
            for frame in range(2):
                kept = cloud[frame][keep[b, c, frame]]
                cloud[frame] = torch.cat([kept, kept[:1].expand(40 - len(kept), 3)])
            expected = policy.encode(cloud[None], obs[keys.AGENT_POS][b][None])[0]
            torch.testing.assert_close(cond[b, c], expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(cond[:, 0], policy.encode(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]))


def test_gaussian_observation_noise_jitters_every_candidate_but_the_clean_one():
    policy, *_ = _parts()
    obs = _observation(batch=2)
    clean = policy.encode(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS])
    cond = GaussianObservationNoise(0.05).conditions(
        policy, obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], 4, torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(cond[:, 0], clean)
    assert all(not torch.allclose(cond[:, k], clean) for k in range(1, 4))
    still = GaussianObservationNoise(0.0).conditions(
        policy, obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], 4, torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(still, clean[:, None].expand(-1, 4, -1))


@pytest.mark.parametrize("candidates", [PointDropout(0.2), GaussianObservationNoise(0.01)])
def test_actor_picks_the_best_scored_candidate_and_includes_the_clean_one(candidates):
    policy, encoder, world_model, scorer = _parts()
    actor = RerankingActor(policy, encoder, world_model, scorer, num_candidates=8, candidates=candidates, seed=3)
    obs = _observation()
    out = actor(obs.clone())
    scores, chosen = out[CANDIDATE_SCORES], out[CHOSEN_CANDIDATE]
    assert scores.shape == (3, 8) and out[keys.ACTION_CHUNK].shape == (3, 16, 4)
    assert torch.equal(chosen, scores.argmax(-1))
    # replay the decision: same generator stream -> same candidates
    g = torch.Generator().manual_seed(3)
    cond = candidates.conditions(policy, obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], 8, g)
    torch.testing.assert_close(cond[:, 0], policy.encode(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]))  # clean candidate
    chunks = policy.sample(cond, g)
    torch.testing.assert_close(actor.score(obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], chunks), scores)
    torch.testing.assert_close(out[keys.ACTION_CHUNK], chunks[torch.arange(3), chosen])


def test_score_imagines_the_executed_actions_from_the_current_frame():
    policy, encoder, world_model, scorer = _parts()
    actor = RerankingActor(policy, encoder, world_model, scorer, num_candidates=5)
    obs = _observation()
    cloud, agent_pos = obs[keys.POINT_CLOUD], obs[keys.AGENT_POS]
    chunks = torch.rand(3, 5, 16, 4) * 2 - 1
    latent = encoder(cloud[:, -1], agent_pos[:, -1])[:, None].expand(-1, 5, -1)
    expected = torch.sigmoid(scorer(world_model.imagine(latent, chunks[:, :, 1:9])))
    torch.testing.assert_close(actor.score(cloud, agent_pos, chunks), expected)
    unexecuted = chunks.clone()
    unexecuted[:, :, 0] += 1
    unexecuted[:, :, 9:] += 1
    assert torch.equal(actor.score(cloud, agent_pos, unexecuted), actor.score(cloud, agent_pos, chunks))
    older = cloud.clone()
    older[:, 0] = torch.rand_like(older[:, 0])  # only the current frame is imagined from
    assert torch.equal(actor.score(older, agent_pos, chunks), actor.score(cloud, agent_pos, chunks))


def test_random_candidate_control_executes_one_of_dalirs_own_candidates_at_random():
    parts = _parts()
    obs = _observation(batch=64)
    control = RandomCandidateActor(*parts, num_candidates=8, seed=3)(obs.clone())
    chosen = control[CHOSEN_CANDIDATE]
    # the same candidates as DALI-R with the same seed, replayed from the same generator stream
    g = torch.Generator().manual_seed(3)
    chunks = parts[0].sample(
        PointDropout(0.2).conditions(parts[0], obs[keys.POINT_CLOUD], obs[keys.AGENT_POS], 8, g), g
    )
    torch.testing.assert_close(control[keys.ACTION_CHUNK], chunks[torch.arange(64), chosen])
    assert torch.equal(chosen, control[CANDIDATE_SCORES].argmax(-1))  # the random draws made the choice
    dalir = RerankingActor(*parts, num_candidates=8, seed=3)(obs.clone())
    assert not torch.equal(chosen, dalir[CHOSEN_CANDIDATE])
    assert len(chosen.unique()) >= 6  # 64 uniform picks among 8 hit nearly every index


def test_actor_is_deterministic_under_a_seed():
    parts = _parts()
    a = RerankingActor(*parts, num_candidates=4, seed=7)(_observation())
    b = RerankingActor(*parts, num_candidates=4, seed=7)(_observation())
    c = RerankingActor(*parts, num_candidates=4, seed=8)(_observation())
    assert (a == b).all()
    assert not torch.equal(a[keys.ACTION_CHUNK], c[keys.ACTION_CHUNK])


def test_actor_rejects_bad_inputs_and_mismatched_models():
    policy, encoder, world_model, scorer = _parts()
    actor = RerankingActor(policy, encoder, world_model, scorer, num_candidates=2)
    with pytest.raises(ValueError, match="point_cloud"):
        actor(TensorDict({keys.POINT_CLOUD: torch.rand(3, 40, 3), keys.AGENT_POS: torch.rand(3, 2, 4)}, [3]))
    bad = _observation()
    bad[keys.AGENT_POS][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        actor(bad)
    other_world_model = LatentWorldModel(encoder.latent_dim, action_dim=6, hidden=32, layers=1, heads=2)
    with pytest.raises(ValueError, match="6-D actions"):
        RerankingActor(policy, encoder, other_world_model, scorer)
    with pytest.raises(ValueError, match="imagines 4 actions; the policy executes 8"):
        RerankingActor(
            policy, encoder, LatentWorldModel(encoder.latent_dim, 4, 4, hidden=32, layers=1, heads=2), scorer
        )
    with pytest.raises(ValueError, match="latent size"):
        RerankingActor(
            policy, encoder, LatentWorldModel(encoder.latent_dim + 1, 4, 8, hidden=32, layers=1, heads=2), scorer
        )
    with pytest.raises(ValueError, match="at least 1"):
        RerankingActor(policy, encoder, world_model, scorer, num_candidates=0)


def test_actor_runs_8_of_16_in_rollout_and_collector():
    decision_keys = [CANDIDATE_SCORES, CHOSEN_CANDIDATE]
    actor = receding_horizon(
        RerankingActor(*_parts(), num_candidates=4), obs_steps=2, action_steps=8, decision_keys=decision_keys
    )
    env = SerialEnv(1, lambda: make_env(SHORT_REACH, seed=0, num_points=40, history=2))
    rollout = env.rollout(16, actor, break_when_any_done=False)
    assert rollout[keys.ACTION].shape == (1, 16, 4)
    # every step carries the scores of the decision its action came from: two decisions of 8 steps
    scores, chosen = rollout[CANDIDATE_SCORES][0], rollout[CHOSEN_CANDIDATE][0]
    assert scores.shape == (16, 4) and chosen.shape == (16,)
    for block in (slice(0, 8), slice(8, 16)):
        assert (scores[block] == scores[block][:1]).all() and (chosen[block] == chosen[block][0]).all()
    assert not torch.equal(scores[0], scores[8])
    assert torch.equal(chosen, scores.argmax(-1))
    collector = Collector(env, actor, frames_per_batch=8, total_frames=8)
    assert next(iter(collector))[keys.ACTION].shape[-1] == 4
    collector.shutdown()


def test_candidate_outcomes_try_every_candidate_from_the_same_state():
    from torchrl_dalir.envs.gym_env import PointCloudObservation, make_simulator
    from torchrl_dalir.seeds import eval_episode_seed

    parts = _parts(task="reach", num_points=40)
    records = candidate_outcomes(
        RerankingActor(*parts, num_candidates=4, seed=3), SHORT_REACH, episodes=1, decisions=2, progress=False
    )
    assert [r["decision"] for r in records] == [0, 1]
    first = records[0]
    assert len(first["imagined_score"]) == len(first["real_score"]) == len(first["success"]) == 4
    assert first["chosen"] == max(range(4), key=first["imagined_score"].__getitem__)
    # Each candidate's real outcome equals running its actions in a fresh episode: the saved state
    # is restored exactly between candidates.
    actor = RerankingActor(*parts, num_candidates=4, seed=3)
    env = PointCloudObservation(make_simulator(SHORT_REACH), SHORT_REACH, num_points=40)
    observation, _ = env.reset(seed=eval_episode_seed(0, 0))
    cloud = torch.as_tensor(observation[keys.POINT_CLOUD]).expand(1, 2, -1, -1)
    agent_pos = torch.as_tensor(observation[keys.AGENT_POS]).expand(1, 2, -1)
    chunks, scores = actor.propose(cloud, agent_pos)
    assert torch.allclose(scores[0], torch.tensor(first["imagined_score"]))
    executed = chunks[0, :, 1:9]
    assert torch.allclose(torch.tensor(first["action_distance"]), (executed - executed[0]).flatten(1).norm(dim=-1))
    for k in (0, 1, 3):
        env.reset(seed=eval_episode_seed(0, 0))
        for action in chunks[0, k, 1:9].numpy():
            observation, *_ = env.step(action)
        real = parts[1](torch.as_tensor(observation[keys.POINT_CLOUD]), torch.as_tensor(observation[keys.AGENT_POS]))
        assert torch.isclose(torch.sigmoid(parts[3](real)), torch.tensor(first["real_score"][k]), atol=1e-6)
    env.close()
    summary = summarize_candidate_outcomes(records)
    assert summary["decisions"] == 2


def test_candidate_outcomes_follow_through_every_stride_th_decision():
    parts = _parts(task="reach", num_points=40)
    task = dataclasses.replace(SHORT_REACH, max_steps=40)  # 5 decisions

    def run():
        actor = RerankingActor(*parts, num_candidates=3, seed=4)
        return candidate_outcomes(actor, task, episodes=1, decisions=5, stride=2, follow_through=True, progress=False)

    records = run()
    assert [r["decision"] for r in records] == [0, 2, 4]
    assert all(len(record["final_success"]) == 3 for record in records)
    assert run() == records  # seeded: the follow-through rollouts replay exactly
    actor = RerankingActor(*parts, num_candidates=3, seed=4)
    every = candidate_outcomes(
        actor, task, episodes=1, decisions=5, stride=2, follow_through=True, progress=False, render_every_step=True
    )
    assert every == records  # rendering only the clouds that are read changes nothing
    assert (
        "final_success"
        not in candidate_outcomes(
            RerankingActor(*parts, num_candidates=3, seed=4), task, episodes=1, decisions=1, progress=False
        )[0]
    )


def test_follow_through_summary_exact_values(tmp_path):
    record = {
        "imagined_score": [0.9, 0.1, 0.5, 0.2],
        "real_score": [0.3, 0.2, 0.1, 0.4],
        "success": [False] * 4,
        "chosen": 0,
        "rank_correlation": 0.0,
        "imagination_error": 1.0,
        "real_spread": 1.0,
        "action_distance": [0.0, 1.0, 2.0, 3.0],
    }
    split = {**record, "final_success": [True, False, False, True]}
    none = {**record, "final_success": [False, False, False, False]}
    summary = summarize_candidate_outcomes([split, none])
    assert summary["mean_pick_percentile"] == pytest.approx(2 / 3)  # real 0.3 beats 0.2 and 0.1, not 0.4
    assert summary["pick_real_score_gain"] == pytest.approx(0.05)  # 0.3 against the mean 0.25
    assert summary["final_success_clean"] == 0.5 and summary["final_success_pick"] == 0.5
    assert summary["final_success_average_candidate"] == 0.25
    assert summary["final_success_real_best"] == 0.5  # real-score argmax: candidate 3, then 3 again
    assert summary["decisions_split_by_final_success"] == 1
    # successes (0.9, 0.2) against failures (0.1, 0.5): 3 of 4 pairs ordered right
    assert summary["imagined_score_auc_there"] == 0.75
    assert summary["real_score_auc_there"] == 1.0  # (0.3, 0.4) against (0.2, 0.1)
    assert "final_success_pick" not in summarize_candidate_outcomes([record])
    # one candidate per quarter here, lowest score first: 0.1, 0.2, 0.5, 0.9
    assert summary["final_success_by_imagined_score_quarter"] == [0.0, 0.5, 0.0, 0.5]
    assert success_by_score_rank([split, none], bins=2) == [0.25, 0.25]
    # perturbed candidates: |score - median 0.2| = (0.1, 0.3, 0.0) against distances (1, 2, 3)
    assert summary["extreme_score_distance_correlation"] == pytest.approx(-0.5)
    # tied scores share their rank positions: equal scores spread each candidate over both halves
    tied = {**split, "imagined_score": [0.5, 0.5, 0.5, 0.5]}
    assert success_by_score_rank([tied], bins=2) == [0.5, 0.5]
    # 0.1 takes the lowest position; the three tied at 0.5 share positions 1-3 (1 in the low half, 2 in the high)
    assert success_by_score_rank([{**tied, "imagined_score": [0.5, 0.1, 0.5, 0.5]}], bins=2) == [
        pytest.approx(1 / 3),
        pytest.approx(2 / 3),
    ]
    with pytest.raises(ValueError, match="fewer than bins=4"):
        success_by_score_rank([{**split, "imagined_score": [0.1, 0.2, 0.3], "final_success": [True] * 3}])
    # saturated scores vary but their distance from the median does not: no correlation to take, whatever the order
    saturated = {**record, "imagined_score": [0.5, 0.0, 0.0, 1.0, 1.0], "action_distance": [0.0, 1.0, 2.0, 3.0, 4.0]}
    assert np.isnan(summarize_candidate_outcomes([saturated])["extreme_score_distance_correlation"])
    for decisions in ([saturated, record], [record, saturated]):  # skipped, not a NaN in the median
        assert summarize_candidate_outcomes(decisions)["extreme_score_distance_correlation"] == pytest.approx(-0.5)
    assert (
        plot_candidate_outcomes([split, none], tmp_path / "outcomes.png").stat().st_size > 0
    )  # with the success-by-quarter panel


def test_dropout_policy_samples_a_dropout_candidate_and_leaves_the_observation_clean():
    from torchrl_dalir.reranking.candidates import DropoutPolicy

    policy, *_ = _parts()
    obs = _observation(batch=2)
    clean = obs[keys.POINT_CLOUD].clone()
    explorer = DropoutPolicy(policy, 0.3, seed=7)
    chunk = explorer(obs.clone())[keys.ACTION_CHUNK]
    generator = torch.Generator().manual_seed(7)  # the masks, then the noise, from the seed's one stream
    keep = PointDropout(0.3).keep_masks((2, 2, 40), generator)
    assert torch.equal(chunk, policy.sample(policy.encode(clean, obs[keys.AGENT_POS], keep), generator))
    generator = torch.Generator().manual_seed(7)
    PointDropout(0.3).keep_masks((2, 2, 40), generator)
    assert not torch.equal(
        chunk, policy.sample(policy.encode(clean, obs[keys.AGENT_POS]), generator)
    )  # the mask mattered
    torch.manual_seed(3)  # torch's global generator plays no part: reset replays
    assert not torch.equal(explorer(obs.clone())[keys.ACTION_CHUNK], chunk)
    explorer.reset()
    assert torch.equal(explorer(obs.clone())[keys.ACTION_CHUNK], chunk)
    out = DropoutPolicy(policy, 0.3)(obs)
    assert torch.equal(out[keys.POINT_CLOUD], clean)
